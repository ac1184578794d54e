"""bfloat16 convolutions (`model.mixed_precision=true`) against float32 on this CPU: speed and accuracy
(lab/tools/benchmark_bf16.py). `bf16_study` returns the sections, the heavy ones each from its own process so that one's
memory does not weigh on another:

  cpu            vendor and bfloat16 flags (`compile.cpu_bf16_support`), what model.mixed_precision=auto resolves to
                 here and why (mode hybrid, the CPU default).
  convolution    one 3x3 64 -> 64 convolution (rows C-F's shape, `CONV_SHAPE`) of a 2 x 512 x 512 grid in float32 and
                 bfloat16, `runs` calls each alternately after a warm-up call each, in a child with ONEDNN_VERBOSE=1:
                 oneDNN's own implementation name and exec time per call (the kernel alone, no TensorFlow around it)
                 and the wall time; and, in the same child, one call of the paper config's dense stages (rows C-V,
                 both frames, mode hybrid) forward and forward + gradient per precision after a warm-up call:
                 oneDNN's time summed by primitive, direction and implementation (where a training step's time goes).
  latency        lab/tools/benchmark_latency.py on the paper config, mode auto, float32 and bfloat16 variants with the
                 same (random) weights in one round robin: inference at each point count, the conv floors, the training
                 step at the first point count; and the flow difference of the two (max and mean, m/s).
  demo           the demo's data (tools/make_synthetic_data.py: `DEMO_SPLITS`, as `make demo`),
                 configs/synthetic_cpu.yaml trained for `train_steps` steps in float32 and in bfloat16 from the same
                 seed (tools/train.py), each evaluated (tools/eval.py); and the float32-trained checkpoint evaluated
                 with bfloat16 convolutions (the inference-only cost on trained weights). Moving and stationary mean
                 errors (all classes, m/s) and their relative differences.
  summary        float32 / bfloat16 time ratios (> 1: bfloat16 faster) and the flow and error differences (`summary`).

The two trainings run one after the other, not interleaved: their wall times are context, the training-step ratio is
the latency section's.
"""
from __future__ import annotations

import contextlib
import ctypes
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Callable, Iterable, Mapping

from lab import children
from lab.paths import ROOT

PAPER_CONFIG = os.path.join(ROOT, "configs", "fastflow3d_waymo.yaml")
DEMO_CONFIG = os.path.join(ROOT, "configs", "synthetic_cpu.yaml")
# The demo's data (tools/demo.py defaults): (split, segments, seed); DEMO_FRAMES frames per segment.
DEMO_SPLITS = (("train", 4, 100), ("val", 2, 900))
DEMO_FRAMES = 12
PRECISION_SETTINGS = {"float32": "false", "bfloat16": "true"}  # -> model.mixed_precision
DEMO_METRICS = ("all/moving/mean_l2_mps", "all/stationary/mean_l2_mps")
# One of the convolutions of rows C-F: NHWC input [2, 512, 512, 64] (both frames), 3x3 kernel 64 -> 64, stride 1.
CONV_SHAPE = (2, 512, 512, 64)
ONEDNN_DATA_TYPES = {"f32": "float32", "bf16": "bfloat16"}  # oneDNN's names -> TensorFlow's
OUTPUT_TAIL_CHARS = children.OUTPUT_TAIL_CHARS


def run_tool(tool: str, args: Iterable[str], env: Mapping | None = None) -> str:
    """Runs `tool` (its path from the repository root: tools/train.py, lab/tools/benchmark_latency.py) with this
    interpreter in the repository root, `env` added to this process's environment; returns its stdout and stderr. A
    tool that fails raises `children.ChildError` with their tail."""
    proc = subprocess.run([sys.executable, os.path.join(ROOT, tool), *args], capture_output=True, text=True,
                          cwd=ROOT, env={**os.environ, **(env or {})})
    output = proc.stdout + proc.stderr
    if proc.returncode != 0:
        raise children.ChildError(f"{tool} failed (exit {proc.returncode}):\n{output[-OUTPUT_TAIL_CHARS:]}")
    return output


