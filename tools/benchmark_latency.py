"""Forward latency of FastFlow3D vs point count, the dense-convolution floor of each backend and the training step,
for every compile mode side by side (paper Table 3). JSON out.

python tools/benchmark_latency.py --config configs/fastflow3d_waymo.yaml --modes auto,xla,hybrid,none --out L.json
Batch 1, the benchmark cloud of `ff3d_tf.bench` (uniform over the grid); warm-up (compilation) excluded; every measured
call (each mode at each point count, the conv floors, each mode's training step) takes its turn in one round robin
(`bench.round_robin`), so load on a shared machine hits them alike: compare ratios within one run. Median and min of
--runs calls; peak resident memory of each call (Linux VmHWM, reset before it, so start-up and compilation do not
count); resident memory between calls. The conv floor is the dense stages alone on a ready grid, XLA and graph
kernels. The training step is forward + backward + Adam (the Trainer's own step, `Trainer.step`) at --train_points,
batch 1. Memory: `rss_before_gb` is the resident set before a call after returning freed heap to the OS
(malloc_trim), `rss_after_gb` right after a call without it (what the process holds between calls).
"""
import json
import os

import _common
import numpy as np
import tensorflow as tf

from ff3d_tf import bench
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib
from ff3d_tf.training import bench_steps


def _interleaved(calls: dict, runs: int) -> dict:
    """{name: fn} -> {name: timing}: two warm-up rounds, then `runs` rounds of one call of each (results fetched to
    the host), each call's peak RSS measured alone (`bench.timed_with_memory`)."""
    readings = bench.round_robin({k: bench.fetched(fn) for k, fn in calls.items()}, runs, warmup=2,
                                 reading=bench.timed_with_memory)
    peak_reset = all(r["peak_reset"] for rs in readings.values() for r in rs)
    return {k: {**bench.summary([r["ms"] for r in rs], ("median", "min")), "runs": runs,
                "peak_rss_gb": float(np.max([r["peak_rss_gb"] for r in rs])),
                "rss_before_gb": float(np.median([r["rss_before_gb"] for r in rs])),
                # Resident set right after a call returns (before any trim): what the process holds between calls.
                "rss_after_gb": float(np.median([r["rss_after_gb"] for r in rs])), "peak_reset": peak_reset}
            for k, rs in readings.items()}


def _args():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--points", default="32000,100000,255000,1000000")
    p.add_argument("--modes", default=None, help="comma-separated model.compile modes (default: the config's)")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--train_points", type=int, default=32000, help="0 = no training-step benchmark")
    p.add_argument("--skip_conv_floor", action="store_true",
                   help="no conv floor (its buffers stay resident and count in the later calls' memory)")
    p.add_argument("--out", default="latency.json")
    return p.parse_args()


def _conv_floors(cfg, model, rng) -> dict:
    """{backend: call} of the conv floor: the encoder (both frames stacked) + decoder on an already-built grid."""
    h, w, c = cfg.grid.num_pillars_y, cfg.grid.num_pillars_x, cfg.model.point_feature_dim
    bev = tf.constant(rng.uniform(0, 1, (2, h, w, c)).astype(np.float32))
    dense = {"xla": tf.function(lambda x: model.dense_stages(x), jit_compile=True),
             "graph": tf.function(lambda x: model.dense_stages(x))}
    return {k: (lambda f=f: f(bev)) for k, f in dense.items()}


def _report(results: dict, timed: dict, args, modes: dict, points: list, padded: dict, outputs: dict) -> None:
    """Fills `results` from the timings (conv floors, latency per point count, ratios, training step) and prints."""
    requested = list(modes)
    if "conv_floor/xla" in timed:
        results["conv_floor"] = {k: timed[f"conv_floor/{k}"] for k in ("xla", "graph")}
        print("conv floor: " + "; ".join(f"{k} {v['median_ms']:.0f} ms" for k, v in results["conv_floor"].items()),
              flush=True)
    for n in points:
        r = {m: {**timed[f"{n}/{m}"], "padded_points": padded[n], f"max_abs_flow_diff_vs_{requested[0]}":
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
        r = {m: {**timed[f"train/{m}"], "padded_points": padded["train"]} for m in modes}
        for m in r:
            r[m]["over_inference_same_points"] = (r[m]["median_ms"] / lat[str(args.train_points)][m]["median_ms"]
                                                  if str(args.train_points) in lat else None)
        results["train_step"] = r
        print(f"train step at {args.train_points} points: " + "; ".join(
            f"{m} {v['median_ms']:.0f} ms (RSS between steps {v['rss_after_gb']:.2f} GB)" for m, v in r.items()),
            flush=True)


def main():
    args = _args()
    cfg = _common.load(args)
    requested = (args.modes or cfg.model.compile).split(",")
    modes = {m: compile_lib.resolve_compile_mode(m) for m in requested}  # "auto" is measured as what it resolves to
    print("modes: " + ", ".join(f"{m} -> {r} ({compile_lib.describe(r)})" for m, r in modes.items()), flush=True)
    models = {m: build_model(cfg, r) for m, r in modes.items()}
    first = next(iter(models.values()))
    for model in models.values():
        model.set_weights(first.get_weights())
    framework_baseline_gb = bench.proc_status("VmRSS")  # TensorFlow imported, model variables created
    forwards = {m: tf.function(lambda x, model=model: model(x, training=False), reduce_retracing=True)
                for m, model in models.items()}
    rng = np.random.default_rng(0)
    results = {"device": compile_lib.accelerator_type(), "cpu_count": os.cpu_count(),
               "load_average_at_start": bench.load_average(), "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y],
               "modes": {m: {"resolved": r, "description": compile_lib.describe(r)} for m, r in modes.items()},
               "mixed_precision": cfg.model.mixed_precision, "params": first.count_params(),
               "framework_baseline_rss_gb": framework_baseline_gb, "latency": {}}
    floors = _conv_floors(cfg, first, rng)
    calls = {} if args.skip_conv_floor else {f"conv_floor/{k}": f for k, f in floors.items()}
    points = sorted(int(v) for v in args.points.split(","))
    padded, outputs = {}, {}
    for n in points:
        inputs, padded[n] = bench_steps.example(cfg, rng, n)
        outputs[n] = {m: f(inputs)["flow_mps"].numpy() for m, f in forwards.items()}
        calls.update({f"{n}/{m}": (lambda f=f, x=inputs: f(x)) for m, f in forwards.items()})
    if args.train_points:
        labelled, padded["train"] = bench_steps.example(cfg, rng, args.train_points, labels=True)
        calls.update({f"train/{m}": fn for m, fn in bench_steps.train_steps(cfg, modes, labelled).items()})
    _report(results, _interleaved(calls, args.runs), args, modes, points, padded, outputs)
    results["load_average_at_end"] = bench.load_average()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps(results["ratios"]))


if __name__ == "__main__":
    main()
