"""The CPU a process runs on, as the numerical libraries see it: model, vendor, the instruction-set flags that choose
their kernels, and the limits set on them through the environment.

Two libraries pick CPU kernels by instruction set: oneDNN (TensorFlow's convolutions and matmuls when its oneDNN
operations are on) and XLA's CPU backend. Both can be capped below what the CPU has, which is how a machine
emulates an older one (e.g. an AVX2-only AMD Zen 3 on an AVX-512 Zen 4):

  ONEDNN_MAX_CPU_ISA=AVX2              oneDNN's dispatcher control (oneDNN docs, "CPU Dispatcher Control")
  XLA_FLAGS=--xla_cpu_max_isa=AVX2     XLA's CPU code generation
  TF_ENABLE_ONEDNN_OPTS=0|1            TensorFlow's oneDNN operations off or on; unset, TensorFlow turns them on for
                                       x86 CPUs with AVX512_VNNI, AVX512_BF16 or AMX (TensorFlow 2.9 release notes),
                                       so an AVX2-only CPU runs Eigen kernels and TensorFlow's plain CPU allocator
  TF_CPU_ALLOCATOR_USE_BFC=true        TensorFlow's CPU allocator as a BFC pool (what oneDNN's operations bring with
                                       them); unset, an AVX2-only CPU's tensors come from malloc and free

On an AVX2-only CPU, oneDNN has no bfloat16 convolutions: with its operations on, `model.mixed_precision=true` stops
with oneDNN's "could not create a primitive descriptor". Whether oneDNN's float32 kernels beat Eigen's there depends on
the model and the compile mode (benchmarks/cpu_onednn_avx2.json). `startup_environment` is the project's choice per
CPU and job, that the tools apply when they start (tools/_common.py), before TensorFlow is imported; what the user set
is always kept (docs/deployment.md says what each CPU gets and why).

`EMULATIONS` names such caps by the CPU they stand for (`make test EMULATE_CPU=zen3`). No TensorFlow here: whether
TensorFlow's oneDNN operations are on in a process is `ff3d_tf.internals.onednn_enabled`.
"""
from __future__ import annotations

import dataclasses
import os
import re

CPUINFO_PATH = "/proc/cpuinfo"
# Flags that choose kernels in oneDNN and XLA (Linux /proc/cpuinfo names), from older to newer.
KERNEL_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_tile")
# oneDNN's ISA names (ONEDNN_MAX_CPU_ISA) below which its bfloat16 / AMX kernels are not dispatched.
_ONEDNN_ISAS_WITHOUT_BF16 = ("SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2", "AVX512_CORE", "AVX512_CORE_VNNI")
_ONEDNN_ISAS_WITHOUT_AMX = _ONEDNN_ISAS_WITHOUT_BF16 + ("AVX512_CORE_BF16", "AVX10_1_512", "AVX512_CORE_FP16")
_XLA_MAX_ISA = re.compile(r"--xla_cpu_max_isa=(\S+)")

# Environment that makes this machine's libraries behave as on the named CPU (as far as kernel choice goes; the
# CPU's own speed and cache sizes stay this machine's). zen3: an AVX2-only CPU with TensorFlow's default there (oneDNN
# off: Eigen's kernels); zen3_onednn: the same CPU with TF_ENABLE_ONEDNN_OPTS=1.
EMULATIONS = {
    "zen3": {"ONEDNN_MAX_CPU_ISA": "AVX2", "XLA_FLAGS": "--xla_cpu_max_isa=AVX2", "TF_ENABLE_ONEDNN_OPTS": "0"},
    "zen3_onednn": {"ONEDNN_MAX_CPU_ISA": "AVX2", "XLA_FLAGS": "--xla_cpu_max_isa=AVX2", "TF_ENABLE_ONEDNN_OPTS": "1"},
}


