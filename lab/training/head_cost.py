"""What DeFlow's GRU head (`model.head=gru`) costs beside the paper head on a CPU: forward latency and peak resident
memory at each point count, and the training step, every figure from its own process (lab/tools/benchmark_head_cost.py;
docs/training.md shows them).

Variants (`variants`): "paper" (rows W-Z, the reference) and "gru<K>" for each `model.gru_iterations` K asked, each a
set of `--set` overrides on the same config.

Every reading is one fresh child process (`lab.children.run_child`, pinned to `cores` CPUs with TensorFlow's pools
of as many threads), so that one variant's memory never weighs on another's:

  forward  `forward_child`: the model's compiled forward (`compiled_forward`, batch 1, compile mode `model.compile`
           resolved for inference) on the benchmark cloud of `lab.bench` at one point count, padded to its
           bucket; `warmup` unmeasured calls (tracing, compilation), then `runs` timed calls;
  train    the Trainer's own step on a labelled benchmark cloud, batch 1 (`train_child`, default
           `lab.training.cpu_step_study.train_child`), `steps` timed steps after `warmup`.

One round robin: each round runs, for each point count, every variant's forward child, then every variant's training
child, so that a change of load on a shared machine hits the variants alike: compare the ratios within one run.
A child that fails or runs past `timeout_s` is recorded ({"error": ...}) beside the others and the run goes on.

Figures per variant (`summaries`): "median_ms", the median of every timed call of every round (a measured value,
`bench.middle`); "peak_rss_gb", the process's peak resident memory from its start to its last call (libraries,
compilation, every call; the largest over the rounds); for the forward also "call_peak_rss_gb" (the peak during the
timed calls alone, reset before each) and "call_peak_above_before_gb" (what one call adds above the memory held before
it: the forward's transient). `ratios`: each variant's figures over the reference's, and the fewest-iterations GRU
over the most; "added_time_share" = 1 - reference / variant, the share of the variant's forward that its head adds
over the paper head's. `note` says in words, from those figures, where the GRU head dominates (`DOMINANT_SHARE`).
"""
from __future__ import annotations

import os
from typing import Callable, Mapping, Sequence

import numpy as np

from ff3d_tf import cpu
from ff3d_tf.config import load_config, replace_config
from lab import bench, children
from lab.training import cpu_step_study

MODULE = __name__
REFERENCE = "paper"
DEFAULT_GRU_ITERATIONS = (4, 2)  # model.gru_iterations measured by default: the config's default and DeFlow's
# self-supervised setting
# The GRU head dominates the forward where the time it adds over the paper head is more than this share of the whole
# forward (where it takes longer than everything else together).
DOMINANT_SHARE = 0.5
FORWARD_FIGURES = ("median_ms", "peak_rss_gb", "call_peak_rss_gb", "call_peak_above_before_gb")
TRAIN_FIGURES = ("median_ms", "peak_rss_gb")


def variants(gru_iterations: Sequence[int] = DEFAULT_GRU_ITERATIONS) -> dict[str, tuple[str, ...]]:
    """{name: config overrides}: the paper head first (the reference), then "gru<K>" for each K of `gru_iterations`."""
    if not gru_iterations or len(set(gru_iterations)) != len(gru_iterations):
        raise ValueError(f"gru_iterations={list(gru_iterations)}: one or more distinct counts")
    out = {REFERENCE: ("model.head=paper",)}
    out.update({f"gru{k}": ("model.head=gru", f"model.gru_iterations={k}") for k in gru_iterations})
    return out


# -- in the child ------------------------------------------------------------------------------------------------------
def example(cfg, rng: np.random.Generator, points: int) -> tuple[dict, int]:
    """(The model's inputs as tensors: one pair of benchmark clouds of `points` points over cfg's grid, padded to their
    bucket, batch 1; the padded size): the cloud `lab.training.bench_steps.example` makes, without labels."""
    import tensorflow as tf
    from ff3d_tf.data.pairs import bucket_size
    padded = bucket_size(points, cfg.data.point_bucket_base)
    g = cfg.grid
    arrays = bench.random_clouds(rng, points, padded, (g.x_range_m, g.y_range_m, g.z_range_m))
    return {k: tf.constant(v) for k, v in arrays.items()}, padded


