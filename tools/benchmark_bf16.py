"""bfloat16 convolutions (`model.mixed_precision=true`) against float32 on this CPU: speed and accuracy. JSON out.

python tools/benchmark_bf16.py --out benchmarks/bf16_cpu.json [--runs 5] [--train_steps 300] [--skip_demo]

Sections, each from its own process (subprocesses of the project's tools), so one's memory does not weigh on another:
  cpu            vendor and bfloat16 flags (`compile.cpu_bf16_support`), what model.mixed_precision=auto resolves to
                 here and why (mode hybrid, the CPU default).
  convolution    one 3x3 64 -> 64 convolution (rows C-F's shape) of a 2 x 512 x 512 grid in float32 and bfloat16,
                 --conv_runs calls each alternately, in a child process with ONEDNN_VERBOSE=1: oneDNN's own
                 implementation name and exec time per call (the kernel alone, no TensorFlow around it); and, in
                 the same child, one call of the paper config's dense stages (rows C-V, both frames, mode hybrid)
                 forward and forward + gradient per precision: oneDNN's time summed by primitive, direction and
                 implementation (where a training step's time goes).
  latency        tools/benchmark_latency.py on the paper config, mode auto, float32 and bfloat16 variants with the same
                 (random) weights in one round robin: inference at 32K and 1M points, the conv floors, the training
                 step at 32K; and the flow difference of the two at both point counts (max and mean, m/s).
  demo           the demo's data (tools/make_synthetic_data.py: 4 training and 2 validation segments of 12 frames,
                 seeds 100 and 900, as `make demo`), configs/synthetic_cpu.yaml trained for --train_steps steps in
                 float32 and in bfloat16 from the same seed (tools/train.py), each evaluated (tools/eval.py); and the
                 float32-trained checkpoint evaluated with bfloat16 convolutions (the inference-only cost on trained
                 weights). Moving and stationary mean errors (all classes, m/s) and their relative differences.
  summary        the ratios the issue's targets name.
The two trainings run one after the other, not interleaved: their wall times are context, the training-step ratio is
the latency section's.
"""
import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

import _common  # noqa: F401  (puts the checkout on sys.path)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
PAPER_CONFIG = os.path.join(ROOT, "configs", "fastflow3d_waymo.yaml")
DEMO_CONFIG = os.path.join(ROOT, "configs", "synthetic_cpu.yaml")
# The demo's data (tools/demo.py defaults): (split, segments, seed); 12 frames per segment.
DEMO_SPLITS = (("train", 4, 100), ("val", 2, 900))
DEMO_FRAMES = 12
PRECISION_SETTINGS = {"float32": "false", "bfloat16": "true"}  # -> model.mixed_precision
DEMO_METRICS = ("all/moving/mean_l2_mps", "all/stationary/mean_l2_mps")
# One of the convolutions of rows C-F: NHWC input [2, 512, 512, 64] (both frames), 3x3 kernel 64 -> 64, stride 1.
CONV_SHAPE = (2, 512, 512, 64)


def _args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="benchmarks/bf16_cpu.json")
    p.add_argument("--runs", type=int, default=5, help="round-robin rounds of the latency section")
    p.add_argument("--points", default="32000,1000000")
    p.add_argument("--conv_runs", type=int, default=5)
    p.add_argument("--train_steps", type=int, default=300, help="demo training steps per precision")
    p.add_argument("--skip_demo", action="store_true")
    p.add_argument("--note", default="", help="context recorded in the JSON (machine load, commit)")
    p.add_argument("--work_dir", default=None, help="demo data and models (default: a temporary directory; "
                                                    "given, existing data and finished runs are reused)")
    p.add_argument("--conv_child", action="store_true", help=argparse.SUPPRESS)  # internal: the convolution child
    return p.parse_args()


def _run(cmd: list[str], env: dict | None = None) -> str:
    """Runs a tool, streaming nothing; its stdout and stderr on success, exit with their tail on failure."""
    proc = subprocess.run([sys.executable] + cmd, capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, **(env or {})})
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd[:1])} failed (exit {proc.returncode}):\n{(proc.stdout + proc.stderr)[-4000:]}")
    return proc.stdout + proc.stderr


