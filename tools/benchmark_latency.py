"""Forward latency of FastFlow3D vs point count, the dense-convolution floor of each backend and the training step,
for every compile mode side by side (paper Table 3). JSON out.

python tools/benchmark_latency.py --config configs/fastflow3d_waymo.yaml --modes auto,xla,hybrid,none --out L.json
Batch 1; warm-up (compilation) excluded; every measured call (each mode at each point count, the conv floors, each
mode's training step) takes its turn in one round robin, so load on a shared machine hits them alike: compare ratios
within one run. Median and min of --runs calls; peak resident memory of each
call (Linux VmHWM, reset before it, so start-up and compilation do not count); resident memory between calls.
The conv floor is the dense stages alone on a ready grid, XLA and graph kernels. The training step is forward + backward + Adam (the Trainer's own step) at --train_points,
batch 1. Memory: `rss_before_gb` is the resident set before a call after returning freed heap to the OS
(malloc_trim), `rss_after_gb` right after a call without it (what the process holds between calls).
"""
import ctypes
import json
import os
import tempfile
import time

import _common
import numpy as np
import tensorflow as tf

from ff3d_tf.config import replace_config
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib


def _cloud(rng, n, cfg):
    g = cfg.grid
    xyz = np.stack([rng.uniform(*g.x_range_m, n), rng.uniform(*g.y_range_m, n), rng.uniform(-2.5, 2.5, n)], -1)
    return xyz.astype(np.float32), rng.uniform(0, 1, (n, 2)).astype(np.float32)


def _example(rng, n, cfg, labels=False):
    """One padded pair of n points per cloud, batch 1 (the model's input keys; flow labels when `labels`)."""
    padded = bucket_size(n, cfg.data.point_bucket_base)
    p0, f0 = _cloud(rng, n, cfg)
    p1, f1 = _cloud(rng, n, cfg)
    pad = [[0, padded - n], [0, 0]]
    ex = {"points_xyz_t0": tf.constant(np.pad(p0, pad)[None]), "point_features_t0": tf.constant(np.pad(f0, pad)[None]),
          "point_mask_t0": tf.sequence_mask([n], padded),
          "points_xyz_tm1_in_t0": tf.constant(np.pad(p1, pad)[None]),
          "point_features_tm1": tf.constant(np.pad(f1, pad)[None]), "point_mask_tm1": tf.sequence_mask([n], padded)}
    if labels:
        ex["flow_mps_t0"] = tf.constant(rng.normal(0, 1, (1, padded, 3)).astype(np.float32))
        ex["class_id_t0"] = tf.constant(rng.integers(0, 5, (1, padded)).astype(np.int32))
    return ex, padded


def _rss_gb(field: str) -> float:
    """VmRSS (now) or VmHWM (peak since the last reset) of this process, GB (Linux /proc)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


def _reset_peak_rss() -> bool:
    """Returns freed heap to the OS and resets VmHWM to the current RSS (Linux >= 4.0, glibc). False where that is
    not possible (the peak then covers the whole process)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except (OSError, AttributeError):
        return False


def _interleaved(fns: dict, runs: int, warmup: int = 2) -> dict:
    """{name: fn} -> {name: timing}, the calls of all fns interleaved; each call's peak RSS measured alone."""
    for _ in range(warmup):
        for fn in fns.values():
            tf.nest.map_structure(lambda t: t.numpy(), fn())
    samples = {k: {"ms": [], "peak": [], "before": [], "after": []} for k in fns}
    peak_reset = True
    for _ in range(runs):
        for name, fn in fns.items():
            peak_reset &= _reset_peak_rss()
            s = samples[name]
            s["before"].append(_rss_gb("VmRSS"))
            t = time.perf_counter()
            tf.nest.map_structure(lambda t: t.numpy(), fn())
            s["ms"].append(1e3 * (time.perf_counter() - t))
            s["peak"].append(_rss_gb("VmHWM"))
            s["after"].append(_rss_gb("VmRSS"))
    return {k: {"median_ms": float(np.median(s["ms"])), "min_ms": float(np.min(s["ms"])), "runs": runs,
                "peak_rss_gb": float(np.max(s["peak"])), "rss_before_gb": float(np.median(s["before"])),
                # Resident set right after a call returns (before any trim): what the process holds between calls.
                "rss_after_gb": float(np.median(s["after"])), "peak_reset": peak_reset}
            for k, s in samples.items()}


