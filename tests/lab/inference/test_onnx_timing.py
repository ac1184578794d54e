"""lab/inference/onnx_timing.py (lab/tools/benchmark_onnx.py): the serving pair, the latency summary, ratios and
accuracy against hand calculations, and one tiny run end to end."""
import numpy as np
import pytest

from ff3d_tf import geometry
from lab.inference import onnx_timing


def test_serving_pair_puts_t_minus_1_in_its_own_frame(tiny_config):
    points_tm1, points_t0, pose_tm1, pose_t0 = onnx_timing.serving_pair(tiny_config, np.random.default_rng(0), 50)
    assert points_tm1.shape == points_t0.shape == (50, 5) and points_t0.dtype == points_tm1.dtype == np.float32
    assert pose_tm1.dtype == np.float64 and pose_tm1[0, 3] == 1000.0 and geometry.pose_problem_np(pose_t0, "p") is None
    # Back into the t0 frame, t-1 lies on the grid like t0 (x, y within +-40 m); in its own frame it does not.
    in_t0 = geometry.transform_points_np(points_tm1[:, :3], geometry.t0_from_tm1_np(pose_t0, pose_tm1))
    assert np.abs(in_t0[:, :2]).max() <= 40.0 + 1e-3
    assert not np.allclose(in_t0, points_tm1[:, :3], atol=0.1)
    same = onnx_timing.serving_pair(tiny_config, np.random.default_rng(0), 50)
    assert all(np.array_equal(a, b) for a, b in zip(same, (points_tm1, points_t0, pose_tm1, pose_t0)))


def test_latency_summary_and_ratios():
    readings = {"tensorflow": [{"ms": 10.0}, {"ms": 30.0}, {"ms": 20.0}], "onnxruntime_loop": [{"ms": 40.0}]}
    latency = onnx_timing.latency_summary(readings)
    # tensorflow: 10, 30, 20 -> median 20, mean 20, min 10
    assert latency["tensorflow"] == {"median_ms": 20.0, "mean_ms": 20.0, "min_ms": 10.0, "runs": 3}
    assert onnx_timing.ratios_over_reference(latency) == {"onnxruntime_loop": 2.0}  # 40 / 20


def _out(flow, valid):
    return {"flow_mps": np.array(flow, np.float32), "point_valid": np.array(valid)}


def test_accuracy_against_hand_calculation():
    reference = _out([[1.0, -4.0, 0.0], [0.0, 0.0, 0.0]], [True, False])
    outputs = {"tensorflow": [_out([[9.0, 9.0, 9.0], [0, 0, 0]], [True, True]), reference],  # only the last counts
               "onnxruntime_loop": [_out([[1.5, -4.0, 0.0], [0, 0, 0]], [True, False])] * 2,
               "onnxruntime_single_chunk": [_out([[1.0, -4.0, 0.0], [0, 0, 0]], [True, True]),
                                            _out([[1.0, -4.25, 0.0], [0, 0, 0]], [True, True])]}
    found = onnx_timing.accuracy(outputs)
    assert list(found) == ["onnxruntime_loop", "onnxruntime_single_chunk"]
    # loop: |1.5 - 1| = 0.5; the reference's largest |component| is 4; one valid point; both calls alike
    assert found["onnxruntime_loop"] == {"max_abs_flow_diff_mps": 0.5, "max_abs_flow_mps": 4.0,
                                         "point_valid_identical": True, "valid_points": 1,
                                         "bit_identical_over_calls": True, "calls": 2}
    # single_chunk: |-4.25 + 4| = 0.25; validity differs at the second point; its two calls differ
    chunk = found["onnxruntime_single_chunk"]
    assert (chunk["max_abs_flow_diff_mps"], chunk["point_valid_identical"], chunk["bit_identical_over_calls"]) == (
        0.25, False, False)


def test_unknown_variant_is_refused_before_any_work(tiny_config):
    with pytest.raises(ValueError, match=r"ONNX variants \['fast'\] unknown"):
        onnx_timing.run(tiny_config, None, 100, 1, 1, ["loop", "fast"])


def test_tiny_run(tiny_config):
    lines = []
    results = onnx_timing.run(tiny_config, None, 300, 1, 1, ["loop"], log=lines.append)
    assert lines == [f"exported loop in {results['exports']['loop']['export_s']:.1f} s"]
    assert list(results["latency"]) == ["tensorflow", "onnxruntime_loop"]
    assert results["latency"]["onnxruntime_loop"]["runs"] == 1 and results["weights"] == onnx_timing.RANDOM_WEIGHTS
    assert results["ratios_over_tensorflow"]["onnxruntime_loop"] == (
        results["latency"]["onnxruntime_loop"]["median_ms"] / results["latency"]["tensorflow"]["median_ms"])
    loop = results["accuracy"]["onnxruntime_loop"]
    assert loop["calls"] == 2 and loop["bit_identical_over_calls"]  # one warm-up call, one measured
    assert loop["max_abs_flow_diff_mps"] < 1e-3 and loop["point_valid_identical"] and loop["valid_points"] > 0
    assert results["exports"]["loop"]["file_mb"] > 0 and set(results["versions"]) == {
        "tensorflow", "tf2onnx", "onnx", "onnxruntime"}
    assert onnx_timing.headline(results)["latency_ms"].keys() == {"tensorflow", "onnxruntime_loop"}
