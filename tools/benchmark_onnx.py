"""Latency of the ONNX export under onnxruntime (CPU) beside TensorFlow's serving forward, in one run. JSON out.

python tools/benchmark_onnx.py --config configs/fastflow3d_waymo.yaml [--checkpoint M] --points 32000 --runs 3
    --threads 2 --variants loop,single_chunk --out benchmarks/onnx_cpu.json

One pair of benchmark clouds (`ff3d_tf.bench.random_clouds`, uniform over the grid; t-1 given in its own vehicle
frame with a pose pair 1 km from the world origin), random weights without --checkpoint. TensorFlow runs the
SavedModel's serving function (`FlowServingModule.serve`: ego motion, padding to the bucket, the model in its
config's compile mode); each ONNX variant runs in onnxruntime with --threads intra-op threads. After one warm-up
round, every call takes its turn in one round robin (`bench.round_robin`): compare the ratios. Also recorded: each
variant's export time, its largest flow difference from TensorFlow, whether validity is identical, and whether its
outputs were bit-identical over all its calls.
"""
import json
import os
import tempfile

import _common
import numpy as np
import tensorflow as tf

from ff3d_tf import bench
from ff3d_tf.checkpoints import restore_model
from ff3d_tf.inference import onnx_export
from ff3d_tf.inference.saved_model import FlowServingModule
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib


def _pose(yaw: float, x: float, y: float) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:3, 3] = [x, y, 2.0]
    return m


def _pair(cfg, rng, n):
    """(points_tm1, points_t0 [N,5] float32 raw, pose_tm1, pose_t0): the benchmark clouds, t-1 back in its frame."""
    g = cfg.grid
    c = bench.random_clouds(rng, n, n, (g.x_range_m, g.y_range_m, g.z_range_m))
    pose_tm1, pose_t0 = _pose(0.30, 1000.0, -500.0), _pose(0.31, 1001.0, -499.8)
    tm1_from_t0 = np.linalg.inv(np.linalg.inv(pose_t0) @ pose_tm1)
    xyz_tm1 = c["points_xyz_tm1_in_t0"][0].astype(np.float64) @ tm1_from_t0[:3, :3].T + tm1_from_t0[:3, 3]
    points_t0 = np.concatenate([c["points_xyz_t0"][0], c["point_features_t0"][0]], -1)
    points_tm1 = np.concatenate([xyz_tm1.astype(np.float32), c["point_features_tm1"][0]], -1)
    return points_tm1, points_t0, pose_tm1, pose_t0


def _recording(fn, outputs: list):
    def call():
        out = bench.fetch(fn())
        outputs.append(out)
        return out
    return call


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", default=None, help="model_dir or checkpoint prefix (default: random weights)")
    p.add_argument("--points", type=int, default=32000)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    p.add_argument("--variants", default="loop,single_chunk")
    p.add_argument("--note", default="")
    p.add_argument("--out", default="onnx_cpu.json")
    args = p.parse_args()
    cfg = _common.load(args)
    variants = args.variants.split(",")
    load_at_start = bench.load_average()
    model = restore_model(cfg, args.checkpoint) if args.checkpoint else build_model(cfg)
    pair = _pair(cfg, np.random.default_rng(0), args.points)
    module = FlowServingModule(model, cfg.data.point_bucket_base, cfg.model.jit_compile)
    tensors = [tf.constant(a) for a in pair]
    outputs = {"tensorflow": []}
    calls = {"tensorflow": _recording(lambda: module.serve(*tensors), outputs["tensorflow"])}
    exports = {}
    with tempfile.TemporaryDirectory() as tmp:
        for variant in variants:
            path = os.path.join(tmp, f"{variant}.onnx")
            info, export_s = bench.elapsed(lambda: onnx_export.export_onnx(model, path, variant))
            predictor = onnx_export.OnnxFlowPredictor(path, args.threads)
            exports[variant] = {"export_s": export_s, "pose_inputs": info["pose_inputs"],
                                "file_mb": os.path.getsize(path) / 1e6, "ops": info["ops"]}
            name = f"onnxruntime_{variant}"
            outputs[name] = []
            calls[name] = _recording(lambda predictor=predictor: predictor(*pair), outputs[name])
            print(f"exported {variant} in {export_s:.1f} s", flush=True)
        readings = bench.round_robin(calls, args.runs, warmup=1)
    ref = outputs["tensorflow"][-1]
    results = {"note": args.note, "device": compile_lib.accelerator_type(), "cpu_count": os.cpu_count(),
               "load_average_at_start": load_at_start, "config": args.config, "overrides": args.set,
               "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y], "points": args.points,
               "runs": args.runs, "onnxruntime_intra_op_threads": args.threads,
               "tensorflow_compile_mode": compile_lib.resolve_compile_mode(cfg.model.compile),
               "weights": args.checkpoint or "random (build_model)", "versions": _versions(), "exports": exports,
               "latency": {k: {**bench.summary([r["ms"] for r in rs]), "runs": len(rs)} for k, rs in readings.items()}}
    tf_ms = results["latency"]["tensorflow"]["median_ms"]
    results["ratios_over_tensorflow"] = {k: v["median_ms"] / tf_ms for k, v in results["latency"].items()
                                         if k != "tensorflow"}
    results["accuracy"] = {}
    for k, outs in outputs.items():
        if k == "tensorflow":
            continue
        last = outs[-1]
        results["accuracy"][k] = {
            "max_abs_flow_diff_mps": float(np.abs(last["flow_mps"] - ref["flow_mps"]).max()),
            "max_abs_flow_mps": float(np.abs(ref["flow_mps"]).max()),
            "point_valid_identical": bool(np.array_equal(last["point_valid"], ref["point_valid"])),
            "valid_points": int(ref["point_valid"].sum()),
            "bit_identical_over_calls": all(np.array_equal(o["flow_mps"], last["flow_mps"]) and
                                            np.array_equal(o["point_valid"], last["point_valid"]) for o in outs),
            "calls": len(outs)}
    results["load_average_at_end"] = bench.load_average()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps({"latency_ms": {k: round(v["median_ms"]) for k, v in results["latency"].items()},
                      "ratios_over_tensorflow": results["ratios_over_tensorflow"],
                      "accuracy": results["accuracy"]}, indent=1))


def _versions() -> dict:
    import onnx
    import onnxruntime
    import tf2onnx
    return {"tensorflow": tf.__version__, "tf2onnx": tf2onnx.__version__, "onnx": onnx.__version__,
            "onnxruntime": onnxruntime.__version__}


if __name__ == "__main__":
    _common.run(main)
