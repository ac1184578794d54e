"""What holds the resident memory between training steps and between inference calls, per allocator setting. JSON out.

python tools/profile_memory.py --config configs/fastflow3d_waymo.yaml --out benchmarks/memory_cpu.json
    [--variants tf_bfc_pool,system_allocator,...] [--points 32000] [--steps 5] [--calls 5]
    [--repeat 3 --repeat_variants tf_bfc_pool,system_allocator]

Every variant runs in fresh child processes (one training, one inference) with its own environment, set before Python
starts, so allocator settings never leak from one variant into the next: the environment keys any variant sets are
removed from the others', and every variant states TF_ONEDNN_USE_SYSTEM_ALLOCATOR explicitly. Training: the Trainer's
own step (forward, backward, Adam; `Trainer.step`) on one batch of --points points (the benchmark cloud of
`ff3d_tf.bench`) held in memory, batch 1, one warm-up step (tracing, compilation) then --steps timed steps.
Inference: the predictor's compiled forward (`compiled_forward`) at --points, two warm-up calls then --calls timed
calls.

Per call: wall ms, CPU ms of the whole process (user + system, all threads: less moved by other load than wall time),
system-CPU ms and minor page faults (fresh pages the kernel had to zero), resident set right after the call (what
the process holds between calls, no trim) and the peak during the call (VmHWM, reset before it). At the end of the
calls: glibc's accounting (mallinfo2: `uordblks` in use in the arenas, `fordblks` free in them, `hblkhd` in live
mmapped chunks, `hblks` their count), TensorFlow's allocator statistics (`get_memory_info('CPU:0')`: bytes in use
and the peak, where the allocator keeps them), /proc/self/smaps summed by kind (the TensorFlow .so files, other
files, [heap], anonymous executable = JIT code of XLA and oneDNN, other anonymous), smaps_rollup; then the same after
gc.collect() + glibc malloc_trim(0).
"""
import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile

import _common

from ff3d_tf import bench, cpu

# name -> environment, config overrides, trim (glibc malloc_trim(0) after every call, inside its time), what it tests.
# Every variant names TF_ENABLE_ONEDNN_OPTS and TF_ONEDNN_USE_SYSTEM_ALLOCATOR, so that neither the caller's
# environment nor the CPU decides them: unset, TensorFlow turns oneDNN on only on CPUs with AVX512_VNNI, AVX512_BF16
# or AMX (`ff3d_tf.cpu`), and without oneDNN there is no BFC pool and no allocator statistics.
_HEAP = "glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=68719476736"  # every chunk from the heap, no auto-trim


def _v(env, what, sets=(), trim=False):
    return {"env": env, "set": list(sets), "trim_after_call": trim, "what": what}