def cpu_section() -> dict:
    from ff3d_tf import cpu
    from ff3d_tf.model import compile as compile_lib
    vendor, flags = compile_lib.cpu_bf16_support()
    precision, reason = compile_lib.resolve_precision("auto", "hybrid", "CPU")
    return {**cpu.describe(), "bf16_flags": list(flags), "auto_resolves_to": precision, "auto_reason": reason}


def conv_child(runs: int) -> None:
    """(In the child, ONEDNN_VERBOSE=1.) One warm-up then `runs` calls per dtype, alternately; prints the wall times
    as a JSON line; then the dense stages once per (precision, phase) after a warm-up call, between "PHASE name" and
    "END" lines. oneDNN prints its own lines around them."""
    import numpy as np
    import tensorflow as tf
    from ff3d_tf.config import load_config, replace_config
    from ff3d_tf.model import build_model
    rng = np.random.default_rng(0)
    x = tf.constant(rng.uniform(0, 1, CONV_SHAPE).astype(np.float32))
    k = tf.constant(rng.normal(0, 0.05, (3, 3, CONV_SHAPE[-1], CONV_SHAPE[-1])).astype(np.float32))
    calls = {}
    for dtype in (tf.float32, tf.bfloat16):
        xs, ks = tf.cast(x, dtype), tf.cast(k, dtype)
        conv = tf.function(lambda a, b: tf.nn.conv2d(a, b, 1, "SAME"))
        calls[dtype.name] = (lambda conv=conv, xs=xs, ks=ks: conv(xs, ks).numpy())
        calls[dtype.name]()
    ms = {name: [] for name in calls}
    for _ in range(runs):
        for name, fn in calls.items():
            t = time.perf_counter()
            fn()
            ms[name].append(1e3 * (time.perf_counter() - t))
    print("WALL_MS " + json.dumps(ms), flush=True)
    cfg = load_config(PAPER_CONFIG)
    g = cfg.grid
    bev = tf.constant(rng.uniform(0, 1, (2, g.num_pillars_y, g.num_pillars_x, cfg.model.point_feature_dim)).astype(
        np.float32))
    for name, setting in (("float32", False), ("bfloat16", True)):
        model = build_model(replace_config(cfg, {"model.mixed_precision": setting}), "hybrid")

        @tf.function
        def forward(x, model=model):
            return model.dense_stages(x)

        @tf.function
        def gradient(x, model=model):
            with tf.GradientTape() as tape:
                loss = tf.reduce_mean(tf.square(tf.cast(model.dense_stages(x, training=True), tf.float32)))
            return tape.gradient(loss, model.trainable_variables)
        for phase, fn in (("inference", forward), ("training", gradient)):
            def fetched(fn=fn):  # results on the host (the point stages' variables have no gradient here: None)
                return [t.numpy() for t in tf.nest.flatten(fn(bev)) if t is not None]
            fetched()  # warm-up: tracing, oneDNN primitive creation
            print(f"PHASE {name}/{phase}", flush=True)
            fetched()
            print("END", flush=True)


def convolution_section(runs: int) -> dict:
    import numpy as np
    out = _run([os.path.abspath(__file__), "--conv_child", "--conv_runs", str(runs)], env={"ONEDNN_VERBOSE": "1"})
    wall = json.loads(next(line for line in out.splitlines() if line.startswith("WALL_MS "))[len("WALL_MS "):])
    # onednn_verbose,v1,primitive,exec,cpu,convolution,<implementation>,<prop>,<src/wei/dst descriptors>,...,<ms>
    kernels = {}
    lines = out.splitlines()
    single = lines[:next(i for i, line in enumerate(lines) if line.startswith("WALL_MS "))]  # not the dense stages
    for line in single:
        fields = line.split(",")
        if len(fields) > 8 and fields[3:6] == ["exec", "cpu", "convolution"]:
            dtype = re.search(r"src:(\w+):", line).group(1)
            kernels.setdefault({"f32": "float32", "bf16": "bfloat16"}.get(dtype, dtype), []).append(
                (fields[6], float(fields[-1])))
    result = {"shape_nhwc": list(CONV_SHAPE), "kernel": [3, 3, CONV_SHAPE[-1], CONV_SHAPE[-1]], "runs": runs,
              "dense_stages_onednn_ms": _dense_stage_primitives(out)}
    for name, readings in kernels.items():
        timed = readings[1:]  # the first is the warm-up call
        result[name] = {"onednn_implementation": sorted({impl for impl, _ in readings}),
                        "onednn_exec_median_ms": float(np.median([t for _, t in timed])),
                        "wall_median_ms": float(np.median(wall[name]))}
    if "float32" in result and "bfloat16" in result:
        result["bfloat16_speedup"] = result["float32"]["onednn_exec_median_ms"] / result["bfloat16"][
            "onednn_exec_median_ms"]
    return result


