"""Forward latency of FastFlow3D vs point count, the dense-convolution floor of each backend and the training step,
for every compile mode side by side (paper Table 3). JSON out.

python tools/benchmark_latency.py --config configs/fastflow3d_waymo.yaml --modes auto,xla,hybrid,none --out L.json
    [--precisions float32,bfloat16]
Variants: every compile mode (--modes) in every precision (--precisions: float32, bfloat16 or auto, the values of
`model.mixed_precision` false, true, auto; default: the config's), named "mode" with one precision, "mode/precision"
with several; all with the same weights.
Batch 1, the benchmark cloud of `ff3d_tf.bench` (uniform over the grid); warm-up (compilation) excluded; every measured
call (each mode at each point count, the conv floors, each mode's training step) takes its turn in one round robin
(`bench.round_robin`), so load on a shared machine hits them alike: compare ratios within one run. Each variant's
maximum flow difference from the first variant is recorded (same weights and input). Median and min of
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
from ff3d_tf.config import replace_config
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
    p.add_argument("--precisions", default=None,
                   help="comma-separated float32, bfloat16, auto (model.mixed_precision false, true, auto; default: "
                        "the config's)")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--train_points", type=int, default=32000, help="0 = no training-step benchmark")
    p.add_argument("--skip_conv_floor", action="store_true",
                   help="no conv floor (its buffers stay resident and count in the later calls' memory)")
    p.add_argument("--out", default="latency.json")
    return p.parse_args()


def _floor_key(backend: str, precision: str) -> str:
    return backend if precision == "float32" else f"{backend}/{precision}"


def _conv_floors(cfg, models: dict, rng) -> dict:
    """{backend: call} of the conv floor: the encoder (both frames stacked) + decoder on an already-built grid, XLA
    and graph kernels in float32, graph kernels (oneDNN) in bfloat16 (as "graph/bfloat16"). `models`: {resolved
    precision: a model in it}."""
    h, w, c = cfg.grid.num_pillars_y, cfg.grid.num_pillars_x, cfg.model.point_feature_dim
    bev = tf.constant(rng.uniform(0, 1, (2, h, w, c)).astype(np.float32))
    calls = {}
    for precision, model in models.items():
        dense = {"graph": tf.function(lambda x, model=model: model.dense_stages(x))}
        if precision == "float32":
            dense["xla"] = tf.function(lambda x, model=model: model.dense_stages(x), jit_compile=True)
        calls.update({_floor_key(k, precision): (lambda f=f: f(bev)) for k, f in sorted(dense.items())})
    return calls


PRECISION_SETTINGS = {"float32": False, "bfloat16": True, "auto": "auto"}  # --precisions -> model.mixed_precision


def _precisions(args, cfg) -> dict:
    """{name: model.mixed_precision value} of --precisions (default: the config's own setting)."""
    if args.precisions is None:
        setting = cfg.model.mixed_precision
        return {next(k for k, v in PRECISION_SETTINGS.items() if v == setting and type(v) is type(setting)): setting}
    names = args.precisions.split(",")
    unknown = [n for n in names if n not in PRECISION_SETTINGS]
    if unknown:
        raise SystemExit(f"--precisions: {unknown} unknown; one of {', '.join(PRECISION_SETTINGS)}")
    return {n: PRECISION_SETTINGS[n] for n in names}


def _report(results: dict, timed: dict, args, modes: dict, points: list, padded: dict, outputs: dict,
            precision_of: dict) -> None:
    """Fills `results` from the timings (conv floors, latency per point count, ratios, training step) and prints.
    `precision_of`: {variant: its resolved precision}; a variant's conv floor is the fastest in its precision."""
    requested = list(modes)
    floors = {k[len("conv_floor/"):]: v for k, v in timed.items() if k.startswith("conv_floor/")}
    if floors:
        results["conv_floor"] = floors
        print("conv floor: " + "; ".join(f"{k} {v['median_ms']:.0f} ms" for k, v in floors.items()), flush=True)
    for n in points:
        ref = outputs[n][requested[0]]
        r = {m: {**timed[f"{n}/{m}"], "padded_points": padded[n],
                 f"max_abs_flow_diff_vs_{requested[0]}": float(np.abs(outputs[n][m] - ref).max()),
                 # Over the n real points (m/s): the largest and mean length of the flow difference, and the scale.
                 f"max_flow_diff_norm_vs_{requested[0]}_mps": float(np.linalg.norm(outputs[n][m] - ref, axis=-1).max()),
                 f"mean_flow_diff_norm_vs_{requested[0]}_mps": float(np.linalg.norm(outputs[n][m] - ref,
                                                                                     axis=-1).mean()),
                 "mean_flow_norm_mps": float(np.linalg.norm(outputs[n][m], axis=-1).mean())} for m in modes}
        results["latency"][str(n)] = r
        print(f"{n} points: " + "; ".join(f"{m} {v['median_ms']:.0f} ms (peak RSS {v['peak_rss_gb']:.2f} GB)"
                                          for m, v in r.items()), flush=True)
    def floor(m):
        same = [v["median_ms"] for k, v in floors.items() if k in (_floor_key(b, precision_of[m]) for b in ("xla",
                                                                                                         "graph"))]
        return min(same) if same else float("nan")
    lat = results["latency"]
    results["ratios"] = {m: {"max_over_min_points": lat[str(points[-1])][m]["median_ms"] /
                             lat[str(points[0])][m]["median_ms"],
                             "min_points_over_fastest_conv_floor": lat[str(points[0])][m]["median_ms"] / floor(m)}
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
    compile_modes = {m: compile_lib.resolve_compile_mode(m) for m in requested}  # "auto": measured as resolved
    precisions = _precisions(args, cfg)
    variants = {}  # name -> (compile mode as requested, resolved mode, precision name, resolved precision)
    for m, r in compile_modes.items():
        for p, setting in precisions.items():
            name = m if len(precisions) == 1 else f"{m}/{p}"
            variants[name] = (m, r, p, compile_lib.resolve_precision(setting, r))
    modes = {name: v[1] for name, v in variants.items()}  # variant -> resolved compile mode
    print("variants: " + "; ".join(f"{name}: {m} -> {r} ({compile_lib.describe(r)}), {p} -> {rp[0]} ({rp[1]})"
                                   for name, (m, r, p, rp) in variants.items()), flush=True)
    models = {name: build_model(replace_config(cfg, {"model.mixed_precision": precisions[p]}), r)
              for name, (m, r, p, _) in variants.items()}
    first = next(iter(models.values()))
    for model in models.values():
        model.set_weights(first.get_weights())
    framework_baseline_gb = bench.proc_status("VmRSS")  # TensorFlow imported, model variables created
    forwards = {m: tf.function(lambda x, model=model: model(x, training=False), reduce_retracing=True)
                for m, model in models.items()}
    rng = np.random.default_rng(0)
    results = {"device": compile_lib.accelerator_type(), "cpu_count": os.cpu_count(),
               "load_average_at_start": bench.load_average(), "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y],
               "modes": {name: {"compile": m, "resolved": r, "description": compile_lib.describe(r),
                                "precision": p, "resolved_precision": rp[0], "precision_reason": rp[1],
                                "precision_description": compile_lib.describe_precision(rp[0])}
                         for name, (m, r, p, rp) in variants.items()},
               "precisions": {p: setting for p, setting in precisions.items()},
               "cpu_bf16_support": list(compile_lib.cpu_bf16_support()), "params": first.count_params(),
               "framework_baseline_rss_gb": framework_baseline_gb, "latency": {}}
    precision_of = {name: v[3][0] for name, v in variants.items()}
    floors = _conv_floors(cfg, {precision_of[name]: model for name, model in reversed(models.items())}, rng)
    calls = {} if args.skip_conv_floor else {f"conv_floor/{k}": f for k, f in floors.items()}
    points = sorted(int(v) for v in args.points.split(","))
    padded, outputs = {}, {}
    for n in points:
        inputs, padded[n] = bench_steps.example(cfg, rng, n)
        outputs[n] = {m: f(inputs)["flow_mps"].numpy()[0, :n] for m, f in forwards.items()}  # the real points
        calls.update({f"{n}/{m}": (lambda f=f, x=inputs: f(x)) for m, f in forwards.items()})
    if args.train_points:
        labelled, padded["train"] = bench_steps.example(cfg, rng, args.train_points, labels=True)
        for p, setting in precisions.items():  # the Trainer builds its model from the config: one call per precision
            names = {name: modes[name] for name, v in variants.items() if v[2] == p}
            steps = bench_steps.train_steps(replace_config(cfg, {"model.mixed_precision": setting}), names, labelled)
            calls.update({f"train/{name}": fn for name, fn in steps.items()})
    _report(results, _interleaved(calls, args.runs), args, modes, points, padded, outputs, precision_of)
    results["load_average_at_end"] = bench.load_average()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps(results["ratios"]))


if __name__ == "__main__":
    main()