_BFC = {"TF_ENABLE_ONEDNN_OPTS": "1", "TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "0"}
_SYS = {"TF_ENABLE_ONEDNN_OPTS": "1", "TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "1"}
VARIANTS = {
    "tf_bfc_pool": _v(_BFC, "TensorFlow's default with oneDNN: tensors of >= 256 KB come from the oneDNN CPU "
                            "allocator's BFC pool, which keeps every region it grew to"),
    "bfc_trim": _v(_BFC, "BFC pool, malloc_trim(0) after every call", trim=True),
    "bfc_arena_max_2": _v({**_BFC, "MALLOC_ARENA_MAX": "2"}, "BFC pool, glibc limited to 2 malloc arenas"),
    "bfc_trim_mmap_thresholds": _v({**_BFC, "GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0:"
                                                              "glibc.malloc.mmap_threshold=131072"},
                                   "BFC pool, glibc trims freed heap at once and mmaps every chunk >= 128 KB"),
    "bfc_onednn_primitive_cache_0": _v({**_BFC, "ONEDNN_PRIMITIVE_CACHE_CAPACITY": "0"},
                                       "BFC pool, oneDNN's primitive cache off"),
    "onednn_off": _v({**_BFC, "TF_ENABLE_ONEDNN_OPTS": "0"},
                     "oneDNN off: Eigen kernels and TensorFlow's plain CPU allocator (malloc/free, no pool)"),
    "system_allocator": _v(_SYS, "every tensor from glibc malloc/free: a freed tensor above glibc's mmap threshold "
                                 "(<= 32 MB) is unmapped at once, the next one faults in fresh pages"),
    "system_allocator_thp": _v({**_SYS, "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"},
                               "system allocator, glibc asks for transparent huge pages (fewer page faults)"),
    "system_heap": _v({**_SYS, "GLIBC_TUNABLES": _HEAP}, "system allocator, glibc serves every chunk from its heap "
                                                          "(no mmap) and never trims it by itself: a pool like BFC"),
    "system_heap_trim": _v({**_SYS, "GLIBC_TUNABLES": _HEAP}, "system_heap, malloc_trim(0) after every call",
                           trim=True),
    "system_heap_trim_thp": _v({**_SYS, "GLIBC_TUNABLES": _HEAP + ":glibc.malloc.hugetlb=1"},
                               "system_heap_trim with transparent huge pages", trim=True),
    "system_arena1_heap_trim": _v({**_SYS, "GLIBC_TUNABLES": "glibc.malloc.arena_max=1:" + _HEAP},
                                  "system allocator, one malloc arena (heap chunks of any size: a thread arena's "
                                  "heap stops at 64 MB and falls back to mmap), heap kept within a call, "
                                  "malloc_trim(0) after every call", trim=True),
    "system_arena1_heap_trim_thp": _v({**_SYS, "GLIBC_TUNABLES": "glibc.malloc.arena_max=1:glibc.malloc.hugetlb=1:"
                                                                 + _HEAP},
                                      "system_arena1_heap_trim with transparent huge pages", trim=True),
    "xla_bfc_pool": _v(_BFC, "compile mode xla (whole step one XLA CPU program), BFC pool", ("model.compile=xla",)),
    "xla_system_allocator": _v(_SYS, "compile mode xla, system allocator", ("model.compile=xla",)),
}
DEFAULT_VARIANTS = ",".join(VARIANTS)
GB = bench.GB


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
    """Resident set, threads, glibc's accounting and smaps of this process (`ff3d_tf.bench`'s readers)."""
    return {"rss_gb": bench.proc_status("VmRSS"), "threads": bench.proc_status("Threads"),
            "mallinfo2": bench.mallinfo2(), "smaps_gb": bench.smaps_by_kind(), "smaps_rollup_gb": bench.smaps_rollup()}


def measure_calls(fn, calls: int, trim: bool = False) -> dict:
    """Runs `fn` (returning tensors) `calls` times: per call wall, CPU and system-CPU ms, minor faults, RSS after,
    peak RSS during (`bench.timed_with_usage`). `trim`: glibc malloc_trim(0) after each call, counted in its time."""
    rows = bench.measure(bench.fetched(fn), calls, reading=functools.partial(bench.timed_with_usage, trim=trim))

    def med(k):
        return bench.middle([r[k] for r in rows])
    return {"median_ms": med("ms"), "min_ms": min(r["ms"] for r in rows), "median_cpu_ms": med("cpu_ms"),
            "median_sys_ms": med("sys_ms"), "median_minor_faults": med("minor_faults"),
            "rss_between_gb": rows[-1]["rss_after_gb"], "peak_rss_gb": max(r["peak_rss_gb"] for r in rows),
            "calls": rows}


def child(args) -> dict:
    """One measurement (training or inference) in this process, with the environment it was started with."""
    import gc

    import numpy as np
    from ff3d_tf.config import replace_config
    from ff3d_tf.model import build_model
    from ff3d_tf.model import compile as compile_lib
    from ff3d_tf.model.forward import compiled_forward
    from ff3d_tf.training import bench_steps

    cfg = _common.load(args)
    mode = compile_lib.resolve_compile_mode(cfg.model.compile)
    rng = np.random.default_rng(0)
    from ff3d_tf import internals
    out = {"compile_mode": mode, "onednn_enabled": internals.onednn_enabled(), "tensorflow_imported": snapshot()}
    if args.child == "train":
        labelled, padded = bench_steps.example(cfg, rng, args.points, labels=True)
        step = bench_steps.train_steps(cfg, {mode: mode}, labelled)[mode]  # the Trainer's step, batch 1
        out["built"] = {**snapshot(), "tf_allocator": tf_memory_info()}
        _, out["warmup_s"] = bench.elapsed(bench.fetched(step))  # tracing and compilation
        out["timed"] = measure_calls(step, args.steps, args.trim_after_call)
    else:
        model = build_model(replace_config(cfg, {"train.global_batch_size": 1}), mode)
        forward = compiled_forward(model, cfg.model.jit_compile)
        inputs, padded = bench_steps.example(cfg, rng, args.points)
        out["built"] = {**snapshot(), "tf_allocator": tf_memory_info()}
        _, out["warmup_s"] = bench.elapsed(lambda: [bench.fetch(forward(inputs)) for _ in range(2)])
        out["timed"] = measure_calls(lambda: forward(inputs), args.calls, args.trim_after_call)
    out["padded_points"] = padded
    out["between_calls"] = {**snapshot(), "tf_allocator": tf_memory_info()}
    gc.collect()
    bench.malloc_trim()
    out["after_gc_and_malloc_trim"] = snapshot()
    return out


def _summary(train: dict | None, infer: dict | None) -> dict:
    s = {}
    for name, r in (("train", train), ("infer", infer)):
        if not r or "error" in r:
            continue
        b, m = r["between_calls"], r["between_calls"]["mallinfo2"] or {}
        s[name] = {"rss_between_gb": r["timed"]["rss_between_gb"], "peak_rss_gb": r["timed"]["peak_rss_gb"],
                   "rss_built_gb": r["built"]["rss_gb"], "rss_after_trim_gb": r["after_gc_and_malloc_trim"]["rss_gb"],
                   "median_ms": r["timed"]["median_ms"], "median_cpu_ms": r["timed"]["median_cpu_ms"],
                   "median_sys_ms": r["timed"]["median_sys_ms"],
                   "median_minor_faults": r["timed"]["median_minor_faults"],
                   "mallinfo2_gb": {k: m.get(k) for k in ("uordblks", "fordblks", "hblkhd", "hblks")},
                   "smaps_anon_gb": b["smaps_rollup_gb"].get("Anonymous"),
                   # resident file pages (Rss, not Pss: Pss shares them out among other processes mapping them)
                   "smaps_file_gb": b["smaps_gb"].get("file_tensorflow", 0.0) + b["smaps_gb"].get("file_other", 0.0),
                   "tf_allocator": b["tf_allocator"]}
    return s


_TIMING = ("median_ms", "median_cpu_ms", "median_sys_ms", "median_minor_faults")


def combine_rounds(rounds: list[dict]) -> dict:
    """Per kind: the first round's memory readings, and each timing field's median over the rounds (`bench.middle`)."""
    out = {}
    for kind, first in rounds[0].items():
        values = {k: [r[kind][k] for r in rounds if kind in r] for k in _TIMING}
        out[kind] = {**first, **{k: bench.middle(v) for k, v in values.items()}, "rounds": len(values["median_ms"])}
    return out


def child_environment(name: str, base: dict) -> dict:
    """`base` without any key that some variant sets, plus variant `name`'s own settings."""
    knobs = {k for v in VARIANTS.values() for k in v["env"]}
    return {**{k: v for k, v in base.items() if k not in knobs}, **VARIANTS[name]["env"]}


def _run_child(args, name: str, kind: str) -> dict:
    variant = VARIANTS[name]
    env = child_environment(name, os.environ)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "child.json")
        cmd = [sys.executable, os.path.abspath(__file__), "--child", kind, "--out", path, "--points", str(args.points),
               "--steps", str(args.steps), "--calls", str(args.calls), "--config", args.config or ""]
        cmd += [a for s in (*args.set, *variant["set"]) for a in ("--set", s)]
        cmd += ["--trim_after_call"] if variant["trim_after_call"] else []
        run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.child_timeout_s)
        if run.returncode != 0:
            return {"error": run.stderr[-2000:]}
        with open(path) as f:
            return json.load(f)