# x86 flags with which TensorFlow turns its oneDNN operations on by itself (TensorFlow 2.9 release notes: AVX512_VNNI,
# AVX512_BF16, AMX); without them it runs Eigen's kernels.
TENSORFLOW_ONEDNN_FLAGS = ("avx512_vnni", "avx512_bf16", "amx_tile", "amx_bf16", "amx_int8")
# What `startup_environment` may set, and the jobs it tells apart.
STARTUP_KEYS = ("TF_ENABLE_ONEDNN_OPTS", "TF_CPU_ALLOCATOR_USE_BFC", "MALLOC_ARENA_MAX")
STARTUP_JOBS = ("train", "inference")
# The start-up environment per job on an x86 CPU with AVX2 but none of TENSORFLOW_ONEDNN_FLAGS usable (AMD Zen 3,
# Intel Haswell to Comet Lake): oneDNN off (TensorFlow's own default there; oneDNN has no bfloat16 convolutions there).
# To serve, TensorFlow's CPU allocator as a BFC pool (Eigen's kernels then reuse memory instead of faulting in fresh
# pages every call); to train, malloc and free as TensorFlow has them there (the pool keeps the region it grew to for
# the training program's temporaries, a higher peak for about the same step time), from two glibc arenas instead of
# up to eight per core: the threads' freed blocks are reused across threads rather than held in arenas of their own
# (`limit_malloc_arenas`). The measurement with them ("after"): benchmarks/cpu_step_avx2.json and
# benchmarks/cpu_step_avx2_memory.json (lab/tools/benchmark_cpu_step.py, both libraries capped to AVX2),
# docs/benchmarks.md.
AVX2_STARTUP = {"train": {"TF_ENABLE_ONEDNN_OPTS": "0", "MALLOC_ARENA_MAX": "2"},
                "inference": {"TF_ENABLE_ONEDNN_OPTS": "0", "TF_CPU_ALLOCATOR_USE_BFC": "true"}}


@dataclasses.dataclass(frozen=True)
class CpuInfo:
    model_name: str  # "AMD EPYC 7B13", "" where /proc/cpuinfo has none
    vendor: str  # "GenuineIntel", "AuthenticAMD", ""
    family_model: str  # "cpu family/model" as cpuinfo numbers them, e.g. "25/17" (AMD Zen 4 Genoa), "" where absent
    flags: frozenset  # the flags every processor lists
    cpu_count: int


def parse_cpuinfo(text: str) -> CpuInfo:
    """The text of /proc/cpuinfo -> CpuInfo (flags common to every processor; empty where no "flags" line)."""
    fields = [[part.strip() for part in line.split(":", 1)] for line in text.splitlines() if ":" in line]

    def first(key):
        return next((value for k, value in fields if k == key), "")
    flag_sets = [set(value.split()) for key, value in fields if key == "flags"]
    family_model = f"{first('cpu family')}/{first('model')}" if first("cpu family") else ""
    return CpuInfo(first("model name"), first("vendor_id"), family_model,
                   frozenset(set.intersection(*flag_sets)) if flag_sets else frozenset(),
                   sum(1 for key, _ in fields if key == "processor"))


def read_cpuinfo(path: str | None = None) -> CpuInfo | None:
    """This machine's CpuInfo, None where the file cannot be read (not Linux)."""
    try:
        with open(path or CPUINFO_PATH) as f:
            return parse_cpuinfo(f.read())
    except OSError:
        return None


def isa_limits(environ=None) -> dict:
    """The caps set in the environment: {"onednn_max_isa": ..., "xla_cpu_max_isa": ..., "tf_enable_onednn_opts": ...}
    (None where unset)."""
    environ = os.environ if environ is None else environ
    xla = _XLA_MAX_ISA.search(environ.get("XLA_FLAGS", ""))
    return {"onednn_max_isa": environ.get("ONEDNN_MAX_CPU_ISA"), "xla_cpu_max_isa": xla.group(1) if xla else None,
            "tf_enable_onednn_opts": environ.get("TF_ENABLE_ONEDNN_OPTS")}


def usable_flags(info: CpuInfo, environ=None) -> frozenset:
    """The CPU's flags less those that oneDNN's cap (ONEDNN_MAX_CPU_ISA) keeps it from using: bfloat16 and AMX below
    AVX512_CORE_BF16, AMX below AVX10_1_512_AMX, everything AVX-512 at AVX2 and below."""
    cap = (isa_limits(environ)["onednn_max_isa"] or "").upper()
    dropped = set()
    if cap in _ONEDNN_ISAS_WITHOUT_BF16:
        dropped |= {"avx512_bf16", "amx_bf16", "amx_tile", "amx_int8"}
    if cap in _ONEDNN_ISAS_WITHOUT_AMX:
        dropped |= {"amx_bf16", "amx_tile", "amx_int8"}
    if cap in ("SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2"):
        dropped |= {f for f in info.flags if f.startswith("avx512")}
    return info.flags - dropped


def describe(info: CpuInfo | None = None, environ=None) -> dict:
    """The CPU for a benchmark's JSON or a test run's header: model, vendor, cores, kernel-choosing flags (the CPU's
    and those left usable under the caps) and the caps."""
    info = info or read_cpuinfo() or CpuInfo("unknown (no readable /proc/cpuinfo)", "", "", frozenset(), os.cpu_count())
    return {"model_name": info.model_name, "vendor": info.vendor, "family_model": info.family_model,
            "cpu_count": info.cpu_count,
            "flags": [f for f in KERNEL_FLAGS if f in info.flags],
            "usable_flags": [f for f in KERNEL_FLAGS if f in usable_flags(info, environ)],
            "limits": {k: v for k, v in isa_limits(environ).items() if v is not None}}


