"""Where the training step's time and memory go on a CPU, per compile mode and per process setting, before and after
the CPU changes of `ff3d_tf.model.compile` and `ff3d_tf.cpu` (lab/tools/benchmark_cpu_step.py).

Every reading comes from a fresh child process (`lab.children.run_child`, pinned cores), one *variant* each:

  settings  "before": the process as TensorFlow starts it by itself on the emulated CPU (`ff3d_tf.cpu.EMULATIONS`
            [cap]: on an AVX2-only CPU, oneDNN off), the point encoding of compile mode hybrid in one XLA program
            (the execution plan's point_programs "one"), the convolutions as Keras has them and row V apart from the
            head (`PLAN_FORMS["plain"]`), `model.compile=auto` by the rule of before the per-job
            choice (hybrid on every CPU);
            "after": the start-up environment the tools choose for the job (`ff3d_tf.cpu.startup_environment`, under
            the same ISA caps), the clouds' point programs apart ("per_cloud"), the model's own convolution forms
            ("fast"), `auto` by `compile_lib.resolve_compile_mode` for the job;
            "after_onednn" (on request): "after" with TensorFlow's oneDNN operations on;
            "after_remat" (on request): "after" with the encoder's activations recomputed in the backward
            (`model.remat_encoder=true`);
            "after_plain_convolutions" (on request): "after" with the convolutions of "before" (what the forms save);
            "after_default_arenas" (on request): "after" without the start-up's malloc arena limit (not measured
            for a job whose start-up has none);
            "after_huge_pages" (on request, training only): "after" with glibc asked for transparent huge pages;
            "after_no_pool", "after_eigen", "after_arenas" (on request): "after" without TensorFlow's BFC pool, with
            the AVX2 training start-up (NO_POOL, `cpu.AVX2_STARTUP`), or with two glibc arenas, on a CPU where oneDNN
            is on by default; "after_bfloat16", "after_remat_bfloat16": "after" and "after_remat" in bfloat16.
  job       "train" (the Trainer's own step: forward, loss, backward, Adam; batch 1, the process's peak resident
            memory) or "forward" (the compiled forward at each point count, in one process, round robin).
  mode      `model.compile`: auto, hybrid, xla, none.

A training child also times the step's parts alone (`stage_times`, same process, after the steps): the point stages
(rows A-B and W-Z) forward and forward + backward, the convolutions (rows C-V) forward and forward + backward, the
BatchNorm kernels inside the latter (profiler, TensorFlow kernels only), Adam's update, the loss; what the parts leave
of the whole step is the rest (copies between TensorFlow kernels and XLA programs, program launches, the tape).

No PyTorch here: the PyTorch FastFlow3D figures of the comparison are the issue's, measured on a real Zen 3
(benchmarks/cpu_step_peer.json); `projection` scales ff3d_tf's figures there by this run's ratios.
"""
from __future__ import annotations

import json
import os
from typing import Callable, Mapping, Sequence

from ff3d_tf import cpu
from lab import bench, children, paths

MODULE = __name__
SETTINGS = ("before", "after")
# A setting measured on request (--settings): "after" with TensorFlow's oneDNN operations on (TF_ENABLE_ONEDNN_OPTS=1,
# what the start-up does not choose on an AVX2-only CPU): the measurement behind that choice and behind
# `compile_lib.AUTO_CPU`'s "onednn_avx2" entries.
# "after_remat": "after" with `model.remat_encoder=true` (REMAT_OVERRIDE), the training memory it saves and its time.
# "after_default_arenas": "after" with glibc's own number of malloc arenas (MALLOC_ARENA_MAX left out), what the
# start-up's limit saves.
# "after_plain_convolutions": "after" with `PLAN_FORMS["plain"]`, what the model's convolution forms
# save.
# "after_huge_pages": "after" with glibc asked for transparent huge pages for the blocks it maps (HUGE_PAGES, set
# before the child starts, as glibc reads it only then): the training program's temporaries, one block mapped afresh
# every step, fault in by huge pages. Measured and not taken into the start-up (docs/benchmarks.md).
# "after_no_pool": "after" with every tensor from malloc (TF_ONEDNN_USE_SYSTEM_ALLOCATOR=1: not the oneDNN CPU
# allocator's BFC pool; TensorFlow's own CPU allocator not a pool either) and two glibc arenas (what the AVX2 training
# start-up has) while oneDNN's operations stay on; "after_eigen": "after" with the AVX2
# training start-up itself (`cpu.AVX2_STARTUP["train"]`: oneDNN off, two arenas): what each would give a CPU on which
# TensorFlow turns oneDNN on by itself (AVX-512 VNNI/BF16, AMX).
# "after_arenas": "after" with two glibc arenas (the pool kept).
# "after_bfloat16", "after_remat_bfloat16": "after" and "after_remat" with `model.mixed_precision=true`.
ALL_SETTINGS = SETTINGS + ("after_onednn", "after_remat", "after_default_arenas", "after_plain_convolutions",
                           "after_huge_pages", "after_no_pool", "after_eigen", "after_arenas", "after_bfloat16",
                           "after_remat_bfloat16")