def _dense_stage_primitives(out: str) -> dict:
    """{precision/phase: {"total_ms", "by_primitive": {"kind direction implementation": ms}}} from the child's
    oneDNN lines between its PHASE and END markers."""
    result, phase = {}, None
    for line in out.splitlines():
        if line.startswith("PHASE "):
            phase = line.split()[1]
            result[phase] = {}
        elif line.startswith("END"):
            phase = None
        elif phase is not None:
            fields = line.split(",")
            if len(fields) > 8 and fields[3:5] == ["exec", "cpu"]:
                key = f"{fields[5]} {fields[7]} {fields[6]}"
                result[phase][key] = result[phase].get(key, 0.0) + float(fields[-1])
    return {p: {"total_ms": sum(v.values()), "by_primitive": dict(sorted(v.items(), key=lambda kv: -kv[1]))}
            for p, v in result.items()}


def latency_section(args, work: str) -> dict:
    path = os.path.join(work, "latency.json")
    _run([os.path.join(HERE, "benchmark_latency.py"), "--config", PAPER_CONFIG, "--modes", "auto", "--precisions",
          "float32,bfloat16", "--points", args.points, "--runs", str(args.runs), "--train_points",
          args.points.split(",")[0], "--out", path])
    with open(path) as f:
        return json.load(f)


def _metrics(path: str) -> dict:
    with open(path) as f:
        m = json.load(f)
    return {k: m[k] for k in DEMO_METRICS}


def demo_section(args, work: str) -> dict:
    data = os.path.join(work, "data")
    for split, segments, seed in DEMO_SPLITS:
        _run([os.path.join(HERE, "make_synthetic_data.py"), "--out_dir", os.path.join(data, split),
              "--num_segments", str(segments), "--frames_per_segment", str(DEMO_FRAMES), "--seed", str(seed)])
    common = ["--config", DEMO_CONFIG, "--set", f"train.num_steps={args.train_steps}"]
    result = {"config": os.path.relpath(DEMO_CONFIG, ROOT), "train_steps": args.train_steps,
              "data": {split: {"segments": n, "frames_per_segment": DEMO_FRAMES, "seed": seed}
                       for split, n, seed in DEMO_SPLITS}, "runs": {}}
    for name, setting in PRECISION_SETTINGS.items():
        model_dir = os.path.join(work, f"model_{name}")
        flags = common + ["--set", f"model.mixed_precision={setting}"]
        t = time.perf_counter()
        log = _run([os.path.join(HERE, "train.py"), *flags, "--data_dir", os.path.join(data, "train"),
                    "--model_dir", model_dir])
        train_s = time.perf_counter() - t
        rates = [float(r) for r in re.findall(r" ([0-9.]+) steps/s", log)]
        _run([os.path.join(HERE, "eval.py"), *flags, "--data_dir", os.path.join(data, "val"), "--checkpoint",
              model_dir, "--out_dir", os.path.join(work, f"eval_{name}")])
        result["runs"][name] = {"train_wall_s": train_s, "last_logged_steps_per_s": rates[-1] if rates else None,
                                "metrics": _metrics(os.path.join(work, f"eval_{name}", "metrics.json"))}
        print(f"demo {name}: {json.dumps(result['runs'][name])}", flush=True)
    # The float32-trained weights run with bfloat16 convolutions: the cost of bfloat16 inference alone.
    _run([os.path.join(HERE, "eval.py"), *common, "--set", "model.mixed_precision=true", "--data_dir",
          os.path.join(data, "val"), "--checkpoint", os.path.join(work, "model_float32"), "--out_dir",
          os.path.join(work, "eval_float32_weights_bfloat16_inference")])
    result["float32_weights_bfloat16_inference"] = {"metrics": _metrics(os.path.join(
        work, "eval_float32_weights_bfloat16_inference", "metrics.json"))}
    ref = result["runs"]["float32"]["metrics"]
    result["relative_difference_vs_float32"] = {
        case: {k: (m[k] - ref[k]) / ref[k] for k in DEMO_METRICS}
        for case, m in (("trained_bfloat16", result["runs"]["bfloat16"]["metrics"]),
                        ("float32_weights_bfloat16_inference",
                         result["float32_weights_bfloat16_inference"]["metrics"]))}
    return result