def one_line(description: dict) -> str:
    """`describe`'s dict as one line: "AMD EPYC (AuthenticAMD, family/model 25/17, 2 cores): avx2 fma avx512f ...;
    limits: ..."."""
    flags = " ".join(description["flags"]) or "none of " + ", ".join(KERNEL_FLAGS)
    limits = ", ".join(f"{k}={v}" for k, v in description["limits"].items()) or "none"
    usable = "" if description["usable_flags"] == description["flags"] else \
        f"; usable under the limits: {' '.join(description['usable_flags'])}"
    family = f" family/model {description['family_model']}," if description["family_model"] else ""
    return (f"{description['model_name']} ({description['vendor'] or 'unknown vendor'},{family} "
            f"{description['cpu_count']} cores): {flags}{usable}; limits: {limits}")


def emulation_env(name: str) -> str:
    """`EMULATIONS[name]` as KEY=VALUE words for `env` (the Makefile's EMULATE_CPU)."""
    if name not in EMULATIONS:
        raise SystemExit(f"EMULATE_CPU={name!r}: one of {', '.join(EMULATIONS)}")
    return " ".join(f"{k}={v}" for k, v in EMULATIONS[name].items())


def tensorflow_onednn_default(info: CpuInfo, environ=None) -> bool:
    """Whether TensorFlow turns its oneDNN operations on by itself on `info`'s CPU, judged on the flags left usable
    under the caps of `environ` (so that a capped CPU is judged as the one it emulates)."""
    return any(f in usable_flags(info, environ) for f in TENSORFLOW_ONEDNN_FLAGS)


def _glibc():
    """The C library as ctypes has it, or None where it is not glibc's libc.so.6."""
    import ctypes
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def limit_malloc_arenas(environ=None) -> int | None:
    """Applies `environ`'s (default os.environ) MALLOC_ARENA_MAX to this process with glibc's mallopt(M_ARENA_MAX):
    glibc reads the variable only when a process starts, so a tool that sets it in its own environment
    (`startup_environment`, tools/_common.py) applies it this way, before TensorFlow starts its threads. Returns the
    limit applied; None when the variable is unset, not a positive integer, or libc is not glibc."""
    value = (os.environ if environ is None else environ).get("MALLOC_ARENA_MAX", "")
    if not value.isdigit() or int(value) < 1:
        return None
    libc = _glibc()
    if libc is None:
        return None
    m_arena_max = -8  # glibc's malloc.h
    return int(value) if hasattr(libc, "mallopt") and libc.mallopt(m_arena_max, int(value)) == 1 else None


def malloc_trim() -> bool:
    """Returns the memory glibc's malloc holds free to the OS (malloc_trim(0): the top of every arena and the free
    pages inside them); False where libc is not glibc."""
    libc = _glibc()
    if libc is None or not hasattr(libc, "malloc_trim"):
        return False
    libc.malloc_trim(0)
    return True


def startup_environment(job: str, info: CpuInfo | None = None, environ=None) -> dict:
    """What a process about to import TensorFlow for `job` ("train" or "inference") adds to its environment
    (tools/_common.py applies it): a dict of `STARTUP_KEYS` and values. `info`: default this machine's CPU;
    `environ`: default os.environ (its caps decide which flags are usable).

      - no readable x86 flags, or no AVX2 among the usable ones: {} (TensorFlow's defaults);
      - a CPU on which TensorFlow turns oneDNN on by itself (`tensorflow_onednn_default`): TF_ENABLE_ONEDNN_OPTS=1,
        the same as its default, written out so that an emulation under caps gets what the real CPU gets (oneDNN's
        own allocator pools memory there). For training there, no pool or the AVX2 start-up lower the peak less
        than bfloat16 does and slow the step (benchmarks/cpu_step_amx.json, docs/benchmarks.md): the pool stays;
      - an AVX2 CPU below those: `AVX2_STARTUP[job]`, whatever the precision: oneDNN stays off, so bfloat16 never
        meets oneDNN on a CPU where it has no bfloat16 convolutions.

    A key already in `environ` is left out (the user's setting is kept)."""
    if job not in STARTUP_JOBS:
        raise ValueError(f"job={job!r}: one of {', '.join(STARTUP_JOBS)}")
    environ = os.environ if environ is None else environ
    info = info or read_cpuinfo()
    if info is None or "avx2" not in usable_flags(info, environ):
        chosen = {}
    elif tensorflow_onednn_default(info, environ):
        chosen = {"TF_ENABLE_ONEDNN_OPTS": "1"}
    else:
        chosen = dict(AVX2_STARTUP[job])
    return {k: v for k, v in chosen.items() if k not in environ}
