"""How TensorFlow runs the training step and the model's forward on a CPU under settings read when a process starts,
each setting (a *variant*) in fresh child processes (`lab.children`):

- `onednn_study` (lab/tools/benchmark_onednn.py): TensorFlow's oneDNN operations off against on (TF_ENABLE_ONEDNN_OPTS),
  per ISA cap (`ONEDNN_CAPS`): the median ms of the training step and of the forward.
- `memory_study` (lab/tools/profile_memory.py): what holds the resident memory between training steps and between
  inference calls, per allocator setting (`MEMORY_VARIANTS`): resident set, CPU time, page faults, glibc's and
  TensorFlow's allocator accounting, /proc/self/smaps by kind, before and after malloc_trim(0).

A child's environment is the caller's without any key that some variant of its study sets, plus its own variant's
(`variant_environment`): neither the caller's environment nor another variant decides a setting. The studies run their
variants in rounds, every variant once per round in turn, so that a change of load on a shared machine hits all alike;
their times are medians over the rounds (`medians`).

What the children measure: the Trainer's own step (`bench_steps.train_steps`: forward, backward, Adam) on one batch of
the benchmark cloud (`bench_steps.example`) held in memory, and the predictor's compiled forward (`compiled_forward`)
on such a cloud; batch 1.
"""
from __future__ import annotations

import functools
import json
import os
from typing import Callable, Iterable, Mapping, Sequence

from ff3d_tf import cpu
from lab import bench, children

GB = bench.GB


# -- shared: variant environments, children in them, medians over rounds -----------------------------------------------
def variant_environment(own: Mapping, variants: Iterable[Mapping], base: Mapping) -> dict:
    """`base` without any key that one of `variants` (each a dict of environment variables) sets, plus `own`."""
    knobs = {key for variant in variants for key in variant}
    return {**{k: v for k, v in base.items() if k not in knobs}, **own}


def medians(rows: Sequence[Mapping], keys: Iterable[str]) -> dict:
    """{key: the median of row[key] over `rows`} (`bench.middle`: of an even count the upper middle value)."""
    return {k: bench.middle([row[k] for row in rows]) for k in keys}


def _absolute(config: str | None) -> str:
    """A config path as a child needs it (children run in the repository root); "" (the built-in defaults) kept."""
    return os.path.abspath(config) if config else ""


def _train_step(cfg, mode: str, points: int, rng) -> tuple[Callable, int]:
    """(the Trainer's step on one labelled benchmark example of `points` points, compile `mode`; its padded size)."""
    from lab.training import bench_steps
    labelled, padded = bench_steps.example(cfg, rng, points, labels=True)
    return bench_steps.train_steps(cfg, {mode: mode}, labelled)[mode], padded


def _forward(cfg, mode: str, points: int, rng) -> tuple[Callable, int]:
    """(a call of the compiled forward, batch 1, on one benchmark example of `points` points; its padded size)."""
    from ff3d_tf.config import replace_config
    from ff3d_tf.model import build_model
    from ff3d_tf.model.forward import compiled_forward
    from lab.training import bench_steps
    model = build_model(replace_config(cfg, {"train.global_batch_size": 1}), mode)
    forward = compiled_forward(model, cfg.model.jit_compile)
    inputs, padded = bench_steps.example(cfg, rng, points)
    return (lambda: forward(inputs)), padded


# -- TensorFlow's oneDNN operations on against off, per ISA cap --------------------------------------------------------
# `avx2`: oneDNN and XLA capped to AVX2 (the caps of `ff3d_tf.cpu.EMULATIONS["zen3"]`: how an AVX2-only CPU such as
# AMD Zen 3 runs); `none`: this CPU's own ISA.
ONEDNN_CAPS = {"avx2": {k: v for k, v in cpu.EMULATIONS["zen3"].items() if k != "TF_ENABLE_ONEDNN_OPTS"}, "none": {}}
ONEDNN_SETTINGS = ("0", "1")  # TF_ENABLE_ONEDNN_OPTS: off, on
ONEDNN_TIMES = ("train_step_ms", "forward_ms")
ONEDNN_WARMUP_CALLS = 2


def onednn_environment(cap: str, onednn: str, base: Mapping) -> dict:
    """The environment of the child of ISA cap `cap` with TF_ENABLE_ONEDNN_OPTS=`onednn` (`variant_environment`)."""
    def settings(c, o):
        return {**ONEDNN_CAPS[c], "TF_ENABLE_ONEDNN_OPTS": o}
    return variant_environment(settings(cap, onednn), (settings(c, o) for c in ONEDNN_CAPS for o in ONEDNN_SETTINGS),
                               base)


