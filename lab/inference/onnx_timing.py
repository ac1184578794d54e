"""Latency of the ONNX export under onnxruntime (CPU) beside TensorFlow's serving forward, in one process
(lab/tools/benchmark_onnx.py).

Input: one pair of benchmark clouds (`serving_pair`: `lab.bench.random_clouds`, uniform over the grid, with t-1
given in its own vehicle frame and a pose pair 1 km from the world origin). TensorFlow runs the SavedModel's serving
function (`FlowServingModule.serve`: ego motion, padding to the bucket, the model in its config's compile mode); each
ONNX variant (`ff3d_tf.inference.onnx_export.VARIANTS`) is exported from the same model and runs in onnxruntime with
the given intra-op threads. After one warm-up round, every call takes its turn in one round robin
(`bench.round_robin`): compare the ratios. Also recorded: each variant's export time, size and ops, its largest flow
difference from TensorFlow's last call, whether validity is identical, and whether its outputs were bit-identical over
all its calls (`accuracy`).
"""
from __future__ import annotations

import os
import tempfile
from typing import Callable, Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf import cpu, geometry
from ff3d_tf.checkpoints import restore_model
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.inference import onnx_export
from ff3d_tf.inference.saved_model import FlowServingModule
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib
from lab import bench

REFERENCE = "tensorflow"  # the call every other is compared with
WARMUP_ROUNDS = 1
RANDOM_WEIGHTS = "random (build_model)"  # the results' "weights" without a checkpoint


def pose(yaw_rad: float, x_m: float, y_m: float, z_m: float = 2.0) -> np.ndarray:
    """[4,4] float64 vehicle -> world transform: a yaw about z, then a translation."""
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw_rad), -np.sin(yaw_rad)], [np.sin(yaw_rad), np.cos(yaw_rad)]]
    m[:3, 3] = [x_m, y_m, z_m]
    return m


POSE_TM1, POSE_T0 = pose(0.30, 1000.0, -500.0), pose(0.31, 1001.0, -499.8)  # 1 km from the world origin


def serving_pair(cfg: ExperimentConfig, rng: np.random.Generator, points: int) -> tuple[np.ndarray, ...]:
    """(points_tm1, points_t0 [points, 5] float32: x, y, z, intensity, elongation, each in its own vehicle frame;
    pose_tm1, pose_t0 [4,4] float64): the benchmark clouds over cfg's grid, t-1 moved back from the t0 frame into
    its own by `POSE_TM1` and `POSE_T0`."""
    g = cfg.grid
    clouds = bench.random_clouds(rng, points, points, (g.x_range_m, g.y_range_m, g.z_range_m))
    tm1_from_t0 = np.linalg.inv(geometry.t0_from_tm1_np(POSE_T0, POSE_TM1))
    xyz_tm1 = geometry.transform_points_np(clouds["points_xyz_tm1_in_t0"][0], tm1_from_t0).astype(np.float32)
    points_t0 = np.concatenate([clouds["points_xyz_t0"][0], clouds["point_features_t0"][0]], -1)
    points_tm1 = np.concatenate([xyz_tm1, clouds["point_features_tm1"][0]], -1)
    return points_tm1, points_t0, POSE_TM1, POSE_T0


def _recording(fn: Callable, outputs: list) -> Callable:
    """`fn` with its results fetched to the host and appended to `outputs`."""
    def call():
        out = bench.fetch(fn())
        outputs.append(out)
        return out
    return call


def latency_summary(readings: dict[str, list[dict]]) -> dict:
    """{call: median_ms, mean_ms, min_ms and runs} of each call's round-robin readings."""
    return {name: {**bench.summary([r["ms"] for r in rs]), "runs": len(rs)} for name, rs in readings.items()}


def ratios_over_reference(latency: dict) -> dict:
    """{call: its median over the reference's (`REFERENCE`)} of every call but the reference."""
    reference_ms = latency[REFERENCE]["median_ms"]
    return {name: v["median_ms"] / reference_ms for name, v in latency.items() if name != REFERENCE}