def forward_child(config: str, overrides: list, points: int, runs: int, warmup: int) -> dict:
    """(In a child.) The compiled forward of the config at `points` points (module docstring): each timed call's
    "forward_ms", their "median_ms", the memory figures, and what ran (mode, head, parameters, CPU, placement)."""
    from ff3d_tf import internals
    from ff3d_tf.model import build_model
    from ff3d_tf.model import compile as compile_lib
    from ff3d_tf.model.forward import compiled_forward
    cfg = replace_config(load_config(config or None, list(overrides)), {"train.global_batch_size": 1})
    mode = compile_lib.resolve_compile_mode(cfg.model.compile, job="inference")
    model = build_model(cfg, mode)
    forward = compiled_forward(model, mode == "xla")
    inputs, padded = example(cfg, np.random.default_rng(0), points)
    call = bench.fetched(lambda: forward(inputs))
    for _ in range(warmup):
        call()
    peak_so_far = bench.proc_status("VmHWM")  # from the process's start: libraries, the model, compilation
    readings = bench.measure(call, runs, reading=bench.timed_with_memory)
    ms = [r["ms"] for r in readings]
    call_peak = max(r["peak_rss_gb"] for r in readings)
    return {"cpu": cpu.describe(), "onednn_enabled": internals.onednn_enabled(), "placement": children.placement(),
            "mode": mode, "head": cfg.model.head, "gru_iterations": cfg.model.gru_iterations,
            "params": model.count_params(), "points": points, "padded_points": padded, "forward_ms": ms,
            "median_ms": bench.middle(ms), "peak_rss_gb": max(peak_so_far, call_peak), "call_peak_rss_gb": call_peak,
            "call_peak_above_before_gb": bench.middle([r["peak_rss_gb"] - r["rss_before_gb"] for r in readings]),
            "peak_reset": all(r["peak_reset"] for r in readings)}


# -- the parent: figures, ratios, the note -----------------------------------------------------------------------------
def summary(readings: Sequence[Mapping], times_key: str, figures: Sequence[str]) -> dict:
    """One variant's figures over the rounds' `readings` (a child's result each, or {"error": ...}): "median_ms"
    (`bench.middle` of every timed call, `times_key` in each reading), the peaks (the largest over the rounds),
    "call_peak_above_before_gb" (the middle over the rounds), "rounds" measured and "failed_rounds"; {"error": the
    first failure, "failed_rounds"} where no round measured."""
    good = [r for r in readings if "error" not in r]
    failed = len(readings) - len(good)
    if not good:
        return {"error": next((r["error"] for r in readings), "not measured yet"), "failed_rounds": failed}
    out = {"median_ms": bench.middle([ms for r in good for ms in r[times_key]])}
    for k in figures:
        if k != "median_ms":
            values = [r[k] for r in good]
            out[k] = bench.middle(values) if k == "call_peak_above_before_gb" else float(max(values))
    out.update({"padded_points": good[0]["padded_points"], "mode": good[0]["mode"], "rounds": len(good),
                "failed_rounds": failed})
    return out


def ratio_row(figures: Mapping, reference: Mapping, keys: Sequence[str]) -> dict | None:
    """{key: figures[key] / reference[key]} of `keys`, with "added_time_share" (1 - reference / figures, median_ms);
    None where either side has no figures (a failed child)."""
    if "error" in figures or "error" in reference:
        return None
    out = {k: figures[k] / reference[k] if reference[k] else None for k in keys}
    out["added_time_share"] = 1.0 - reference["median_ms"] / figures["median_ms"]
    return out


def ratios(forward: Mapping, train: Mapping, over: str) -> dict:
    """{variant: {"forward": {points: `ratio_row`}, "train_step": `ratio_row`}} of every variant other than `over`
    against `over`. `forward`: {variant: {points: figures}}; `train`: {variant: figures} ({}: no training step)."""
    out = {}
    for name in forward:
        if name == over:
            continue
        out[name] = {"forward": {n: ratio_row(row, forward[over][n], FORWARD_FIGURES)
                                 for n, row in forward[name].items()}}
        if train:
            out[name]["train_step"] = ratio_row(train[name], train[over], TRAIN_FIGURES)
    return out


def _times(values: Sequence, fmt: str) -> str:
    return " / ".join("n/a" if v is None else format(v, fmt) for v in values)


