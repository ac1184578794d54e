"""What the benchmarks and profilers measure with: timers, the round robin, readings of this process and the one
synthetic benchmark cloud. NumPy and the standard library only: the TensorFlow-free XLA runners use it too.

Timing. `elapsed` times one call. A *reading* is one call's measurements as a dict: `timed` (wall ms),
`timed_with_memory` (and resident memory), `timed_with_usage` (and CPU time, page faults, memory). `measure` repeats
one callable, `round_robin` interleaves several, each after unmeasured warm-up calls, and both return every call's
reading; `summary` reduces call times to their median, mean and min. A measured callable must finish its work before
it returns: `fetched` makes a TensorFlow call wait for its results on the host; a JAX caller blocks until its results
are ready.

Readings of this process (Linux /proc, glibc): each has an explicit empty result where its file or library is missing
(nan, {}, [], False or None, as each says).

The benchmark cloud (`random_clouds`, `random_labels`): the made-up input of the portable XLA exports' reference
(`ff3d_tf.xla_export_dir`, where it is defined), which every benchmark that runs the model on made-up input uses too.
`write_json` is `ff3d_tf.json_io`'s.
"""
from __future__ import annotations

import ctypes
import functools
import math
import resource
import time
from typing import Callable, Sequence

import numpy as np

from ff3d_tf.cpu import malloc_trim
from ff3d_tf.json_io import write_json  # noqa: F401  (the lab's tools and studies save their results with it)
from ff3d_tf.xla_export_dir import random_clouds, random_labels  # noqa: F401  (the benchmark cloud)

GB = 1e9
STATISTICS = ("median", "mean", "min")


# -- timers ---------------------------------------------------------------------------------------------------------
def elapsed(fn: Callable, clock=time.perf_counter) -> tuple[object, float]:
    """(fn(), its wall time in seconds)."""
    start = clock()
    out = fn()
    return out, clock() - start


def timed(fn: Callable, clock=time.perf_counter) -> dict:
    """One call's reading: {"ms": wall time}."""
    return {"ms": 1e3 * elapsed(fn, clock)[1]}


def timed_with_memory(fn: Callable, clock=time.perf_counter) -> dict:
    """One call's reading: {"ms", "rss_before_gb" (resident set before the call, freed heap returned to the OS
    first), "peak_rss_gb" (VmHWM during the call, reset before it), "rss_after_gb" (resident set right after, no
    trim: what the process holds between calls), "peak_reset" (see `reset_peak_rss`)}."""
    peak_reset = reset_peak_rss(trim=True)
    before = proc_status("VmRSS")
    ms = timed(fn, clock)["ms"]
    return {"ms": ms, "rss_before_gb": before, "peak_rss_gb": proc_status("VmHWM"),
            "rss_after_gb": proc_status("VmRSS"), "peak_reset": peak_reset}


def timed_with_usage(fn: Callable, trim: bool = False, clock=time.perf_counter) -> dict:
    """One call's reading: {"ms", "cpu_ms" (user + system CPU of the whole process, all threads: less moved by other
    load than wall time), "sys_ms", "minor_faults" (fresh pages the kernel had to zero), "rss_after_gb" (no trim
    unless `trim`), "peak_rss_gb" (VmHWM, reset without trimming before the call), "peak_reset"}. `trim`: glibc
    malloc_trim(0) after the call, inside its time."""
    peak_reset = reset_peak_rss()
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), clock()
    fn()
    if trim:
        malloc_trim()
    t1, r1 = clock(), resource.getrusage(resource.RUSAGE_SELF)
    return {"ms": 1e3 * (t1 - t0), "cpu_ms": 1e3 * (r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime),
            "sys_ms": 1e3 * (r1.ru_stime - r0.ru_stime), "minor_faults": r1.ru_minflt - r0.ru_minflt,
            "rss_after_gb": proc_status("VmRSS"), "peak_rss_gb": proc_status("VmHWM"), "peak_reset": peak_reset}


def round_robin(calls: dict, runs: int, warmup: int = 1, reading: Callable = timed) -> dict[str, list[dict]]:
    """{name: callable} -> {name: its `runs` readings}: `warmup` unmeasured rounds (tracing, compilation), then `runs`
    rounds, each calling every callable once in the dict's order, so that a change of load on a shared machine hits
    all of them alike: compare their ratios within one run."""
    for _ in range(warmup):
        for fn in calls.values():
            fn()
    readings = {name: [] for name in calls}
    for _ in range(runs):
        for name, fn in calls.items():
            readings[name].append(reading(fn))
    return readings


def measure(fn: Callable, runs: int, warmup: int = 0, reading: Callable = timed) -> list[dict]:
    """`runs` readings of `fn` after `warmup` unmeasured calls."""
    return round_robin({"": fn}, runs, warmup, reading)[""]


def summary(ms: Sequence[float], statistics: Sequence[str] = STATISTICS) -> dict:
    """{"median_ms", "mean_ms", "min_ms"} (those of `statistics`) of call times in ms."""
    reduce = {"median": np.median, "mean": np.mean, "min": np.min}
    return {f"{s}_ms": float(reduce[s](ms)) for s in statistics}