REMAT_SETTINGS = ("after_remat", "after_remat_bfloat16")
BFLOAT16_SETTINGS = ("after_bfloat16", "after_remat_bfloat16")
BFLOAT16_OVERRIDE = "model.mixed_precision=true"
TWO_ARENAS = {"MALLOC_ARENA_MAX": "2"}
NO_POOL = {"TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "1", "TF_CPU_ALLOCATOR_USE_BFC": "false", "MALLOC_ARENA_MAX": "2"}
HUGE_PAGES = {"GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}
# The settings that differ from "after" in the environment alone: not measured for a job whose start-up they leave as
# "after" has it; and the settings measured for some jobs only.
ENVIRONMENT_SETTINGS = ("after_onednn", "after_default_arenas", "after_no_pool", "after_eigen", "after_arenas")
SETTING_JOBS = {"after_huge_pages": ("train",)}
# What the settings and the emulations set: taken out of a child's inherited environment, recorded in its reading.
KNOBS = tuple(sorted({k for e in cpu.EMULATIONS.values() for k in e} | set(cpu.STARTUP_KEYS) | set(HUGE_PAGES) |
                    set(NO_POOL)))
REMAT_OVERRIDE = "model.remat_encoder=true"
JOBS = ("train", "forward")
MODES = ("auto", "hybrid", "xla", "none")
# The PyTorch FastFlow3D peer and ff3d_tf before this change as the issue measured them on an AMD Zen 3, and the
# issue's targets: the anchor of `projection`, which cannot be measured here (no torch).
PEER_FILE = paths.benchmark_file("cpu_step_peer.json")


def peer_figures(path: str = PEER_FILE) -> dict:
    """The issue's figures (benchmarks/cpu_step_peer.json): {"cpu", "peer", "ff3d_tf_before", "targets", "note"}."""
    with open(path) as f:
        return json.load(f)


PAPER_CONFIG = "configs/fastflow3d_waymo.yaml"

# -- the environment of a variant --------------------------------------------------------------------------------------
STARTUP_JOB = {"train": "train", "forward": "inference"}  # this study's jobs -> `cpu.startup_environment`'s
NO_CAP = "none"  # `cap` for this CPU's own kernels: "before" is then TensorFlow's own default on it


def variant_environment(setting: str, job: str, cap: str, base: Mapping | None = None) -> dict:
    """The environment of a child: `base` (default os.environ) without the keys the emulations and the start-up rule
    set, plus the caps of `cpu.EMULATIONS[cap]`, and for "after" with TensorFlow's oneDNN setting of the emulation
    replaced by what `cpu.startup_environment` chooses for `job` on this CPU under those caps."""
    base = dict(os.environ if base is None else base)
    env = {k: v for k, v in base.items() if k not in KNOBS}
    caps = dict(cpu.EMULATIONS[cap]) if cap != NO_CAP else {}
    if setting != "before":
        caps.pop("TF_ENABLE_ONEDNN_OPTS", None)
        caps.update(cpu.startup_environment(STARTUP_JOB[job], environ=caps))
    if setting == "after_onednn":
        caps["TF_ENABLE_ONEDNN_OPTS"] = "1"
    if setting == "after_default_arenas":
        caps.pop("MALLOC_ARENA_MAX", None)
    if setting == "after_huge_pages":
        caps.update(HUGE_PAGES)
    if setting == "after_no_pool":
        caps.update(NO_POOL)
    if setting == "after_arenas":
        caps.update(TWO_ARENAS)
    if setting == "after_eigen":
        caps.update(cpu.AVX2_STARTUP["train"])
    return {**env, **caps}


def resolved_mode(setting: str, mode: str, job: str, environment: Mapping) -> str:
    """The compile mode a variant runs: "auto" by the rule of `setting` (before: hybrid on every CPU; after:
    `compile_lib.resolve_compile_mode` for the job on the CPU class the child's `environment` gives)."""
    if mode != "auto":
        return mode
    if setting == "before":
        return "hybrid"
    from ff3d_tf.model import compile as compile_lib
    info = cpu.read_cpuinfo()
    flag = environment.get("TF_ENABLE_ONEDNN_OPTS")
    onednn = flag == "1" if flag is not None else bool(info and cpu.tensorflow_onednn_default(info, environment))
    kind = compile_lib.cpu_class(onednn, info, environment)
    return compile_lib.resolve_compile_mode(mode, "CPU", job=STARTUP_JOB[job], cpu_kind=kind)


# -- in the child ------------------------------------------------------------------------------------------------------
# The study's forms as changes of the execution plan the config resolves to (`ff3d_tf.model.plan`): "fast" keeps it,
# "plain" computes every row as Keras has it (the layout before the forms; the table's rows in the fused forward).
PLAN_FORMS = {"fast": {}, "plain": {"matmul_1x1": False, "stride2_phase_gradients": False, "u6_into_next_u1": False,
                                    "v_with_head": False, "decoder_chain": False}}


def _setup(config: str, overrides: Sequence[str], point_programs: str, convolution_forms: str):
    """(the config, the plan's changes) of a child."""
    from ff3d_tf.config import load_config
    return load_config(config or None, list(overrides)), {**PLAN_FORMS[convolution_forms],
                                                          "point_programs": point_programs}


def _header(mode: str) -> dict:
    from ff3d_tf import internals
    return {"cpu": cpu.describe(), "onednn_enabled": internals.onednn_enabled(), "mode": mode,
            "placement": children.placement()}


def train_child(config: str, overrides: list, mode: str, points: int, steps: int, warmup: int,
                point_programs: str, stages: bool, stage_runs: int, malloc_arena_max: str | None = None,
                convolution_forms: str = "fast") -> dict:
    """(In a child.) The Trainer's step in compile `mode` (resolved) on one labelled benchmark example: "step_ms" and
    "step_cpu_ms" of each of `steps` steps after `warmup`, "peak_rss_gb" (the process's peak resident memory from its
    start to the last step: libraries, compilation, every step), "steps_peak_rss_gb" (the peak of the timed steps
    alone, after the warm-up: what a training job holds from then on; None where the peak cannot be reset), and with
    `stages` the step's parts (`stage_times`).
    `malloc_arena_max`: applied before TensorFlow starts, as tools/_common.py does (`cpu.limit_malloc_arenas`)."""
    arenas = cpu.limit_malloc_arenas({"MALLOC_ARENA_MAX": malloc_arena_max or ""})
    import numpy as np
    from lab.training import bench_steps
    cfg, plan_changes = _setup(config, overrides, point_programs, convolution_forms)
    labelled, padded = bench_steps.example(cfg, np.random.default_rng(0), points, labels=True)
    step = bench.fetched(bench_steps.train_steps(cfg, {mode: mode}, labelled, plan_changes)[mode])
    bench.measure(step, 0, warmup)
    process_peak_gb = bench.proc_status("VmHWM")
    peak_reset = bench.reset_peak_rss()
    readings = bench.measure(step, steps, 0, reading=bench.timed_with_usage)
    steps_peak_gb = bench.proc_status("VmHWM")
    out = {**_header(mode), "points": points, "padded_points": padded, "point_programs": point_programs,
           "convolution_forms": convolution_forms,
           "malloc_arena_max": arenas, "step_ms": [r["ms"] for r in readings],
           "step_cpu_ms": [r["cpu_ms"] for r in readings], "step_sys_ms": [r["sys_ms"] for r in readings],
           "step_minor_faults": [r["minor_faults"] for r in readings],
           "peak_rss_gb": max(process_peak_gb, steps_peak_gb),
           "steps_peak_rss_gb": steps_peak_gb if peak_reset else None, "rss_after_gb": bench.proc_status("VmRSS")}
    out["step_median_ms"] = bench.middle(out["step_ms"])
    if stages:  # after the steps: the peak above is the step's alone
        out["stage_runs"] = stage_runs
        try:
            out["stages"] = stage_times(cfg, mode, labelled, stage_runs, plan_changes)
        except Exception as e:  # noqa: BLE001 -- the step's figures stand without the parts
            out["stages_error"] = f"{type(e).__name__}: {e}"
    return out


def forward_child(config: str, overrides: list, mode: str, points: list, runs: int, warmup: int,
                  point_programs: str, malloc_arena_max: str | None = None, convolution_forms: str = "fast") -> dict:
    """(In a child.) The compiled forward (`compiled_forward`, batch 1) in compile `mode` at each of `points`, round
    robin: {"forward_ms": {points: each call's ms}, "median_ms": {points: median}, "peak_rss_gb"}."""
    cpu.limit_malloc_arenas({"MALLOC_ARENA_MAX": malloc_arena_max or ""})
    import numpy as np
    from ff3d_tf.config import replace_config
    from ff3d_tf.model import build_model
    from ff3d_tf.model.forward import compiled_forward
    from lab.training import bench_steps
    from ff3d_tf.model.plan import resolve
    cfg, plan_changes = _setup(config, overrides, point_programs, convolution_forms)
    cfg1 = replace_config(cfg, {"train.global_batch_size": 1})
    model = build_model(cfg1, plan=resolve(cfg1.model, "inference", mode)[0].replace(**plan_changes))
    forward = compiled_forward(model, mode == "xla")
    rng = np.random.default_rng(0)
    inputs = {n: bench_steps.example(cfg, rng, n)[0] for n in points}
    calls = {str(n): bench.fetched(lambda x=x: forward(x)) for n, x in inputs.items()}
    readings = bench.round_robin(calls, runs, warmup, reading=bench.timed_with_usage)
    out = {**_header(mode), "point_programs": point_programs, "convolution_forms": convolution_forms,
           "forward_ms": {n: [r["ms"] for r in rs] for n, rs in readings.items()},
           "forward_cpu_ms": {n: [r["cpu_ms"] for r in rs] for n, rs in readings.items()}}
    out["median_ms"] = {n: bench.middle(v) for n, v in out["forward_ms"].items()}
    out["cpu_median_ms"] = {n: bench.middle(v) for n, v in out["forward_cpu_ms"].items()}
    out["peak_rss_gb"] = bench.proc_status("VmHWM")
    return out


BN_OP_TYPES = ("FusedBatchNorm", "BatchNorm")  # substrings of the op types counted as BatchNorm


def stage_times(cfg, mode: str, labelled: dict, runs: int, plan_changes: dict | None = None) -> dict:
    """The parts of a training step in compile `mode` (`step_parts`), each alone, round robin: median ms, and the peak
    resident memory a call adds above what the process held before it, GB. "batchnorm_ms": the BatchNorm kernels'
    time inside one conv_forward_backward call (TensorFlow profiler; None in mode xla, where they are fused into XLA's
    program)."""
    parts = step_parts(cfg, mode, labelled, plan_changes)
    calls = {k: bench.fetched(lambda f=f, a=a: f(*a)) for k, (f, a) in parts.items()}
    readings = bench.round_robin(calls, runs, warmup=1, reading=bench.timed_with_memory)
    out = {k: {"median_ms": bench.middle([r["ms"] for r in rs]),
               "peak_above_before_gb": bench.middle([r["peak_rss_gb"] - r["rss_before_gb"] for r in rs])}
           for k, rs in readings.items()}
    out["batchnorm_ms"] = None if mode == "xla" else _op_type_ms(calls["conv_forward_backward"], BN_OP_TYPES)
    return out


def _dense_and_point_variables(model) -> tuple[list, list]:
    """The model's trainable variables of rows C-V, and the rest (rows A, Y, Z or the GRU head)."""
    dense_vars = [v for layer in [b for s in model.encoder_stages for b in s] + model.upsample_skips + [model.conv_v]
                  for v in layer.trainable_variables]
    dense_ids = {id(v) for v in dense_vars}
    return dense_vars, [v for v in model.trainable_variables if id(v) not in dense_ids]


def _optimizer_part(cfg, model) -> tuple:
    """(compiled function, its arguments): the step's update on `model`'s weights, global norm, clipping as `cfg`
    says and Adam (`step.adam_update`), from a fresh optimizer state and small constant gradients."""
    import tensorflow as tf
    from ff3d_tf.model import step as step_lib
    weights = model.trainable_variables
    state = step_lib.TrainState([v.value for v in weights], [v.value for v in model.non_trainable_variables],
                                [tf.zeros_like(v) for v in weights], [tf.zeros_like(v) for v in weights],
                                tf.constant(0, tf.int64))
    grads = [tf.ones_like(v) * 1e-3 for v in weights]

    def optimizer(state, grads):
        norm = tf.linalg.global_norm(grads)
        if cfg.train.grad_clip_norm is not None:
            grads, _ = tf.clip_by_global_norm(grads, cfg.train.grad_clip_norm, use_norm=norm)
        return list(step_lib.adam_update(cfg, state, grads))

    return tf.function(optimizer), (state, grads)


def step_parts(cfg, mode: str, labelled: dict, plan_changes: dict | None = None) -> dict:
    """{part: (compiled function, its arguments)}: the parts of a training step in compile `mode` on `labelled`:

      point_forward          rows A-B (pillars, point encoder, scatter; BN statistics of training) and W-Z (head)
      point_forward_backward the same and their gradients (upstream: ones)
      conv_forward           rows C-V (with the paper head, and the head's grid part: `FastFlow3D.grid_stages`)
                             with training=True (BatchNorm on batch statistics)
      conv_forward_backward  the same and their gradients
      optimizer              the step's update: global norm, clipping, Adam (`step.adam_update`) on the model's weights
      loss                   the loss and its gradient with respect to the flow

    compiled as the step compiles them: mode xla, one XLA program each; hybrid, the point stages as XLA programs
    (`compile_lib.hybrid_encode`) and the rest as graph kernels; none, graph kernels."""
    import tensorflow as tf
    from ff3d_tf.config import replace_config
    from ff3d_tf.model import build_model
    from ff3d_tf.model import compile as compile_lib
    from ff3d_tf.model.forward import model_inputs
    from ff3d_tf.model.losses import batch_flow_loss
    from ff3d_tf.model.plan import resolve
    cfg1 = replace_config(cfg, {"train.global_batch_size": 1})
    model = build_model(cfg1, plan=resolve(cfg1.model, "train", mode)[0].replace(**(plan_changes or {})))
    inputs = model_inputs(labelled)
    xla = mode == "xla"

    def encode(x):
        if mode == "hybrid":
            return compile_lib.hybrid_encode(model.encode_points, x, True, model.plan.point_programs)
        return model.encode_points(x, True)

    def decode(grid, encoded):
        if mode == "hybrid":
            return compile_lib.xla_function(lambda g, e: model.decode_points(g, e, True))(grid, encoded)
        return model.decode_points(grid, encoded, True)

    encoded0 = tf.function(encode, jit_compile=xla)(inputs)
    grid0 = tf.function(lambda b: model.grid_stages(b, True), jit_compile=xla)(encoded0["bev_features"])
    dense_vars, point_vars = _dense_and_point_variables(model)

    def point_fb(x, grid):
        with tf.GradientTape() as tape:
            tape.watch(grid)
            encoded = encode(x)
            flow = decode(grid, encoded)["flow_mps"]
            total = tf.reduce_sum(flow) + tf.reduce_sum(tf.cast(encoded["bev_features"], tf.float32))
        return tape.gradient(total, point_vars + [grid])

    def conv_fb(bev):
        with tf.GradientTape() as tape:
            tape.watch(bev)
            total = tf.reduce_sum(tf.cast(model.grid_stages(bev, True), tf.float32))
        return tape.gradient(total, dense_vars + [bev])

    flow0 = decode(grid0, encoded0)

    def loss_fb(flow):
        with tf.GradientTape() as tape:
            tape.watch(flow)
            loss = batch_flow_loss(labelled, {"flow_mps": flow, "point_valid": flow0["point_valid"]},
                                   cfg.train.background_weight, 1)
        return tape.gradient(loss, flow)

    return {"point_forward": (tf.function(lambda x, g: decode(g, encode(x)), jit_compile=xla), (inputs, grid0)),
            "point_forward_backward": (tf.function(point_fb, jit_compile=xla), (inputs, grid0)),
            "conv_forward": (tf.function(lambda b: model.grid_stages(b, True), jit_compile=xla),
                             (encoded0["bev_features"],)),
            "conv_forward_backward": (tf.function(conv_fb, jit_compile=xla), (encoded0["bev_features"],)),
            "optimizer": _optimizer_part(cfg1, model),
            "loss": (tf.function(loss_fb, jit_compile=xla), (flow0["flow_mps"],))}


def _op_type_ms(call: Callable, substrings: Sequence[str]) -> float:
    """ms of the TensorFlow kernels whose op type contains one of `substrings`, in one profiled `call`."""
    import glob
    import tempfile
    import tensorflow as tf
    from ff3d_tf import internals
    with tempfile.TemporaryDirectory() as logdir:
        tf.profiler.experimental.start(logdir)
        call()
        tf.profiler.experimental.stop()
        total = 0.0
        for path in glob.glob(os.path.join(logdir, "**", "*.xplane.pb"), recursive=True):
            for plane in internals.profiler_xspace(path).planes:
                names = {k: v.name for k, v in plane.event_metadata.items()}
                for line in plane.lines:
                    for event in line.events:
                        name = names.get(event.metadata_id, "")
                        if ":" in name and any(s in name.rsplit(":", 1)[1] for s in substrings):
                            total += event.duration_ps / 1e9
    return total


# -- the parent --------------------------------------------------------------------------------------------------------
def stage_summary(stages: Mapping, step_ms: float) -> dict:
    """Backward parts as (forward + backward) - forward, and the rest of the step: step - (point stages forward and
    backward + convolutions forward and backward + optimizer + loss); ms."""
    ms = {k: v["median_ms"] for k, v in stages.items() if isinstance(v, dict)}
    out = {"point_forward_ms": ms["point_forward"],
           "point_backward_ms": ms["point_forward_backward"] - ms["point_forward"],
           "conv_forward_ms": ms["conv_forward"],
           "conv_backward_ms": ms["conv_forward_backward"] - ms["conv_forward"],
           "batchnorm_ms": stages.get("batchnorm_ms"), "optimizer_ms": ms["optimizer"], "loss_ms": ms["loss"]}
    out["rest_ms"] = step_ms - (ms["point_forward_backward"] + ms["conv_forward_backward"] + ms["optimizer"] +
                                ms["loss"])
    return out


def _train_projection(measured_before: Mapping, measured: Mapping, before: Mapping, peer: Mapping) -> dict:
    """The issue's training step figures of ff3d_tf before, scaled by `measured` over `measured_before`."""
    ratio = measured["step_median_ms"] / measured_before["step_median_ms"]
    out = {"train_step_32000_ms": before["train_step_32000_ms"] * ratio}
    out["train_step_speedup_over_peer"] = peer["train_step_32000_ms"] / out["train_step_32000_ms"]
    if measured_before.get("step_cpu_median_ms") and measured.get("step_cpu_median_ms"):
        # By CPU time (user + system, all threads): less moved by other load on a shared machine than wall time.
        cpu_ratio = measured["step_cpu_median_ms"] / measured_before["step_cpu_median_ms"]
        out["train_step_32000_ms_by_cpu_time"] = before["train_step_32000_ms"] * cpu_ratio
        out["train_step_speedup_over_peer_by_cpu_time"] = (peer["train_step_32000_ms"] /
                                                           out["train_step_32000_ms_by_cpu_time"])
    mem = measured["peak_rss_gb"] / measured_before["peak_rss_gb"]
    out["train_step_32000_peak_gb"] = before["train_step_32000_peak_gb"] * mem
    if measured.get("steps_peak_rss_gb"):
        # The steps' own peak after the warm-up (the program compiled and run twice), against the same "before"
        # process peak as above: "before" (TensorFlow's kernels, no compilation of the step) peaks in its steps.
        out["train_step_32000_steps_peak_gb"] = (before["train_step_32000_peak_gb"] * measured["steps_peak_rss_gb"] /
                                                 measured_before["peak_rss_gb"])
    return out


def projection(summary: Mapping, figures: Mapping | None = None) -> dict:
    """The issue's Zen 3 figures of ff3d_tf before (`figures`, default `peer_figures()`), scaled by this run's
    after/before ratios (AVX2 caps), beside the peer's: what the change is expected to give on that CPU."""
    figures = figures or peer_figures()
    before, peer = figures["ff3d_tf_before"], figures["peer"]
    out = {}

    def both(row):
        return row and all(s in row and "error" not in row[s] for s in SETTINGS)
    step, fwd = summary.get("train/auto"), summary.get("forward/auto")
    if both(step):
        out.update(_train_projection(step["before"], step["after"], before, peer))
        for setting in ALL_SETTINGS[len(SETTINGS):]:
            if setting in step and "error" not in step[setting]:
                out[setting] = _train_projection(step["before"], step[setting], before, peer)
    if both(fwd):
        for n in ("32000", "1000000"):
            if n in fwd["after"]["median_ms"]:
                ratio = fwd["after"]["median_ms"][n] / fwd["before"]["median_ms"][n]
                out[f"forward_{n}_ms"] = before[f"forward_{n}_ms"] * ratio
                out[f"forward_{n}_speedup_over_peer"] = peer[f"forward_{n}_ms"] / out[f"forward_{n}_ms"]
                cpu_b, cpu_a = fwd["before"].get("cpu_median_ms", {}), fwd["after"].get("cpu_median_ms", {})
                if n in cpu_b and n in cpu_a:
                    out[f"forward_{n}_speedup_over_peer_by_cpu_time"] = peer[f"forward_{n}_ms"] / (
                        before[f"forward_{n}_ms"] * cpu_a[n] / cpu_b[n])
    return out


def study(config: str, overrides: Sequence[str], train_points: int, forward_points: Sequence[int],
          modes: Sequence[str], jobs: Sequence[str], settings: Sequence[str], cap: str, steps: int, warmup: int,
          runs: int, stages: bool, stage_runs: int, cores: int, timeout_s: float | None = None,
          log_fn: Callable[[str], None] = print, save: Callable[[dict], None] = lambda result: None,
          rounds: int = 1) -> dict:
    """Every (job, mode, setting) child once per round, `rounds` rounds, settings of one (job, mode) next to each
    other, so that a change of load hits them alike; the JSON of lab/tools/benchmark_cpu_step.py (`save` gets it after
    every child). A variant's first reading is its entry, later rounds' are in its "later_rounds"; the summary takes
    the median over the rounds. A failed child is recorded ({"error": ...})."""
    for name, given, known in (("modes", modes, MODES), ("jobs", jobs, JOBS), ("settings", settings, ALL_SETTINGS)):
        if not set(given) <= set(known):
            raise ValueError(f"{name}={list(given)}: of {', '.join(known)}")
    if cap not in cpu.EMULATIONS and cap != NO_CAP:
        raise ValueError(f"cap={cap!r}: one of {', '.join(cpu.EMULATIONS)}, {NO_CAP}")
    config = os.path.abspath(config) if config else ""
    figures = peer_figures()
    result = {"how": "", "cpu": cpu.describe(), "cap": cap, "load_average_at_start": bench.load_average(),
              "config": config and os.path.relpath(config, children.ROOT), "overrides": list(overrides),
              "train_points": train_points, "forward_points": list(forward_points), "steps": steps,
              "warmup": warmup, "runs": runs, "stage_runs": stage_runs, "rounds": rounds, "cores": cores,
              "peer": {k: v for k, v in figures.items() if k != "targets"}, "targets": figures["targets"],
              "variants": {}, "summary": {}}
    result["how"] = (f"each variant a fresh process pinned to {cores} cores with TensorFlow's pools of {cores} "
                     f"threads; training: median of {steps} steps after {warmup} warm-up steps, peak = the "
                     f"process's VmHWM; forward: median of {runs} calls after {warmup} warm-up calls per point count, "
                     "round robin in one process; every figure under the caps of " +
                     (f"ff3d_tf.cpu.EMULATIONS[{cap!r}]" if cap != NO_CAP else "none (the CPU's own kernels)") +
                     " (the CPU and its limits named in each variant's cpu)")
    # The Zen 3 figures are of the paper config at 32,000 and 1,000,000 points: projected only for that.
    paper = (result["config"] == PAPER_CONFIG and not overrides and train_points == 32000 and cap == "zen3")
    measured = {}  # (job, setting, resolved mode) -> the key of the variant that measured it
    plan = [(job, mode, setting) for job in jobs for mode in modes for setting in settings]
    for round_, (job, mode, setting) in ((r, v) for r in range(rounds) for v in plan):
        key = f"{job}/{mode}"
        result["variants"].setdefault(key, {})
        environment = variant_environment(setting, job, cap)
        if job not in SETTING_JOBS.get(setting, JOBS) or (
                setting in ENVIRONMENT_SETTINGS and environment == variant_environment("after", job, cap)):
            continue
        resolved = resolved_mode(setting, mode, job, environment)
        if measured.get((job, setting, resolved), key) != key:  # "auto" and the mode it resolves to: one
            result["variants"][key][setting] = {"same_as": measured[(job, setting, resolved)],
                                                "mode": resolved}
            continue
        point_programs = "one" if setting == "before" else "per_cloud"
        kwargs = {"config": config, "mode": resolved, "warmup": warmup,
                  "overrides": list(overrides) + ([REMAT_OVERRIDE] if setting in REMAT_SETTINGS else []) +
                  ([BFLOAT16_OVERRIDE] if setting in BFLOAT16_SETTINGS else []),
                  "point_programs": point_programs,
                  "convolution_forms": "plain" if setting in ("before", "after_plain_convolutions") else "fast"}
        if job == "train":
            fn = f"{MODULE}:train_child"
            kwargs.update(points=train_points, steps=steps, stages=stages, stage_runs=stage_runs)
        else:
            fn = f"{MODULE}:forward_child"
            kwargs.update(points=list(forward_points), runs=runs)
        # The child applies MALLOC_ARENA_MAX as a tool does (`cpu.limit_malloc_arenas` after its start), not at exec.
        kwargs["malloc_arena_max"] = environment.get("MALLOC_ARENA_MAX")
        exec_environment = {k: v for k, v in environment.items() if k != "MALLOC_ARENA_MAX"}
        removed = {k: os.environ.pop(k) for k in list(os.environ) if k not in exec_environment}
        try:
            reading = children.run_child(fn, kwargs, cores=cores, env=exec_environment,
                                         timeout_s=timeout_s, what=f"{key} {setting}", on_error="record")
        finally:
            os.environ.update(removed)
        reading.update({"setting": setting, "requested_mode": mode,
                        "environment": {k: environment.get(k) for k in KNOBS}})
        if job == "train" and "stages" in reading and "step_median_ms" in reading:
            reading["stage_summary"] = stage_summary(reading["stages"], reading["step_median_ms"])
        if round_ == 0:
            result["variants"][key][setting] = reading
        else:
            result["variants"][key][setting].setdefault("later_rounds", []).append(reading)
        measured[(job, setting, resolved)] = key
        log_fn(f"round {round_ + 1} {key} {setting}: " + _brief(reading))
        result["summary"] = summarize(result["variants"])
        if paper:
            result["projection_zen3"] = projection(result["summary"], figures)
        result["load_average_at_end"] = bench.load_average()
        save(result)
    return result


def _brief(reading: Mapping) -> str:
    if "error" in reading:
        return "FAILED " + reading["error"].splitlines()[0]
    if "step_median_ms" in reading:
        return (f"{reading['mode']}, oneDNN {reading['onednn_enabled']}: step {reading['step_median_ms']:.0f} ms, "
                f"peak {reading['peak_rss_gb']:.2f} GB")
    return f"{reading['mode']}, oneDNN {reading['onednn_enabled']}: forward " + json.dumps(
        {k: round(v) for k, v in reading["median_ms"].items()})


def summarize(variants: Mapping) -> dict:
    """{"<job>/<mode>": {setting: the reading's figures}, and "after_over_before"} of the variants measured."""
    out = {}
    for key, by_setting in variants.items():
        row = {}
        for setting, r in by_setting.items():
            if "same_as" in r:
                r = {**variants[r["same_as"]][setting], "same_as": r["same_as"]}
            readings = [x for x in [r] + list(r.get("later_rounds", [])) if "error" not in x]
            if not readings:
                row[setting] = {"error": True}
            elif "step_median_ms" in r or "step_median_ms" in readings[0]:
                first = readings[0]
                row[setting] = {"mode": first["mode"], "onednn_enabled": first["onednn_enabled"],
                                "rounds": len(readings),
                                "step_median_ms": bench.middle([x["step_median_ms"] for x in readings]),
                                "peak_rss_gb": bench.middle([x["peak_rss_gb"] for x in readings]),
                                "steps_peak_rss_gb": bench.middle([x["steps_peak_rss_gb"] for x in readings])
                                if all(x.get("steps_peak_rss_gb") for x in readings) else None,
                                **{key: bench.middle([bench.middle(x[name]) for x in readings])
                                   if all(x.get(name) for x in readings) else None
                                   for key, name in (("step_cpu_median_ms", "step_cpu_ms"),
                                                     ("step_sys_median_ms", "step_sys_ms"),
                                                     ("step_minor_faults_median", "step_minor_faults"))},
                                **({"stages": first["stage_summary"]} if "stage_summary" in first else {})}
            else:
                first = readings[0]
                med = {n: bench.middle([x["median_ms"][n] for x in readings]) for n in first["median_ms"]}
                cpu_med = ({n: bench.middle([x["cpu_median_ms"][n] for x in readings]) for n in first["cpu_median_ms"]}
                           if all("cpu_median_ms" in x for x in readings) else {})
                r = first
                row[setting] = {"mode": r["mode"], "onednn_enabled": r["onednn_enabled"], "median_ms": med,
                                "cpu_median_ms": cpu_med, "peak_rss_gb": r["peak_rss_gb"]}
                if "32000" in med and "1000000" in med:
                    row[setting]["t1m_over_t32k"] = med["1000000"] / med["32000"]
                if "32000" in cpu_med and "1000000" in cpu_med:
                    row[setting]["cpu_t1m_over_t32k"] = cpu_med["1000000"] / cpu_med["32000"]
        if all(s in row and "error" not in row[s] for s in SETTINGS):
            b, a = row["before"], row["after"]
            if "step_median_ms" in b:
                row["before_over_after"] = {"step": b["step_median_ms"] / a["step_median_ms"],
                                            "peak": b["peak_rss_gb"] / a["peak_rss_gb"]}
                if b.get("step_cpu_median_ms") and a.get("step_cpu_median_ms"):
                    row["before_over_after"]["step_cpu"] = b["step_cpu_median_ms"] / a["step_cpu_median_ms"]
            else:
                row["before_over_after"] = {n: b["median_ms"][n] / a["median_ms"][n] for n in a["median_ms"]}
        out[key] = row
    return out


def resummarize(result: dict) -> dict:
    """`result` (a study's JSON) with "summary" and "projection_zen3" computed again from its variants: what a newer
    summary adds, without measuring again."""
    out = dict(result, summary=summarize(result["variants"]))
    if "projection_zen3" in result:
        figures = {**result["peer"], "targets": result["targets"]}
        out["projection_zen3"] = projection(out["summary"], figures)
    return out
