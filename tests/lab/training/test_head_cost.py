"""lab/training/head_cost.py (lab/tools/benchmark_head_cost.py): the variants, the figures over the rounds, the ratios
and the generated note against hand calculations, and one tiny run end to end in child processes (a failed child
recorded beside the others)."""
import json

import pytest

from ff3d_tf.config import TINY_OVERRIDES
from lab import bench
from lab.training import head_cost

FAILING_CHILD = "lab.children:no_such_function"  # fails in its child at once: a recorded error


def test_variants():
    assert head_cost.variants((4, 2)) == {"paper": ("model.head=paper",),
                                          "gru4": ("model.head=gru", "model.gru_iterations=4"),
                                          "gru2": ("model.head=gru", "model.gru_iterations=2")}
    for bad in ((), (2, 2)):
        with pytest.raises(ValueError, match="distinct"):
            head_cost.variants(bad)


def _forward(ms, peak, call_peak, above):
    return {"forward_ms": ms, "peak_rss_gb": peak, "call_peak_rss_gb": call_peak, "call_peak_above_before_gb": above,
            "padded_points": 1024, "mode": "hybrid"}


def _train(ms, peak):
    return {"step_ms": ms, "peak_rss_gb": peak, "padded_points": 1024, "mode": "xla"}


def test_summary_pools_the_rounds_and_keeps_failures():
    rounds = [_forward([3.0, 1.0], 1.0, 0.9, 0.2), {"error": "boom"}, _forward([2.0, 5.0], 1.5, 0.8, 0.4)]
    out = head_cost.summary(rounds, "forward_ms", head_cost.FORWARD_FIGURES)
    # calls 3, 1, 2, 5 -> the upper middle, 3; peaks: the largest; the transient: the upper middle of 0.2, 0.4
    assert out == {"median_ms": 3.0, "peak_rss_gb": 1.5, "call_peak_rss_gb": 0.9, "call_peak_above_before_gb": 0.4,
                   "padded_points": 1024, "mode": "hybrid", "rounds": 2, "failed_rounds": 1}
    assert head_cost.summary([{"error": "boom"}], "step_ms", head_cost.TRAIN_FIGURES) == {"error": "boom",
                                                                                           "failed_rounds": 1}


def _readings():
    """Paper, gru4, gru2 at 100 and 400 points and their training steps; gru2's forward at 400 points failed."""
    forward = {"100": {"paper": [_forward([10.0], 1.0, 0.9, 0.1)], "gru4": [_forward([15.0], 1.1, 1.0, 0.2)],
                       "gru2": [_forward([12.0], 1.05, 0.95, 0.15)]},
               "400": {"paper": [_forward([20.0], 2.0, 1.8, 0.5)], "gru4": [_forward([50.0], 3.0, 2.7, 1.5)],
                       "gru2": [{"error": "gru2 forward at 400 points: its process ended with exit 1"}]}}
    train = {"paper": [_train([100.0], 2.0)], "gru4": [_train([300.0], 2.5)], "gru2": [_train([200.0], 2.2)]}
    return {"forward": forward, "train": train}


def test_report_against_hand_calculation():
    out = head_cost.report(_readings(), ["paper", "gru4", "gru2"], [100, 400], 100)
    assert out["forward"]["gru4"]["400"]["median_ms"] == 50.0 and "error" in out["forward"]["gru2"]["400"]
    gru4 = out["ratios"]["gru4"]
    assert gru4["forward"]["100"] == pytest.approx({"median_ms": 1.5, "peak_rss_gb": 1.1, "call_peak_rss_gb": 1.0 / 0.9,
                                                    "call_peak_above_before_gb": 2.0, "added_time_share": 1 / 3})
    assert gru4["forward"]["400"]["median_ms"] == 2.5 and gru4["forward"]["400"]["added_time_share"] == 0.6
    assert gru4["train_step"] == pytest.approx({"median_ms": 3.0, "peak_rss_gb": 1.25, "added_time_share": 2 / 3})
    assert out["ratios"]["gru2"]["forward"]["400"] is None  # a failed child: no ratio
    between = out["ratios_between"]["gru2/gru4"]
    assert between["forward"]["100"]["median_ms"] == pytest.approx(0.8) and between["forward"]["400"] is None
    assert between["train_step"]["median_ms"] == pytest.approx(2 / 3)
    note = out["note"]
    # gru4's head adds 60% of its forward at 400 points (> DOMINANT_SHARE), 33% at 100; gru2 dominates nowhere
    assert "gru4 over paper: forward x1.50 / 2.50 at 100 / 400 points" in note
    assert "dominates gru4's forward (more than half its time) at 400 points." in note
    assert "does not dominate gru2's forward" in note and "training step at 100 points x3.00, peak x1.25" in note
    assert "gru2/gru4: forward x0.80 / n/a" in note and "gru2 forward at 400 points" in note


def test_run_checks_its_arguments_before_any_child():
    for kwargs, match in (({"points": []}, "points"), ({"points": [0]}, "points"), ({"runs": 0}, "runs"),
                          ({"train_child": None}, "train_child")):
        args = {"config": "", "overrides": list(TINY_OVERRIDES), "points": [300], "train_points": 300,
                "train_child": FAILING_CHILD, **kwargs}
        with pytest.raises(ValueError, match=match):
            head_cost.run(**args, log=lambda line: None)


def test_tiny_run_end_to_end_records_a_failed_child(tmp_path):
    saved = []
    out = head_cost.run("", list(TINY_OVERRIDES), [300], 300, FAILING_CHILD, gru_iterations=(2,), runs=1, warmup=1,
                        steps=1, cores=1, command="test", log=lambda line: None, save=saved.append)
    path = str(tmp_path / "head_cost.json")
    bench.write_json(path, out)
    with open(path) as f:
        result = json.load(f)
    assert len(saved) == 4  # after every child: two forwards, two training steps
    for key in ("command", "cpu", "how", "variants", "modes", "points", "train_points", "readings", "forward",
                "train_step", "ratios", "ratios_between", "note"):
        assert key in result, key
    assert result["cpu"]["cpu_count"] >= 1 and result["variants"] == {"paper": ["model.head=paper"],
                                                                      "gru2": ["model.head=gru",
                                                                               "model.gru_iterations=2"]}
    paper, gru2 = result["forward"]["paper"]["300"], result["forward"]["gru2"]["300"]
    for row in (paper, gru2):
        assert row["median_ms"] > 0 and row["peak_rss_gb"] >= row["call_peak_rss_gb"] > 0 and row["rounds"] == 1
    child = result["readings"]["forward"]["300"]["gru2"][0]
    assert child["head"] == "gru" and child["gru_iterations"] == 2 and child["placement"]["cpus"] == [0]
    assert result["params"]["gru2"] != result["params"]["paper"]
    ratio = result["ratios"]["gru2"]["forward"]["300"]
    assert ratio["median_ms"] == gru2["median_ms"] / paper["median_ms"]
    assert ratio["peak_rss_gb"] == gru2["peak_rss_gb"] / paper["peak_rss_gb"]
    assert ratio["added_time_share"] == 1 - paper["median_ms"] / gru2["median_ms"]
    # the training children failed: recorded, no ratio, named in the note; the forward figures stand
    assert "no_such_function" in result["train_step"]["gru2"]["error"]
    assert result["ratios"]["gru2"]["train_step"] is None
    assert f"forward x{ratio['median_ms']:.2f} at 300 points" in result["note"]
    assert "paper training step, gru2 training step" in result["note"]