def summary(results: dict) -> dict:
    out = {}
    lat = results.get("latency")
    if lat:
        f32, b16 = "auto/float32", "auto/bfloat16"
        points = sorted(lat["latency"], key=int)
        # float32 time / bfloat16 time (> 1: bfloat16 faster), of the medians and of the minima (on a loaded
        # machine the minima are the calls least disturbed by others).
        for stat in ("median", "min"):
            ms = {n: {v: lat["latency"][n][v][f"{stat}_ms"] for v in (f32, b16)} for n in points}
            out[f"inference_speedup_bfloat16_{stat}"] = {n: ms[n][f32] / ms[n][b16] for n in points}
            out[f"t_max_over_t_min_points_{stat}"] = {v: ms[points[-1]][v] / ms[points[0]][v] for v in (f32, b16)}
            if "train_step" in lat:
                out[f"train_step_speedup_bfloat16_{stat}"] = (lat["train_step"][f32][f"{stat}_ms"] /
                                                              lat["train_step"][b16][f"{stat}_ms"])
            if "graph/bfloat16" in lat.get("conv_floor", {}):
                out[f"conv_floor_speedup_bfloat16_{stat}"] = (lat["conv_floor"]["graph"][f"{stat}_ms"] /
                                                              lat["conv_floor"]["graph/bfloat16"][f"{stat}_ms"])
        out["load_average"] = {"start": lat["load_average_at_start"], "end": lat["load_average_at_end"]}
        out["flow_difference_bfloat16_vs_float32_mps"] = {
            n: {"max": lat["latency"][n][b16][f"max_flow_diff_norm_vs_{f32}_mps"],
                "mean": lat["latency"][n][b16][f"mean_flow_diff_norm_vs_{f32}_mps"],
                "mean_flow_norm": lat["latency"][n][f32]["mean_flow_norm_mps"],
                # Random Glorot weights give flows of tens of m/s on the paper grid: the relative size is the measure.
                "mean_over_mean_flow_norm": lat["latency"][n][b16][f"mean_flow_diff_norm_vs_{f32}_mps"] /
                lat["latency"][n][f32]["mean_flow_norm_mps"]} for n in points}
    if "demo" in results:
        out["demo_relative_difference_vs_float32"] = results["demo"]["relative_difference_vs_float32"]
    conv = results.get("convolution", {})
    if "bfloat16_speedup" in conv:
        out["single_convolution_speedup_bfloat16"] = conv["bfloat16_speedup"]
    dense = conv.get("dense_stages_onednn_ms", {})
    for phase in ("inference", "training"):
        if f"float32/{phase}" in dense and f"bfloat16/{phase}" in dense:
            out[f"dense_stages_onednn_speedup_bfloat16_{phase}"] = (dense[f"float32/{phase}"]["total_ms"] /
                                                                   dense[f"bfloat16/{phase}"]["total_ms"])
    return out


def main():
    args = _args()
    if args.conv_child:
        conv_child(args.conv_runs)
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work_dir or tmp
        os.makedirs(work, exist_ok=True)
        results = {"command": " ".join(["tools/benchmark_bf16.py"] + sys.argv[1:]), "note": args.note,
                   "cpu": cpu_section()}
        print(f"cpu: {json.dumps(results['cpu'])}", flush=True)
        results["convolution"] = convolution_section(args.conv_runs)
        print(f"convolution: {json.dumps(results['convolution'])}", flush=True)
        results["latency"] = latency_section(args, work)
        print(f"latency: {json.dumps(summary(results))}", flush=True)
        if not args.skip_demo:
            results["demo"] = demo_section(args, work)
        results["summary"] = summary(results)
    print(json.dumps(results["summary"], indent=1))
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