def note(forward: Mapping, train: Mapping, by_reference: Mapping, between: Mapping | None, train_points: int) -> str:
    """A few sentences generated from the figures: each GRU variant's forward and memory ratios over the paper head's
    at every point count, its training step's, where its head dominates the forward (added time share above
    `DOMINANT_SHARE`), the fewest-iterations variant against the most (`between`: {"<a>/<b>": `ratios` row of a over
    b}), and which children failed."""
    points = list(next(iter(forward.values())))
    sentences = []
    for name, row in by_reference.items():
        fwd = [row["forward"][n] for n in points]
        share = [r and r["added_time_share"] for r in fwd]
        speed, memory = [r and r["median_ms"] for r in fwd], [r and r["peak_rss_gb"] for r in fwd]
        text = (f"{name} over {REFERENCE}: forward x{_times(speed, '.2f')} at {' / '.join(points)} points (the time "
                f"its head adds over the paper head: {_times(share, '.0%')} of its forward), peak RSS "
                f"x{_times(memory, '.2f')}")
        step = row.get("train_step")
        if step:
            text += (f"; training step at {train_points} points x{step['median_ms']:.2f}, "
                     f"peak x{step['peak_rss_gb']:.2f}")
        dominant = [n for n, s in zip(points, share) if s is not None and s > DOMINANT_SHARE]
        measured = [n for n, s in zip(points, share) if s is not None]
        if dominant:
            text += (f". The GRU head dominates {name}'s forward (more than half its time) at {' / '.join(dominant)} "
                     "points")
        elif measured:
            text += f". The GRU head does not dominate {name}'s forward at any measured point count"
        sentences.append(text + ".")
    for pair, row in (between or {}).items():
        fwd = [row["forward"][n] for n in points]
        text = f"{pair}: forward x{_times([r and r['median_ms'] for r in fwd], '.2f')} at {' / '.join(points)} points"
        step = row.get("train_step")
        if step:
            text += f", training step x{step['median_ms']:.2f}"
        sentences.append(text + " (below 1: the fewer iterations cost less; accuracy is measured apart).")
    failed = [f"{name} forward at {n} points" for name, rows in forward.items() for n, r in rows.items()
              if r["failed_rounds"]] + [f"{name} training step" for name, r in train.items() if r["failed_rounds"]]
    if failed:
        sentences.append("Failed children (recorded in readings): " + ", ".join(failed) + ".")
    return " ".join(sentences)


def report(readings: Mapping, names: Sequence[str], points: Sequence[int], train_points: int) -> dict:
    """The results' "forward", "train_step", "ratios", "ratios_between" and "note" from `readings` ({"forward":
    {points: {variant: [a reading per round]}}, "train": {variant: [...]}})."""
    forward = {name: {str(n): summary(readings["forward"][str(n)][name], "forward_ms", FORWARD_FIGURES)
                      for n in points} for name in names}
    train = {name: summary(readings["train"][name], "step_ms", TRAIN_FIGURES) for name in readings.get("train", {})}
    by_reference = ratios(forward, train, names[0])
    grus = list(names[1:])
    between = {}
    if len(grus) > 1:  # the fewest iterations over the most, as measured (names as `variants` gives them)
        most, fewest = grus[0], grus[-1]
        pair = ratios({most: forward[most], fewest: forward[fewest]},
                      {k: train[k] for k in (most, fewest) if k in train}, most)
        between = {f"{fewest}/{most}": pair[fewest]}
    return {"forward": forward, "train_step": train, "ratios": by_reference, "ratios_between": between,
            "note": note(forward, train, by_reference, between, train_points)}


def _brief(reading: Mapping) -> str:
    if "error" in reading:
        return "FAILED " + reading["error"].splitlines()[0]
    ms = reading.get("median_ms", reading.get("step_median_ms"))
    return f"{reading.get('mode')}: {ms:.1f} ms, peak {reading['peak_rss_gb']:.2f} GB"