def onednn_child(config: str, points: int, steps: int) -> dict:
    """(In a child.) {"onednn_enabled", "train_step_ms", "forward_ms"}: the median ms of `steps` training steps and of
    `steps` forward calls at `points` points, each after `ONEDNN_WARMUP_CALLS` warm-up calls; compile mode hybrid."""
    import numpy as np
    from ff3d_tf import internals
    from ff3d_tf.config import load_config
    cfg = load_config(config or None, [])
    rng = np.random.default_rng(0)
    step, _ = _train_step(cfg, "hybrid", points, rng)
    forward, _ = _forward(cfg, "hybrid", points, rng)
    out = {"onednn_enabled": internals.onednn_enabled()}
    for key, fn in zip(ONEDNN_TIMES, (step, forward)):
        out[key] = bench.middle([r["ms"] for r in bench.measure(bench.fetched(fn), steps, ONEDNN_WARMUP_CALLS)])
    return out


def onednn_summary(runs: Mapping[str, Sequence[Mapping]], caps: Sequence[str]) -> dict:
    """{"<cap>_onednn_<0|1>": each time's median over the rounds, "<cap>_onednn_speedup": off time / on time (> 1:
    oneDNN faster)} of `runs` ({"<cap>_onednn_<0|1>": the children's results, one per round})."""
    summary = {name: medians(rows, ONEDNN_TIMES) for name, rows in runs.items()}
    for cap in caps:
        off, on = summary[f"{cap}_onednn_0"], summary[f"{cap}_onednn_1"]
        summary[f"{cap}_onednn_speedup"] = {k: off[k] / on[k] for k in ONEDNN_TIMES}
    return summary


def onednn_study(config: str, points: int, caps: Sequence[str], steps: int, rounds: int,
                 log_fn: Callable[[str], None] = print) -> dict:
    """Every (cap, oneDNN off / on) child once per round, `rounds` rounds; the JSON of lab/tools/benchmark_onednn.py.
    A child that fails raises `children.ChildError`."""
    unknown = [c for c in caps if c not in ONEDNN_CAPS]
    if unknown:
        raise ValueError(f"unknown caps {unknown}; known: {', '.join(ONEDNN_CAPS)}")
    runs = {f"{cap}_onednn_{onednn}": [] for cap in caps for onednn in ONEDNN_SETTINGS}
    load_start = bench.load_average()
    for round_ in range(rounds):
        for cap in caps:
            for onednn in ONEDNN_SETTINGS:
                result = children.run_child(f"{__name__}:onednn_child",
                                            {"config": _absolute(config), "points": points, "steps": steps},
                                            base=onednn_environment(cap, onednn, os.environ),
                                            what=f"cap {cap}, oneDNN {onednn}")
                runs[f"{cap}_onednn_{onednn}"].append(result)
                log_fn(f"round {round_ + 1} cap {cap} oneDNN {onednn}: {result}")
    return {"cpu": cpu.describe(), "load_average_at_start": load_start, "load_average_at_end": bench.load_average(),
            "config": config, "points": points, "steps": steps, "rounds": rounds,
            "how": f"medians over rounds of each child's median of --steps after {ONEDNN_WARMUP_CALLS} warm-up calls; "
                   "model.compile hybrid, batch 1; caps: " + json.dumps({c: ONEDNN_CAPS[c] for c in caps}),
            "summary": onednn_summary(runs, caps), "runs": runs}


# -- resident memory per allocator setting -----------------------------------------------------------------------------
# name -> environment, config overrides, trim (glibc malloc_trim(0) after every call, inside its time), what it tests.
# Every variant names TF_ENABLE_ONEDNN_OPTS and TF_ONEDNN_USE_SYSTEM_ALLOCATOR, so that neither the caller's
# environment nor the CPU decides them: unset, TensorFlow turns oneDNN on only on CPUs with AVX512_VNNI, AVX512_BF16
# or AMX (`ff3d_tf.cpu`), and without oneDNN there is no BFC pool and no allocator statistics.
_HEAP = "glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=68719476736"  # every chunk from the heap, no auto-trim


def _variant(env: dict, what: str, sets: Sequence[str] = (), trim: bool = False) -> dict:
    return {"env": env, "set": list(sets), "trim_after_call": trim, "what": what}