def _train_steppers(cfg, modes: dict, example: dict):
    """{mode: step fn} running the Trainer's own step (forward + backward + Adam) on `example` forever; the same
    seed gives every mode's trainer the same initial weights."""
    from ff3d_tf.training.trainer import Trainer
    steppers = {}
    for name, resolved in modes.items():
        tcfg = replace_config(cfg, {"model.compile": resolved, "train.global_batch_size": 1,
                                    "train.learning_rate": 1e-6})
        trainer = Trainer(tcfg, tempfile.mkdtemp(prefix="bench_train_"), [],
                          strategy=tf.distribute.OneDeviceStrategy("/cpu:0"), log_fn=lambda s: None)
        ds = trainer.strategy.experimental_distribute_dataset(tf.data.Dataset.from_tensors(example).repeat())
        iterator = iter(ds)
        steppers[name] = (lambda tr=trainer, it=iterator: tr._train_step(it))
    return steppers


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--points", default="32000,100000,255000,1000000")
    p.add_argument("--modes", default=None, help="comma-separated model.compile modes (default: the config's)")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--train_points", type=int, default=32000, help="0 = no training-step benchmark")
    p.add_argument("--skip_conv_floor", action="store_true",
                   help="no conv floor (its buffers stay resident and count in the later calls' memory)")
    p.add_argument("--out", default="latency.json")
    args = p.parse_args()
    cfg = _common.load(args)
    requested = (args.modes or cfg.model.compile).split(",")
    modes = {m: compile_lib.resolve_compile_mode(m) for m in requested}  # "auto" is measured as what it resolves to
    print("modes: " + ", ".join(f"{m} -> {r} ({compile_lib.describe(r)})" for m, r in modes.items()), flush=True)
    models = {m: build_model(cfg, r) for m, r in modes.items()}
    first = next(iter(models.values()))
    for model in models.values():
        model.set_weights(first.get_weights())
    framework_baseline_gb = _rss_gb("VmRSS")  # TensorFlow imported, model variables created
    forwards = {m: tf.function(lambda x, model=model: model(x, training=False), reduce_retracing=True)
                for m, model in models.items()}
    rng = np.random.default_rng(0)
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    results = {"device": compile_lib.accelerator_type(), "cpu_count": os.cpu_count(), "load_average_at_start": load,
               "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y],
               "modes": {m: {"resolved": r, "description": compile_lib.describe(r)} for m, r in modes.items()},
               "mixed_precision": cfg.model.mixed_precision, "params": first.count_params(),
               "framework_baseline_rss_gb": framework_baseline_gb, "latency": {}}
    # Conv floor of each backend: the encoder (both frames stacked) + decoder on an already-built grid.
    h, w, c = cfg.grid.num_pillars_y, cfg.grid.num_pillars_x, cfg.model.point_feature_dim
    bev = tf.constant(rng.uniform(0, 1, (2, h, w, c)).astype(np.float32))
    dense = {"xla": tf.function(lambda x: first.dense_stages(x), jit_compile=True),
             "graph": tf.function(lambda x: first.dense_stages(x))}
    calls = {} if args.skip_conv_floor else {f"conv_floor/{k}": (lambda f=f: f(bev)) for k, f in dense.items()}
    points = sorted(int(v) for v in args.points.split(","))
    padded_points, outputs = {}, {}
    for n in points:
        inputs, padded_points[n] = _example(rng, n, cfg)
        outputs[n] = {m: f(inputs)["flow_mps"].numpy() for m, f in forwards.items()}
        calls.update({f"{n}/{m}": (lambda f=f, x=inputs: f(x)) for m, f in forwards.items()})
    if args.train_points:
        example, train_padded = _example(rng, args.train_points, cfg, labels=True)
        calls.update({f"train/{m}": fn for m, fn in _train_steppers(cfg, modes, example).items()})
    timed = _interleaved(calls, args.runs)
    if not args.skip_conv_floor:
        results["conv_floor"] = {k: timed[f"conv_floor/{k}"] for k in dense}
        print("conv floor: " + "; ".join(f"{k} {v['median_ms']:.0f} ms" for k, v in results["conv_floor"].items()),
              flush=True)
    for n in points:
        r = {m: {**timed[f"{n}/{m}"], "padded_points": padded_points[n], f"max_abs_flow_diff_vs_{requested[0]}":
                 float(np.abs(outputs[n][m] - outputs[n][requested[0]]).max())} for m in modes}
        results["latency"][str(n)] = r
        print(f"{n} points: " + "; ".join(f"{m} {v['median_ms']:.0f} ms (peak RSS {v['peak_rss_gb']:.2f} GB)"
                                          for m, v in r.items()), flush=True)
    floor = min(v["median_ms"] for v in results["conv_floor"].values()) if "conv_floor" in results else float("nan")
    lat = results["latency"]
    results["ratios"] = {m: {"max_over_min_points": lat[str(points[-1])][m]["median_ms"] /
                             lat[str(points[0])][m]["median_ms"],
                             "min_points_over_fastest_conv_floor": lat[str(points[0])][m]["median_ms"] / floor}
                         for m in modes}
    if args.train_points:
        r = {m: {**timed[f"train/{m}"], "padded_points": train_padded} for m in modes}
        for m in r:
            r[m]["over_inference_same_points"] = (r[m]["median_ms"] / lat[str(args.train_points)][m]["median_ms"]
                                                  if str(args.train_points) in lat else None)
        results["train_step"] = r
        print(f"train step at {args.train_points} points: " + "; ".join(
            f"{m} {v['median_ms']:.0f} ms (RSS between steps {v['rss_after_gb']:.2f} GB)" for m, v in r.items()),
            flush=True)
    with open("/proc/loadavg") as f:
        results["load_average_at_end"] = f.read().split()[:3]
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps(results["ratios"]))


if __name__ == "__main__":
    main()