# -- cpu ---------------------------------------------------------------------------------------------------------------
def cpu_section() -> dict:
    """`ff3d_tf.cpu.describe()` with the bfloat16 flags and what model.mixed_precision=auto resolves to and why."""
    from ff3d_tf import cpu
    from ff3d_tf.model import compile as compile_lib
    vendor, flags = compile_lib.cpu_bf16_support()
    precision, reason = compile_lib.resolve_precision("auto", "hybrid", "CPU")
    return {**cpu.describe(), "bf16_flags": list(flags), "auto_resolves_to": precision, "auto_reason": reason}


# -- convolution: oneDNN's verbose lines -------------------------------------------------------------------------------
@contextlib.contextmanager
def stdout_lines(into: list):
    """Whatever this process writes to its standard output (file descriptor 1) inside the block, the C libraries'
    output included (oneDNN's verbose lines), goes to a temporary file instead; its lines are appended to `into` when
    the block ends."""
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    libc.fflush(None)
    saved = os.dup(1)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 1)
        try:
            yield into
        finally:
            sys.stdout.flush()
            libc.fflush(None)
            os.dup2(saved, 1)
            os.close(saved)
            captured.seek(0)
            into.extend(captured.read().decode(errors="replace").splitlines())


def onednn_exec_fields(lines: Iterable[str]) -> list[list[str]]:
    """The comma-separated fields of oneDNN's verbose lines of executed CPU primitives among `lines`:
    onednn_verbose,v1,primitive,exec,cpu,<primitive>,<implementation>,<direction>,<descriptors>,...,<ms>."""
    fields = (line.split(",") for line in lines)
    return [f for f in fields if len(f) > 8 and f[3:5] == ["exec", "cpu"]]


def convolution_kernels(lines: Iterable[str]) -> dict[str, list[tuple[str, float]]]:
    """{data type (TensorFlow's name): [(oneDNN implementation, exec ms) per call]} of the convolutions in `lines`;
    the data type is the source tensor's."""
    kernels = {}
    for fields in onednn_exec_fields(lines):
        if fields[5] == "convolution":
            data_type = re.search(r"src:(\w+):", fields[8]).group(1)
            kernels.setdefault(ONEDNN_DATA_TYPES.get(data_type, data_type), []).append((fields[6], float(fields[-1])))
    return kernels


def onednn_ms_by_primitive(lines: Iterable[str]) -> dict:
    """{"total_ms", "by_primitive": {"<primitive> <direction> <implementation>": summed exec ms, largest first}} of
    the oneDNN exec lines in `lines`."""
    by_primitive = {}
    for fields in onednn_exec_fields(lines):
        key = f"{fields[5]} {fields[7]} {fields[6]}"
        by_primitive[key] = by_primitive.get(key, 0.0) + float(fields[-1])
    return {"total_ms": sum(by_primitive.values()),
            "by_primitive": dict(sorted(by_primitive.items(), key=lambda kv: -kv[1]))}


def convolution_timings(lines: Iterable[str], wall_ms: Mapping[str, list]) -> dict:
    """{data type: {"onednn_implementation", "onednn_exec_median_ms", "wall_median_ms"}} of the timed calls' oneDNN
    lines and wall times ({data type: ms per call}), and "bfloat16_speedup": float32 exec median / bfloat16's (> 1:
    bfloat16 faster) where both ran in oneDNN."""
    out = {}
    for name, readings in convolution_kernels(lines).items():
        out[name] = {"onednn_implementation": sorted({impl for impl, _ in readings}),
                     "onednn_exec_median_ms": statistics.median(ms for _, ms in readings),
                     "wall_median_ms": statistics.median(wall_ms[name])}
    if "float32" in out and "bfloat16" in out:
        out["bfloat16_speedup"] = out["float32"]["onednn_exec_median_ms"] / out["bfloat16"]["onednn_exec_median_ms"]
    return out