_BFC = {"TF_ENABLE_ONEDNN_OPTS": "1", "TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "0"}
_SYS = {"TF_ENABLE_ONEDNN_OPTS": "1", "TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "1"}
MEMORY_VARIANTS = {
    "tf_bfc_pool": _variant(_BFC, "TensorFlow's default with oneDNN: tensors of >= 256 KB come from the oneDNN CPU "
                                  "allocator's BFC pool, which keeps every region it grew to"),
    "bfc_trim": _variant(_BFC, "BFC pool, malloc_trim(0) after every call", trim=True),
    "bfc_arena_max_2": _variant({**_BFC, "MALLOC_ARENA_MAX": "2"}, "BFC pool, glibc limited to 2 malloc arenas"),
    "bfc_trim_mmap_thresholds": _variant(
        {**_BFC, "GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0:glibc.malloc.mmap_threshold=131072"},
        "BFC pool, glibc trims freed heap at once and mmaps every chunk >= 128 KB"),
    "bfc_onednn_primitive_cache_0": _variant({**_BFC, "ONEDNN_PRIMITIVE_CACHE_CAPACITY": "0"},
                                             "BFC pool, oneDNN's primitive cache off"),
    "onednn_off": _variant({**_BFC, "TF_ENABLE_ONEDNN_OPTS": "0"},
                           "oneDNN off: Eigen kernels and TensorFlow's plain CPU allocator (malloc/free, no pool)"),
    "system_allocator": _variant(_SYS, "every tensor from glibc malloc/free: a freed tensor above glibc's mmap "
                                       "threshold (<= 32 MB) is unmapped at once, the next one faults in fresh pages"),
    "system_allocator_thp": _variant({**_SYS, "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"},
                                     "system allocator, glibc asks for transparent huge pages (fewer page faults)"),
    "system_heap": _variant({**_SYS, "GLIBC_TUNABLES": _HEAP}, "system allocator, glibc serves every chunk from its "
                                                               "heap (no mmap) and never trims it by itself: a pool "
                                                               "like BFC"),
    "system_heap_trim": _variant({**_SYS, "GLIBC_TUNABLES": _HEAP}, "system_heap, malloc_trim(0) after every call",
                                 trim=True),
    "system_heap_trim_thp": _variant({**_SYS, "GLIBC_TUNABLES": _HEAP + ":glibc.malloc.hugetlb=1"},
                                     "system_heap_trim with transparent huge pages", trim=True),
    "system_arena1_heap_trim": _variant({**_SYS, "GLIBC_TUNABLES": "glibc.malloc.arena_max=1:" + _HEAP},
                                        "system allocator, one malloc arena (heap chunks of any size: a thread "
                                        "arena's heap stops at 64 MB and falls back to mmap), heap kept within a "
                                        "call, malloc_trim(0) after every call", trim=True),
    "system_arena1_heap_trim_thp": _variant(
        {**_SYS, "GLIBC_TUNABLES": "glibc.malloc.arena_max=1:glibc.malloc.hugetlb=1:" + _HEAP},
        "system_arena1_heap_trim with transparent huge pages", trim=True),
    "xla_bfc_pool": _variant(_BFC, "compile mode xla (whole step one XLA CPU program), BFC pool",
                             ("model.compile=xla",)),
    "xla_system_allocator": _variant(_SYS, "compile mode xla, system allocator", ("model.compile=xla",)),
}
MEMORY_KINDS = ("train", "infer")
MEMORY_TIMES = ("median_ms", "median_cpu_ms", "median_sys_ms", "median_minor_faults")
INFERENCE_WARMUP_CALLS = 2


def memory_environment(name: str, base: Mapping) -> dict:
    """The environment of variant `name`'s children (`variant_environment` over `MEMORY_VARIANTS`)."""
    return variant_environment(MEMORY_VARIANTS[name]["env"], (v["env"] for v in MEMORY_VARIANTS.values()), base)


def tf_memory_info() -> dict:
    """TensorFlow's CPU allocator statistics ({current_gb, peak_gb}); where its allocator keeps none (oneDNN off:
    TensorFlow's plain CPU allocator), both None and why."""
    import tensorflow as tf
    from ff3d_tf import internals
    try:
        info = tf.config.experimental.get_memory_info("CPU:0")
        return {"current_gb": info["current"] / GB, "peak_gb": info["peak"] / GB}
    except (ValueError, RuntimeError) as e:
        why = "oneDNN operations off: TensorFlow's plain CPU allocator keeps no statistics" \
            if not internals.onednn_enabled() else str(e)[:200]
        return {"current_gb": None, "peak_gb": None, "unavailable": why}


def snapshot() -> dict:
    """Resident set, threads, glibc's accounting and smaps of this process (`lab.bench`'s readers)."""
    return {"rss_gb": bench.proc_status("VmRSS"), "threads": bench.proc_status("Threads"),
            "mallinfo2": bench.mallinfo2(), "smaps_gb": bench.smaps_by_kind(), "smaps_rollup_gb": bench.smaps_rollup()}


def measure_calls(fn: Callable, calls: int, trim: bool = False) -> dict:
    """Runs `fn` (returning tensors) `calls` times: per call wall, CPU and system-CPU ms, minor faults, RSS after,
    peak RSS during (`bench.timed_with_usage`). `trim`: glibc malloc_trim(0) after each call, counted in its time."""
    rows = bench.measure(bench.fetched(fn), calls, reading=functools.partial(bench.timed_with_usage, trim=trim))
    timing = medians(rows, ("ms", "cpu_ms", "sys_ms", "minor_faults"))
    return {**{f"median_{k}": v for k, v in timing.items()}, "min_ms": min(r["ms"] for r in rows),
            "rss_between_gb": rows[-1]["rss_after_gb"], "peak_rss_gb": max(r["peak_rss_gb"] for r in rows),
            "calls": rows}


def memory_child(kind: str, config: str, overrides: list, points: int, steps: int, calls: int,
                 trim_after_call: bool) -> dict:
    """(In a child.) One measurement of `kind`, with the environment the child was started with. train: one warm-up
    step (tracing, compilation) then `steps` timed steps; infer: `INFERENCE_WARMUP_CALLS` warm-up calls then `calls`
    timed calls. Snapshots (`snapshot`) after TensorFlow's import, after building, between calls and after
    gc.collect() + malloc_trim(0)."""
    import gc
    import importlib

    import numpy as np
    from ff3d_tf.config import load_config
    if kind not in MEMORY_KINDS:
        raise ValueError(f"kind={kind!r}: one of {MEMORY_KINDS}")
    cfg = load_config(config or None, overrides)  # a bad config fails here, before TensorFlow starts
    for module in ("ff3d_tf.model.forward", "lab.training.bench_steps"):  # in memory before the first snapshot
        importlib.import_module(module)
    from ff3d_tf import internals
    from ff3d_tf.model import compile as compile_lib
    mode = compile_lib.resolve_compile_mode(cfg.model.compile, job="train" if kind == "train" else "inference")
    rng = np.random.default_rng(0)
    out = {"compile_mode": mode, "onednn_enabled": internals.onednn_enabled(), "tensorflow_imported": snapshot()}
    if kind == "train":
        step, padded = _train_step(cfg, mode, points, rng)
        out["built"] = {**snapshot(), "tf_allocator": tf_memory_info()}
        _, out["warmup_s"] = bench.elapsed(bench.fetched(step))
        out["timed"] = measure_calls(step, steps, trim_after_call)
    else:
        forward, padded = _forward(cfg, mode, points, rng)
        out["built"] = {**snapshot(), "tf_allocator": tf_memory_info()}
        _, out["warmup_s"] = bench.elapsed(lambda: [bench.fetch(forward()) for _ in range(INFERENCE_WARMUP_CALLS)])
        out["timed"] = measure_calls(forward, calls, trim_after_call)
    out["padded_points"] = padded
    out["between_calls"] = {**snapshot(), "tf_allocator": tf_memory_info()}
    gc.collect()
    cpu.malloc_trim()
    out["after_gc_and_malloc_trim"] = snapshot()
    return out


def memory_round_summary(measured: Mapping[str, Mapping]) -> dict:
    """{kind: the readings a table compares} of one round's children ({kind: a child's result}); a failed child
    ({"error"}) or a kind not measured is left out."""
    summary = {}
    for kind in MEMORY_KINDS:
        r = measured.get(kind)
        if not r or "error" in r:
            continue
        between, timed = r["between_calls"], r["timed"]
        allocator = between["mallinfo2"] or {}
        summary[kind] = {
            "rss_between_gb": timed["rss_between_gb"], "peak_rss_gb": timed["peak_rss_gb"],
            "rss_built_gb": r["built"]["rss_gb"], "rss_after_trim_gb": r["after_gc_and_malloc_trim"]["rss_gb"],
            **{k: timed[k] for k in MEMORY_TIMES},
            "mallinfo2_gb": {k: allocator.get(k) for k in ("uordblks", "fordblks", "hblkhd", "hblks")},
            "smaps_anon_gb": between["smaps_rollup_gb"].get("Anonymous"),
            # resident file pages (Rss, not Pss: Pss shares them out among other processes mapping them)
            "smaps_file_gb": between["smaps_gb"].get("file_tensorflow", 0.0) + between["smaps_gb"].get("file_other",
                                                                                                     0.0),
            "tf_allocator": between["tf_allocator"]}
    return summary


def combine_rounds(rounds: Sequence[Mapping]) -> dict:
    """Per kind: the first round's memory readings, each timing field's median over the rounds that measured the kind
    (`medians`) and their count."""
    out = {}
    for kind, first in rounds[0].items():
        rows = [r[kind] for r in rounds if kind in r]
        out[kind] = {**first, **medians(rows, MEMORY_TIMES), "rounds": len(rows)}
    return out


def memory_study(config: str, overrides: Sequence[str], variants: Sequence[str], points: int, steps: int,
                 calls: int, kinds: Sequence[str] = MEMORY_KINDS, repeat: int = 1,
                 repeat_variants: Sequence[str] | None = None, child_timeout_s: float | None = None, note: str = "",
                 log_fn: Callable[[str], None] = print) -> dict:
    """Every variant of `variants`, one child per kind, `repeat` rounds (those after the first: `repeat_variants`,
    default all); the JSON of lab/tools/profile_memory.py. A child that fails or runs past `child_timeout_s` is recorded
    as {"error": why} and left out of the summaries."""
    unknown = [n for n in variants if n not in MEMORY_VARIANTS]
    if unknown:
        raise ValueError(f"unknown variants {unknown}; known: {', '.join(MEMORY_VARIANTS)}")
    if [k for k in kinds if k not in MEMORY_KINDS]:
        raise ValueError(f"kinds {list(kinds)}: of {', '.join(MEMORY_KINDS)}")
    again = list(repeat_variants or variants)
    if not set(again) <= set(variants):
        raise ValueError(f"repeat variants {again}: not all in the variants {list(variants)}")
    load_start = bench.load_average()
    results = {}
    for round_ in range(repeat):
        for name in variants if round_ == 0 else again:
            variant = MEMORY_VARIANTS[name]
            r = results.setdefault(name, {**variant, "rounds": []})
            kwargs = {"config": _absolute(config), "overrides": [*overrides, *variant["set"]], "points": points,
                      "steps": steps, "calls": calls, "trim_after_call": variant["trim_after_call"]}
            measured = {kind: children.run_child(f"{__name__}:memory_child", {"kind": kind, **kwargs},
                                                 base=memory_environment(name, os.environ), timeout_s=child_timeout_s,
                                                 what=f"{name} {kind}", on_error="record") for kind in kinds}
            if round_ == 0:
                r.update(measured)  # the first round's readings in full
            r["rounds"].append(memory_round_summary(measured))
            r["summary"] = combine_rounds(r["rounds"])
            log_fn(f"round {round_ + 1} {name}: " + "; ".join(
                f"{k} RSS between {v['rss_between_gb']:.2f} GB, peak {v['peak_rss_gb']:.2f} GB, {v['median_ms']:.0f} "
                f"ms (CPU {v['median_cpu_ms']:.0f} ms)" for k, v in r["rounds"][-1].items())
                + "".join(f"; {k} failed: {m['error'][-300:]}" for k, m in measured.items() if "error" in m))
    load_end = bench.load_average()
    summary_note = (
        f"Load average {' '.join(load_start)} at start, {' '.join(load_end)} at end, on {os.cpu_count()} CPUs shared "
        f"with other jobs: wall ms move with that load, CPU ms (user + system of the process) much less. Measured per "
        f"variant in fresh processes: the Trainer's step (forward, backward, Adam) on one in-memory batch of {points} "
        f"points, batch 1, 1 warm-up + {steps} steps; the compiled forward, {INFERENCE_WARMUP_CALLS} warm-up + {calls} "
        f"calls; RSS right after each call (between calls), VmHWM during it, glibc mallinfo2, TensorFlow's allocator "
        f"stats, smaps by kind, before and after malloc_trim(0). Summary times: median over {repeat} round(s) "
        f"(variants in turn; `rounds` per variant), memory readings from the first round (in full under train/infer). "
        f"{note}").strip()
    return {"note": summary_note, "cpu": cpu.describe(), "cpu_count": os.cpu_count(),
            "load_average_at_start": load_start, "load_average_at_end": load_end, "config": config,
            "overrides": list(overrides), "points": points, "batch": 1, "steps": steps, "calls": calls,
            "repeat": repeat, "variants": results}
