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

On an AVX2-only CPU, TF_ENABLE_ONEDNN_OPTS=1 trains in float32 faster (benchmarks/cpu_onednn_avx2.json), but oneDNN
has no bfloat16 convolutions there: with it on, `model.mixed_precision=true` stops with oneDNN's "could not create a
primitive descriptor". The project keeps TensorFlow's default; the setting is the user's.

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
