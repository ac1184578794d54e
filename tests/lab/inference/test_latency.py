"""lab/inference/latency.py (lab/tools/benchmark_latency.py): precision names, the variants, the call summaries, the
report's sections against hand calculations, and one tiny run end to end."""
import math

import numpy as np
import pytest

from ff3d_tf.config import replace_config
from lab.inference import latency
from lab.training import bench_steps

AMD_BF16 = ("AuthenticAMD", ("avx512_bf16",))  # auto resolves to bfloat16 under hybrid and none, float32 under xla


def test_precision_settings():
    assert latency.precision_settings(None, False) == {"float32": False}
    assert latency.precision_settings(None, True) == {"bfloat16": True}
    assert latency.precision_settings(None, "auto") == {"auto": "auto"}
    assert latency.precision_settings("bfloat16,float32", False) == {"bfloat16": True, "float32": False}
    with pytest.raises(ValueError, match=r"\['fp16'\] unknown; one of float32, bfloat16, auto"):
        latency.precision_settings("float32,fp16", False)


def test_variants_cover_every_mode_in_every_precision():
    found = latency.variants(["auto", "xla"], {"float32": False, "auto": "auto"}, "CPU", AMD_BF16)
    assert list(found) == ["auto/float32", "auto/auto", "xla/float32", "xla/auto"]
    assert [(v.compile, v.resolved, v.precision, v.resolved_precision) for v in found.values()] == [
        ("auto", "hybrid", "float32", "float32"), ("auto", "hybrid", "auto", "bfloat16"),
        ("xla", "xla", "float32", "float32"), ("xla", "xla", "auto", "float32")]
    one = latency.variants(["none", "hybrid"], {"bfloat16": True}, "CPU", AMD_BF16)  # one precision: the mode alone
    assert list(one) == ["none", "hybrid"] and {v.resolved_precision for v in one.values()} == {"bfloat16"}
    assert one["none"].record()["precision_reason"] == "as set"
    with pytest.raises(ValueError, match="model.compile='fast'"):
        latency.variants(["fast"], {"float32": False}, "CPU", AMD_BF16)


def _reading(ms, peak, before, after, reset=True):
    return {"ms": ms, "peak_rss_gb": peak, "rss_before_gb": before, "rss_after_gb": after, "peak_reset": reset}


def test_call_summaries():
    readings = {"a": [_reading(3.0, 1.0, 0.5, 0.7), _reading(1.0, 1.4, 0.6, 0.9), _reading(2.0, 1.2, 0.4, 0.8)],
                "b": [_reading(10.0, 2.0, 1.0, 1.5, reset=False)]}
    out = latency.call_summaries(readings)
    # a: ms 3, 1, 2 -> median 2, min 1; peak: the largest, 1.4; before 0.5, 0.6, 0.4 -> 0.5; after 0.7, 0.9, 0.8 -> 0.8
    assert out["a"] == {"median_ms": 2.0, "min_ms": 1.0, "runs": 3, "peak_rss_gb": 1.4, "rss_before_gb": 0.5,
                        "rss_after_gb": 0.8, "peak_reset": False}  # b's reading could not reset: none counts as reset
    assert out["b"]["runs"] == 1 and out["b"]["peak_reset"] is False


def _timed(ms):
    return {"median_ms": ms, "min_ms": ms, "runs": 1, "peak_rss_gb": 1.0, "rss_before_gb": 0.5, "rss_after_gb": 0.6,
            "peak_reset": True}


