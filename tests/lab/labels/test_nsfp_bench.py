"""lab/labels/nsfp_bench.py (lab/tools/benchmark_nsfp.py): seconds per pair and the bar against hand calculations,
the tool commands, which sections a rerun keeps or redoes, and one tiny speed section."""
import dataclasses
import json
import os
import sys

import pytest

from ff3d_tf.labels import nsfp
from lab.labels import nsfp_bench

SPEED = {"points": 4096, "point_bucket": 4096,
         "distance_transform": {"timed_steps": 10, "seconds_per_step": 0.5, "grid_build_s_both_clouds": 0.75,
                                "first_call_s_with_compilation": 9.0},
         "exact_nearest_neighbours": {"timed_steps": 3, "seconds_per_step": 2.0, "grid_build_s_both_clouds": 0.0,
                                      "first_call_s_with_compilation": 5.0},
         "exact_over_distance_transform_per_step": 4.0}


def test_seconds_per_pair_against_hand_calculation():
    found = nsfp_bench.seconds_per_pair(SPEED, max_iterations=5000, av2_sample_steps=700)
    # distance transform: 0.75 + 0.5 x 5000 = 2500.75, 0.75 + 0.5 x 700 = 350.75; exact: no grid, 2 x 5000, 2 x 700
    assert found["distance_transform"] == {"max_iterations": 2500.75, "av2_sample_steps": 350.75}
    assert found["exact_nearest_neighbours"] == {"max_iterations": 10000.0, "av2_sample_steps": 1400.0}
    assert "timed over 10 steps (distance transform) and 3 steps (exact" in found["how"]
    assert "benchmark cloud of 4096 points" in found["how"]
    without_av2 = nsfp_bench.seconds_per_pair(SPEED, max_iterations=100, av2_sample_steps=None)
    assert without_av2["distance_transform"] == {"max_iterations": 50.75}


def test_meets_bar():
    assert nsfp_bench.meets_bar({"three_way/mean_epe_m": 0.08, "bucketed/mean_dynamic_norm_epe": 0.6})  # at the bar
    assert not nsfp_bench.meets_bar({"three_way/mean_epe_m": 0.05, "bucketed/mean_dynamic_norm_epe": 0.61})
    with pytest.raises(KeyError, match="bucketed/mean_dynamic_norm_epe"):
        nsfp_bench.meets_bar({"three_way/mean_epe_m": 0.05})


def test_av2_commands():
    write, label = nsfp_bench.av2_commands("LOG", ["--set", "nsfp.fit_every=8"], "/repo/tools", "R", "P")
    assert write == [sys.executable, "/repo/tools/write_pair_records.py", "--source", "av2", "--input", "LOG",
                     "--out_dir", "R"]
    assert label == [sys.executable, "/repo/tools/pseudo_label.py", "--input", "R", "--out_dir", "P", "--set",
                     "nsfp.fit_every=8"]


def _fakes(monkeypatch, calls):
    def speed(points, dt_steps, exact_steps, options, log):
        calls.append(("speed", points, dt_steps, exact_steps, options.max_iterations))
        return SPEED

    def av2_sample(log_dir, extra_args, tools_dir, log):
        calls.append(("av2", log_dir, list(extra_args), tools_dir))
        return {"args": list(extra_args), "counts": {"nsfp_iterations": 700}}

    monkeypatch.setattr(nsfp_bench, "speed", speed)
    monkeypatch.setattr(nsfp_bench, "av2_sample", av2_sample)


def test_rerun_keeps_sections_and_redoes_av2_of_other_flags(tmp_path, monkeypatch):
    calls = []
    _fakes(monkeypatch, calls)
    out = str(tmp_path / "sub" / "nsfp.json")
    args = dict(points=4096, dt_steps=10, exact_steps=3, av2_log="LOG", tools_dir="TOOLS", log=lambda line: None)
    first = nsfp_bench.run(out, av2_args=[], skip_av2=False, fresh=False, **args)
    cap = nsfp.MEASURED_FIT_OPTIONS.max_iterations
    assert calls == [("speed", 4096, 10, 3, cap), ("av2", "LOG", [], "TOOLS")]
    assert first["options"]["max_iterations"] == cap and "model_name" in first["machine"]
    assert first["seconds_per_pair"]["exact_nearest_neighbours"] == {"max_iterations": 2.0 * cap,
                                                                     "av2_sample_steps": 1400.0}
    with open(out) as f:
        assert json.load(f) == json.loads(json.dumps(first)) and not os.path.exists(out + ".partial")

    calls.clear()  # same flags: nothing redone
    again = nsfp_bench.run(out, av2_args=[], skip_av2=False, fresh=False, **args)
    assert again == json.loads(json.dumps(first)) and calls == []
    nsfp_bench.run(out, av2_args=["--set", "nsfp.fit_every=8"], skip_av2=False, fresh=False, **args)
    assert calls == [("av2", "LOG", ["--set", "nsfp.fit_every=8"], "TOOLS")]  # other flags: av2 alone redone
    calls.clear()
    nsfp_bench.run(out, av2_args=[], skip_av2=True, fresh=True, **args)
    assert calls == [("speed", 4096, 10, 3, cap)]  # fresh: speed redone; skip_av2: no av2
    with open(out) as f:
        assert "av2_sample" not in json.load(f)


def test_tiny_speed_section():
    lines = []
    small_fit = dataclasses.replace(nsfp.MEASURED_FIT_OPTIONS, hidden_layers=2, hidden_units=16)
    found = nsfp_bench.speed(600, dt_steps=2, exact_steps=1, options=small_fit, log=lines.append)
    assert (found["points"], found["point_bucket"]) == (600, 1024)
    assert found["distance_transform"]["timed_steps"] == 2 and found["exact_nearest_neighbours"]["timed_steps"] == 1
    assert found["distance_transform"]["grid_build_s_both_clouds"] > 0  # exact neighbours build no grid
    assert found["exact_nearest_neighbours"]["grid_build_s_both_clouds"] == 0
    assert found["exact_over_distance_transform_per_step"] == pytest.approx(
        found["exact_nearest_neighbours"]["seconds_per_step"] / found["distance_transform"]["seconds_per_step"])
    assert [line.split(":")[0] for line in lines] == ["distance_transform", "exact_nearest_neighbours"]