def run(config: str, overrides: Sequence[str], points: Sequence[int], train_points: int,
        train_child: str | None = cpu_step_study.MODULE + ":train_child",
        gru_iterations: Sequence[int] = DEFAULT_GRU_ITERATIONS, runs: int = 3, warmup: int = 2, steps: int = 3,
        rounds: int = 1, cores: int | None = None, timeout_s: float | None = None, command: str = "",
        log: Callable[[str], None] = print, save: Callable[[dict], None] = lambda result: None) -> dict:
    """The benchmark (module docstring): the results as written to JSON; `save` gets them after every child.

    `config`, `overrides`: the config every variant starts from (each variant adds its own overrides; every variant's
    config is checked before any child starts). `points`: the forward's point counts; `train_points`: the training
    step's (0: none); `train_child`: "module:function" of the training pipeline that runs in each training child as
    `function(config=, overrides=, mode=, points=, steps=, warmup=, point_programs=, stages=False, stage_runs=0)` and
    returns "step_ms", "peak_rss_gb", "padded_points", "mode" (`lab.training.cpu_step_study.train_child`).
    `cores`: per child (default: every CPU this process may use). `command`: how the run was started, for the JSON."""
    from ff3d_tf.model import compile as compile_lib
    if not points or any(n <= 0 for n in points):
        raise ValueError(f"points={list(points)}: one or more positive counts")
    if min(runs, rounds, steps) < 1 or warmup < 0:
        raise ValueError(f"runs={runs}, rounds={rounds}, steps={steps} (each >= 1), warmup={warmup} (>= 0)")
    if train_points < 0 or (train_points and not train_child):
        raise ValueError(f"train_points={train_points}: >= 0, and a training step needs train_child")
    cores = cores or len(os.sched_getaffinity(0))
    config = os.path.abspath(config) if config else ""
    named = variants(gru_iterations)
    for sets in named.values():  # a ConfigError here, before any child starts
        load_config(config or None, list(overrides) + list(sets))
    base = load_config(config or None, list(overrides))
    modes = {job: compile_lib.resolve_compile_mode(base.model.compile, job=job) for job in ("inference", "train")}
    points = [int(n) for n in points]
    result = {
        "command": command, "cpu": cpu.describe(), "load_average_at_start": bench.load_average(),
        "how": (f"each reading a fresh process pinned to {cores} cores with TensorFlow's pools of {cores} threads; "
                f"forward: median of {runs} calls after {warmup} warm-up calls per process, batch 1; training step: "
                f"median of {steps} steps after {warmup} warm-up steps, batch 1; {rounds} round(s), each every "
                "variant in turn at each point count, then every variant's training step; peak_rss_gb: the "
                "process's VmHWM from its start"),
        "config": config and os.path.relpath(config, children.ROOT), "overrides": list(overrides),
        "variants": {name: list(sets) for name, sets in named.items()},
        "params": {}, "modes": modes, "environment": {k: os.environ.get(k) for k in cpu.STARTUP_KEYS},
        "points": points, "train_points": train_points, "runs": runs, "warmup": warmup, "steps": steps,
        "rounds": rounds, "cores": cores, "readings": {"forward": {str(n): {name: [] for name in named}
                                                                   for n in points}}}
    if train_points:
        result["readings"]["train"] = {name: [] for name in named}
    plan = [("forward", n, name) for n in points for name in named]
    plan += [("train", train_points, name) for name in named] if train_points else []
    for round_ in range(rounds):
        for job, n, name in plan:
            sets = list(overrides) + list(named[name])
            if job == "forward":
                fn, kwargs = f"{MODULE}:forward_child", {"config": config, "overrides": sets, "points": n,
                                                         "runs": runs, "warmup": warmup}
                into = result["readings"]["forward"][str(n)][name]
            else:
                fn = train_child
                kwargs = {"config": config, "overrides": sets, "mode": modes["train"], "points": n, "steps": steps,
                          "warmup": warmup, "point_programs": "per_cloud", "stages": False,
                          "stage_runs": 0}
                into = result["readings"]["train"][name]
            what = f"{name} {job} at {n} points"
            reading = children.run_child(fn, kwargs, cores=cores, timeout_s=timeout_s, what=what, on_error="record")
            if "params" in reading:
                result["params"][name] = reading["params"]
            into.append(reading)
            log(f"round {round_ + 1} {what}: {_brief(reading)}")
            result.update(report(result["readings"], list(named), points, train_points))
            result["load_average_at_end"] = bench.load_average()
            save(result)
    log(result["note"])
    return result