def test_report_against_hand_calculation():
    both = latency.variants(["none"], {"float32": False, "bfloat16": True}, "CPU", AMD_BF16)
    timed = {"conv_floor/graph": _timed(8.0), "conv_floor/xla": _timed(5.0),  # no bfloat16 floor
             "100/none/float32": _timed(20.0), "100/none/bfloat16": _timed(16.0),
             "400/none/float32": _timed(50.0), "400/none/bfloat16": _timed(32.0),
             "train/none/float32": _timed(60.0), "train/none/bfloat16": _timed(48.0)}
    flows = {n: {"none/float32": np.zeros((n, 3), np.float32), "none/bfloat16": np.zeros((n, 3), np.float32)}
             for n in (100, 400)}
    flows[100]["none/bfloat16"][7] = [3.0, 4.0, 0.0]  # one point 5 m/s off the reference (float32, the first variant)
    flows[100]["none/float32"][:] = [0.0, 2.0, 0.0]
    flows[100]["none/bfloat16"][:7] = [0.0, 2.0, 0.0]
    flows[100]["none/bfloat16"][8:] = [0.0, 2.0, 0.0]
    out = latency.report(timed, both, [400, 100], {100: 1024, 400: 1024, "train": 1024}, flows, train_points=100)
    assert list(out["conv_floor"]) == ["graph", "xla"]
    row = out["latency"]["100"]["none/bfloat16"]
    # point 7: (3, 4, 0) against (0, 2, 0): components 3, 2, 0 -> max 3; length sqrt(9 + 4) = 3.606; mean over 100
    # points 0.03606; the variant's own flow: 99 points of length 2 and one of 5 -> mean 2.03
    assert row["max_abs_flow_diff_vs_none/float32"] == 3.0
    assert row["max_flow_diff_norm_vs_none/float32_mps"] == pytest.approx(math.sqrt(13))
    assert row["mean_flow_diff_norm_vs_none/float32_mps"] == pytest.approx(math.sqrt(13) / 100)
    assert row["mean_flow_norm_mps"] == pytest.approx(2.03)
    assert row["padded_points"] == 1024 and row["median_ms"] == 16.0
    assert out["latency"]["100"]["none/float32"]["max_abs_flow_diff_vs_none/float32"] == 0.0
    # float32: 50 / 20 = 2.5 over the point counts; 20 ms over the fastest float32 floor (xla, 5 ms) = 4
    assert out["ratios"]["none/float32"] == {"max_over_min_points": 2.5, "min_points_over_fastest_conv_floor": 4.0}
    assert out["ratios"]["none/bfloat16"]["max_over_min_points"] == 2.0  # 32 / 16
    assert math.isnan(out["ratios"]["none/bfloat16"]["min_points_over_fastest_conv_floor"])  # no bfloat16 floor
    assert out["train_step"]["none/float32"]["over_inference_same_points"] == 3.0  # 60 / 20 at 100 points
    assert out["train_step"]["none/bfloat16"]["over_inference_same_points"] == 3.0  # 48 / 16
    assert out["train_step"]["none/float32"]["padded_points"] == 1024

    timed_at_other_points = {k: v for k, v in timed.items() if not k.startswith("conv_floor/")}
    out = latency.report(timed_at_other_points, both, [100, 400], {100: 1024, 400: 1024, "train": 2048}, flows,
                         train_points=250)  # the forward is not timed at 250 points
    assert "conv_floor" not in out
    assert out["train_step"]["none/float32"]["over_inference_same_points"] is None
    assert latency.report(timed, both, [100, 400], {100: 1024, 400: 1024}, flows, train_points=0).keys() == {
        "conv_floor", "latency", "ratios"}
    lines = latency.report_lines(out, 250)
    assert lines[0] == "100 points: none/float32 20 ms (peak RSS 1.00 GB); none/bfloat16 16 ms (peak RSS 1.00 GB)"
    assert lines[-1] == ("train step at 250 points: none/float32 60 ms (RSS between steps 0.60 GB); none/bfloat16 "
                         "48 ms (RSS between steps 0.60 GB)")


def test_run_refuses_before_building_anything(tiny_config):
    with pytest.raises(ValueError, match="train_points given without train_steps"):
        latency.run(tiny_config, ["none"], {"float32": False}, [100], 1, 100, False, bench_steps.example, None)
    with pytest.raises(ValueError, match="no point counts"):
        latency.run(tiny_config, ["none"], {"float32": False}, [], 1, 0, False, bench_steps.example, None)


def test_tiny_run(tiny_config):
    asked = []

    def train_steps(cfg, modes, labelled):  # one call per precision; a step that returns a constant loss
        asked.append((cfg.model.mixed_precision, dict(modes), int(labelled["point_mask_t0"].shape[1])))
        return {name: (lambda: np.float32(1.0)) for name in modes}

    cfg = replace_config(tiny_config, {"model.mixed_precision": False})
    lines = []
    results = latency.run(cfg, ["none", "hybrid"], {"float32": False}, [900, 300], 1, 300, True, bench_steps.example,
                          train_steps, log=lines.append)
    assert asked == [(False, {"none": "none", "hybrid": "hybrid"}, 1024)]
    assert lines[0].startswith("variants: none: none -> none (no XLA), float32 -> float32 (as set); hybrid: ")
    assert list(results["latency"]) == ["300", "900"] and list(results["conv_floor"]) == ["graph", "xla"]
    for n in ("300", "900"):
        assert results["latency"][n]["none"]["max_abs_flow_diff_vs_none"] == 0.0  # the reference itself
        assert results["latency"][n]["hybrid"]["max_abs_flow_diff_vs_none"] < 1e-3  # same weights, same input
        assert results["latency"][n]["hybrid"]["runs"] == 1 and results["latency"][n]["hybrid"]["padded_points"] == 1024
    lat = results["latency"]
    assert results["ratios"]["hybrid"]["max_over_min_points"] == lat["900"]["hybrid"]["median_ms"] / \
        lat["300"]["hybrid"]["median_ms"]
    floor_ms = min(results["conv_floor"][b]["median_ms"] for b in ("graph", "xla"))
    assert results["ratios"]["none"]["min_points_over_fastest_conv_floor"] == lat["300"]["none"]["median_ms"] / floor_ms
    assert results["train_step"]["none"]["over_inference_same_points"] == \
        results["train_step"]["none"]["median_ms"] / lat["300"]["none"]["median_ms"]
    assert results["modes"]["hybrid"]["resolved"] == "hybrid" and results["precisions"] == {"float32": False}
    assert results["grid"] == [32, 32] and results["params"] > 0
    assert lines[-1].startswith("train step at 300 points: none ")