def _args(argv=None):
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--variants", default=DEFAULT_VARIANTS, help=f"comma-separated, of: {', '.join(VARIANTS)}")
    p.add_argument("--points", type=int, default=32000)
    p.add_argument("--steps", type=int, default=5, help="timed training steps (after one warm-up step)")
    p.add_argument("--calls", type=int, default=5, help="timed inference calls (after two warm-up calls)")
    p.add_argument("--kinds", default="train,infer", help="train, infer or both")
    p.add_argument("--repeat", type=int, default=1,
                   help="rounds over the variants, in turn (fresh processes each): the summary's times are the "
                        "median over the rounds, so a change of load hits all variants alike")
    p.add_argument("--repeat_variants", default=None, help="the variants of the rounds after the first (default: all)")
    p.add_argument("--child_timeout_s", type=int, default=1800)
    p.add_argument("--note", default="", help="findings, appended to the JSON's note")
    p.add_argument("--out", default="benchmarks/memory_cpu.json")
    p.add_argument("--child", choices=("train", "infer"), help=argparse.SUPPRESS)  # internal: one measurement
    p.add_argument("--trim_after_call", action="store_true", help=argparse.SUPPRESS)  # internal, set per variant
    return p.parse_args(argv)


def main(argv=None):
    args = _args(argv)
    if args.child:
        result = child(args)
        with open(args.out, "w") as f:
            json.dump(result, f)
        return
    names = args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        sys.exit(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    kinds = args.kinds.split(",")
    load_start = bench.load_average()
    again = args.repeat_variants.split(",") if args.repeat_variants else names
    if not set(again) <= set(names):
        sys.exit(f"--repeat_variants {again}: not all in --variants")
    results = {}
    for round_ in range(args.repeat):
        for name in names if round_ == 0 else again:
            r = results.setdefault(name, {**VARIANTS[name], "rounds": []})
            measured = {kind: _run_child(args, name, kind) for kind in kinds}
            if round_ == 0:
                r.update(measured)  # the first round's readings in full
            r["rounds"].append(_summary(measured.get("train"), measured.get("infer")))
            r["summary"] = combine_rounds(r["rounds"])
            print(f"round {round_ + 1} {name}: " + "; ".join(
                f"{k} RSS between {v['rss_between_gb']:.2f} GB, peak {v['peak_rss_gb']:.2f} GB, {v['median_ms']:.0f} "
                f"ms (CPU {v['median_cpu_ms']:.0f} ms)" for k, v in r["rounds"][-1].items())
                + "".join(f"; {k} failed: {m['error'][-300:]}" for k, m in measured.items() if "error" in m),
                flush=True)
    load_end = bench.load_average()
    note = (f"Load average {' '.join(load_start)} at start, {' '.join(load_end)} at end, on {os.cpu_count()} CPUs "
            f"shared with other jobs: wall ms move with that load, CPU ms (user + system of the process) much less. "
            f"Measured per variant in fresh processes: the Trainer's step (forward, backward, Adam) on one in-memory "
            f"batch of {args.points} points, batch 1, 1 warm-up + {args.steps} steps; the compiled forward, 2 warm-up "
            f"+ {args.calls} calls; RSS right after each call (between calls), VmHWM during it, glibc mallinfo2, "
            f"TensorFlow's allocator stats, smaps by kind, before and after malloc_trim(0). Summary times: median over "
            f"{args.repeat} round(s) (variants in turn; `rounds` per variant), memory readings from the first round "
            f"(in full under train/infer). {args.note}").strip()
    out = {"note": note, "cpu": cpu.describe(), "cpu_count": os.cpu_count(), "load_average_at_start": load_start,
           "load_average_at_end": load_end, "config": args.config, "overrides": args.set, "points": args.points,
           "batch": 1, "steps": args.steps, "calls": args.calls, "repeat": args.repeat, "variants": results}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