def middle(values: Sequence[float]) -> float:
    """The median of an odd count; of an even count the upper of the two middle values (always a measured value)."""
    return float(sorted(values)[len(values) // 2])


def fetch(outputs):
    """`outputs` (arrays or tensors, nested in dicts, lists and tuples) as NumPy arrays: a TensorFlow call is done
    only when its results are on the host."""
    if isinstance(outputs, dict):
        return {k: fetch(v) for k, v in outputs.items()}
    if isinstance(outputs, (list, tuple)):
        return type(outputs)(fetch(v) for v in outputs)
    return None if outputs is None else np.asarray(outputs)


def fetched(fn: Callable) -> Callable:
    """`fn` that returns only once its results are on the host (`fetch`): what a timed TensorFlow call waits for."""
    return lambda: fetch(fn())


# -- readings of this process ---------------------------------------------------------------------------------------
def proc_status(field: str, path: str = "/proc/self/status") -> float:
    """A field of /proc/self/status: kB fields (VmRSS: resident now, VmHWM: peak since the last reset) in GB, the
    others (Threads) as counts; nan where the file or the field is missing."""
    try:
        with open(path) as f:
            lines = f.readlines()
    except OSError:
        return math.nan
    for line in lines:
        if line.startswith(field + ":"):
            parts = line.split()
            return int(parts[1]) * 1024 / GB if parts[-1] == "kB" else int(parts[1])
    return math.nan


class _MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                "fsmblks", "uordblks", "fordblks", "keepcost")]


@functools.lru_cache(maxsize=None)
def _libc():
    """glibc with mallinfo2 typed, or None (not glibc; mallinfo2 alone needs glibc >= 2.33)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    if hasattr(libc, "mallinfo2"):
        libc.mallinfo2.restype = _MallInfo2
    return libc


def reset_peak_rss(trim: bool = False, path: str = "/proc/self/clear_refs") -> bool:
    """Resets VmHWM to the current VmRSS (Linux >= 4.0); `trim` first returns freed heap to the OS (`malloc_trim`).
    False where the peak cannot be reset: it then covers the whole life of the process."""
    if trim:
        malloc_trim()
    try:
        with open(path, "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def mallinfo2() -> dict | None:
    """glibc's heap accounting, GB (counts for ordblks, smblks, hblks): arena = bytes the arenas got from the OS,
    uordblks in use in them, fordblks free in them, hblkhd in live mmapped chunks (every chunk above the mmap
    threshold); None where libc is not glibc >= 2.33."""
    libc = _libc()
    if libc is None or not hasattr(libc, "mallinfo2"):
        return None
    m = libc.mallinfo2()
    return {k: (getattr(m, k) if k in ("ordblks", "smblks", "hblks") else getattr(m, k) / GB)
            for k, _ in _MallInfo2._fields_}


def smaps_by_kind(path: str = "/proc/self/smaps") -> dict:
    """Resident GB of this process's mappings by kind: file_tensorflow (files under a tensorflow/ folder),
    file_other, heap ([heap]), other ([stack], [vdso], ...), anon_exec (anonymous executable: JIT code of XLA and
    oneDNN) and anon; {} where the file is missing."""
    try:
        with open(path) as f:
            lines = f.readlines()
    except OSError:
        return {}
    kinds, kind = {}, None
    for line in lines:
        parts = line.split()
        if parts and "-" in parts[0] and not parts[0].endswith(":"):  # a mapping's header line
            perms, name = parts[1], (parts[5] if len(parts) > 5 else "")
            if name.startswith("/"):
                kind = "file_tensorflow" if "/tensorflow/" in name else "file_other"
            elif name == "[heap]":
                kind = "heap"
            elif name.startswith("["):
                kind = "other"
            else:
                kind = "anon_exec" if "x" in perms else "anon"
        elif parts and parts[0] == "Rss:":
            kinds[kind] = kinds.get(kind, 0.0) + int(parts[1]) * 1024 / GB
    return kinds


def smaps_rollup(path: str = "/proc/self/smaps_rollup") -> dict:
    """Rss, Pss_Anon, Pss_File, Anonymous and AnonHugePages of /proc/self/smaps_rollup, GB (those the kernel has);
    {} where the file is missing (Linux < 4.14: the sums of `smaps_by_kind` still stand)."""
    try:
        with open(path) as f:
            lines = f.readlines()
    except OSError:
        return {}
    out = {}
    for line in lines:
        parts = line.split()
        if len(parts) == 3 and parts[2] == "kB":
            out[parts[0].rstrip(":")] = int(parts[1]) * 1024 / GB
    return {k: out[k] for k in ("Rss", "Pss_Anon", "Pss_File", "Anonymous", "AnonHugePages") if k in out}


def load_average(path: str = "/proc/loadavg") -> list[str]:
    """The system's 1, 5 and 15 minute load averages as the kernel writes them; [] where the file is missing."""
    try:
        with open(path) as f:
            return f.read().split()[:3]
    except OSError:
        return []