def convolution_child(runs: int) -> dict:
    """(In a child with ONEDNN_VERBOSE=1.) The convolution section (module docstring)."""
    import numpy as np
    import tensorflow as tf
    from ff3d_tf.config import load_config, replace_config
    from ff3d_tf.model import build_model
    from lab import bench
    rng = np.random.default_rng(0)
    x = tf.constant(rng.uniform(0, 1, CONV_SHAPE).astype(np.float32))
    k = tf.constant(rng.normal(0, 0.05, (3, 3, CONV_SHAPE[-1], CONV_SHAPE[-1])).astype(np.float32))
    calls = {}
    for dtype in (tf.float32, tf.bfloat16):
        conv = tf.function(lambda a, b: tf.nn.conv2d(a, b, 1, "SAME"))
        calls[dtype.name] = bench.fetched(lambda conv=conv, xs=tf.cast(x, dtype), ks=tf.cast(k, dtype): conv(xs, ks))
    lines = []
    for call in calls.values():
        call()  # warm-up: tracing, oneDNN primitive creation
    with stdout_lines(lines):
        readings = bench.round_robin(calls, runs, warmup=0)
    wall_ms = {name: [r["ms"] for r in rows] for name, rows in readings.items()}
    result = {"shape_nhwc": list(CONV_SHAPE), "kernel": [3, 3, CONV_SHAPE[-1], CONV_SHAPE[-1]], "runs": runs,
              "dense_stages_onednn_ms": {}}
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
            phase_lines = []
            with stdout_lines(phase_lines):
                fetched()
            result["dense_stages_onednn_ms"][f"{name}/{phase}"] = onednn_ms_by_primitive(phase_lines)
    return {**result, **convolution_timings(lines, wall_ms)}


def convolution_section(runs: int) -> dict:
    """`convolution_child` in a fresh process with ONEDNN_VERBOSE=1."""
    return children.run_child(f"{__name__}:convolution_child", {"runs": runs}, env={"ONEDNN_VERBOSE": "1"},
                              what="the convolution section")


# -- latency, demo -----------------------------------------------------------------------------------------------------
def latency_section(points: list[int], runs: int, work_dir: str) -> dict:
    """lab/tools/benchmark_latency.py's JSON: the paper config, mode auto, float32 and bfloat16, `runs` rounds,
    inference at each of `points`, the training step at the first."""
    path = os.path.join(work_dir, "latency.json")
    run_tool("lab/tools/benchmark_latency.py", ["--config", PAPER_CONFIG, "--modes", "auto", "--precisions",
                                               "float32,bfloat16", "--points", ",".join(map(str, points)), "--runs",
                                               str(runs), "--train_points", str(points[0]), "--out", path])
    with open(path) as f:
        return json.load(f)


def _demo_metrics(path: str) -> dict:
    with open(path) as f:
        metrics = json.load(f)
    return {k: metrics[k] for k in DEMO_METRICS}


def relative_differences(cases: Mapping[str, Mapping], reference: Mapping) -> dict:
    """{case: {metric: (its value - the reference's) / the reference's}} for each metric of `reference`."""
    return {case: {k: (metrics[k] - reference[k]) / reference[k] for k in reference} for case, metrics in cases.items()}