def accuracy(outputs: dict[str, list[dict]]) -> dict:
    """{call: how its last outputs compare with the reference's last} for every call but the reference: the largest
    absolute flow difference (m/s) and the reference's largest absolute flow component, whether `point_valid` is
    identical, the reference's valid points, whether all the call's outputs were bit-identical, and its call count.
    `outputs`: {call: the {"flow_mps", "point_valid"} of each of its calls}."""
    ref = outputs[REFERENCE][-1]
    out = {}
    for name, outs in outputs.items():
        if name == REFERENCE:
            continue
        last = outs[-1]
        out[name] = {"max_abs_flow_diff_mps": float(np.abs(last["flow_mps"] - ref["flow_mps"]).max()),
                     "max_abs_flow_mps": float(np.abs(ref["flow_mps"]).max()),
                     "point_valid_identical": bool(np.array_equal(last["point_valid"], ref["point_valid"])),
                     "valid_points": int(ref["point_valid"].sum()),
                     "bit_identical_over_calls": all(np.array_equal(o["flow_mps"], last["flow_mps"]) and
                                                     np.array_equal(o["point_valid"], last["point_valid"])
                                                     for o in outs),
                     "calls": len(outs)}
    return out


def versions() -> dict:
    """The versions of TensorFlow and of the ONNX packages the export and the runtime use."""
    import onnx
    import onnxruntime
    import tf2onnx
    return {"tensorflow": tf.__version__, "tf2onnx": tf2onnx.__version__, "onnx": onnx.__version__,
            "onnxruntime": onnxruntime.__version__}


def run(cfg: ExperimentConfig, checkpoint: str | None, points: int, runs: int, threads: int,
        variants: Sequence[str], log: Callable[[str], None] = print) -> dict:
    """The benchmark (module docstring) of the model of `checkpoint` (a model_dir or checkpoint prefix; None: random
    weights) on one pair of `points` points: `runs` measured rounds, onnxruntime with `threads` intra-op threads, the
    ONNX `variants`. The results as written to JSON."""
    unknown = [v for v in variants if v not in onnx_export.VARIANTS]
    if unknown:
        raise ValueError(f"ONNX variants {unknown} unknown; of {', '.join(onnx_export.VARIANTS)}")
    load_average_at_start = bench.load_average()
    model = restore_model(cfg, checkpoint) if checkpoint else build_model(cfg)
    pair = serving_pair(cfg, np.random.default_rng(0), points)
    module = FlowServingModule(model, cfg.data.point_bucket_base, cfg.model.jit_compile)
    tensors = [tf.constant(a) for a in pair]
    outputs = {REFERENCE: []}
    calls = {REFERENCE: _recording(lambda: module.serve(*tensors), outputs[REFERENCE])}
    exports = {}
    with tempfile.TemporaryDirectory() as tmp:
        for variant in variants:
            path = os.path.join(tmp, f"{variant}.onnx")
            info, export_s = bench.elapsed(lambda: onnx_export.export_onnx(model, path, variant))
            predictor = onnx_export.OnnxFlowPredictor(path, threads)
            exports[variant] = {"export_s": export_s, "pose_inputs": info["pose_inputs"],
                                "file_mb": os.path.getsize(path) / 1e6, "ops": info["ops"]}
            name = f"onnxruntime_{variant}"
            outputs[name] = []
            calls[name] = _recording(lambda predictor=predictor: predictor(*pair), outputs[name])
            log(f"exported {variant} in {export_s:.1f} s")
        readings = bench.round_robin(calls, runs, warmup=WARMUP_ROUNDS)
    latency = latency_summary(readings)
    return {"device": compile_lib.accelerator_type(), "cpu_count": os.cpu_count(), "cpu": cpu.describe(),
            "load_average_at_start": load_average_at_start, "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y],
            "points": points, "runs": runs, "onnxruntime_intra_op_threads": threads,
            "tensorflow_compile_mode": compile_lib.resolve_compile_mode(cfg.model.compile),
            "weights": checkpoint or RANDOM_WEIGHTS, "versions": versions(), "exports": exports, "latency": latency,
            "ratios_over_tensorflow": ratios_over_reference(latency), "accuracy": accuracy(outputs),
            "load_average_at_end": bench.load_average()}


def headline(results: dict) -> dict:
    """What the tool prints: the medians rounded to ms, the ratios and the accuracy."""
    return {"latency_ms": {k: round(v["median_ms"]) for k, v in results["latency"].items()},
            "ratios_over_tensorflow": results["ratios_over_tensorflow"], "accuracy": results["accuracy"]}