def demo_section(train_steps: int, work_dir: str, log_fn: Callable[[str], None] = print) -> dict:
    """The demo section (module docstring); data, models and evaluations under `work_dir` (the tools skip the data
    segments that exist and resume finished trainings)."""
    data = os.path.join(work_dir, "data")
    for split, segments, seed in DEMO_SPLITS:
        run_tool("tools/make_synthetic_data.py", ["--out_dir", os.path.join(data, split), "--num_segments",
                                                  str(segments), "--frames_per_segment", str(DEMO_FRAMES), "--seed",
                                                  str(seed)])
    common = ["--config", DEMO_CONFIG, "--set", f"train.num_steps={train_steps}"]
    result = {"config": os.path.relpath(DEMO_CONFIG, ROOT), "train_steps": train_steps,
              "data": {split: {"segments": n, "frames_per_segment": DEMO_FRAMES, "seed": seed}
                       for split, n, seed in DEMO_SPLITS}, "runs": {}}

    def evaluate(flags: list[str], checkpoint: str, name: str) -> dict:
        out_dir = os.path.join(work_dir, f"eval_{name}")
        run_tool("tools/eval.py", [*flags, "--data_dir", os.path.join(data, "val"), "--checkpoint", checkpoint,
                                   "--out_dir", out_dir])
        return _demo_metrics(os.path.join(out_dir, "metrics.json"))
    for name, setting in PRECISION_SETTINGS.items():
        model_dir = os.path.join(work_dir, f"model_{name}")
        flags = common + ["--set", f"model.mixed_precision={setting}"]
        start = time.perf_counter()
        log = run_tool("tools/train.py", [*flags, "--data_dir", os.path.join(data, "train"), "--model_dir", model_dir])
        train_s = time.perf_counter() - start
        rates = [float(r) for r in re.findall(r" ([0-9.]+) steps/s", log)]
        result["runs"][name] = {"train_wall_s": train_s, "last_logged_steps_per_s": rates[-1] if rates else None,
                                "metrics": evaluate(flags, model_dir, name)}
        log_fn(f"demo {name}: {json.dumps(result['runs'][name])}")
    # The float32-trained weights run with bfloat16 convolutions: the cost of bfloat16 inference alone.
    case = "float32_weights_bfloat16_inference"
    result[case] = {"metrics": evaluate(common + ["--set", "model.mixed_precision=true"],
                                        os.path.join(work_dir, "model_float32"), case)}
    result["relative_difference_vs_float32"] = relative_differences(
        {"trained_bfloat16": result["runs"]["bfloat16"]["metrics"], case: result[case]["metrics"]},
        result["runs"]["float32"]["metrics"])
    return result


# -- summary -----------------------------------------------------------------------------------------------------------
def summary(results: Mapping) -> dict:
    """The ratios of the sections in `results`: float32 time / bfloat16 time (> 1: bfloat16 faster) of inference per
    point count, the training step and the conv floor, by the medians and by the minima (on a loaded machine the
    minima are the calls least disturbed by others); the largest point count's time over the smallest's per
    precision; the flow difference of bfloat16 from float32; the demo's relative error differences; the single
    convolution's and the dense stages' oneDNN time ratios."""
    out = {}
    lat = results.get("latency")
    if lat:
        f32, b16 = "auto/float32", "auto/bfloat16"
        points = sorted(lat["latency"], key=int)
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


def bf16_study(points: list[int], runs: int, conv_runs: int, train_steps: int, demo: bool, work_dir: str | None,
               command: str = "", note: str = "", log_fn: Callable[[str], None] = print) -> dict:
    """{"command", "note", "cpu", "convolution", "latency", "demo" (with `demo`), "summary"}: the JSON of
    lab/tools/benchmark_bf16.py. `work_dir`: the latency JSON, the demo's data and models (None: a temporary folder)."""
    with tempfile.TemporaryDirectory() as tmp:
        work = work_dir or tmp
        os.makedirs(work, exist_ok=True)
        results = {"command": command, "note": note, "cpu": cpu_section()}
        log_fn(f"cpu: {json.dumps(results['cpu'])}")
        results["convolution"] = convolution_section(conv_runs)
        log_fn(f"convolution: {json.dumps(results['convolution'])}")
        results["latency"] = latency_section(points, runs, work)
        log_fn(f"latency: {json.dumps(summary(results))}")
        if demo:
            results["demo"] = demo_section(train_steps, work, log_fn)
        results["summary"] = summary(results)
    return results
