"""ff3d_tf.cpu: /proc/cpuinfo parsing, the ISA caps read from the environment, the flags left usable under them."""
import os

import pytest

from ff3d_tf import cpu

ZEN4 = ("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\nmodel name\t: AMD EPYC 9B14\n"
        "flags\t\t: fpu sse2 avx2 fma avx512f avx512_vnni avx512_bf16 sha_ni\n\n"
        "processor\t: 1\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 17\nmodel name\t: AMD EPYC 9B14\n"
        "flags\t\t: fpu sse2 avx2 fma avx512f avx512_vnni avx512_bf16\n\n")


def test_parse_keeps_the_flags_every_processor_has():
    info = cpu.parse_cpuinfo(ZEN4)
    assert (info.model_name, info.vendor, info.family_model, info.cpu_count) == ("AMD EPYC 9B14", "AuthenticAMD",
                                                                                  "25/17", 2)
    assert "sha_ni" not in info.flags and {"avx2", "avx512_bf16"} <= info.flags
    assert cpu.parse_cpuinfo("") == cpu.CpuInfo("", "", "", frozenset(), 0)


def test_limits_and_usable_flags_under_each_emulation():
    info = cpu.parse_cpuinfo(ZEN4)
    assert cpu.isa_limits({}) == {"onednn_max_isa": None, "xla_cpu_max_isa": None, "tf_enable_onednn_opts": None}
    zen3 = cpu.EMULATIONS["zen3"]
    assert cpu.isa_limits({**zen3, "XLA_FLAGS": "--xla_dump_to=/x --xla_cpu_max_isa=AVX2"}) == {
        "onednn_max_isa": "AVX2", "xla_cpu_max_isa": "AVX2", "tf_enable_onednn_opts": "0"}
    assert cpu.usable_flags(info, zen3) == {"fpu", "sse2", "avx2", "fma"}
    assert cpu.EMULATIONS["zen3_onednn"]["TF_ENABLE_ONEDNN_OPTS"] == "1"
    assert cpu.usable_flags(info, {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_VNNI"}) == info.flags - {"avx512_bf16"}
    assert cpu.usable_flags(info, {}) == info.flags


def test_description_names_the_cpu_its_flags_and_the_caps():
    info = cpu.parse_cpuinfo(ZEN4)
    described = cpu.describe(info, cpu.EMULATIONS["zen3"])
    assert described["flags"] == ["avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16"]
    assert described["usable_flags"] == ["avx2", "fma"]
    line = cpu.one_line(described)
    assert line.startswith("AMD EPYC 9B14 (AuthenticAMD, family/model 25/17, 2 cores): avx2 fma avx512f avx512_vnni avx512_bf16; "
                           "usable under the limits: avx2 fma; limits: onednn_max_isa=AVX2")
    assert cpu.one_line(cpu.describe(info, {})).endswith("avx512_bf16; limits: none")
    assert cpu.describe(None, {})["cpu_count"] >= 1  # this machine (or the fallback where it has no cpuinfo)


ZEN3 = ("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 1\nmodel name\t: AMD EPYC 7B13\n"
        "flags\t\t: fpu sse2 avx avx2 fma\n\n")
SKYLAKE = ("processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\nmodel\t\t: 85\nmodel name\t: Intel Xeon\n"
           "flags\t\t: fpu sse2 avx2 fma avx512f avx512bw\n\n")
ARM = "processor\t: 0\nBogoMIPS\t: 50.00\nFeatures\t: fp asimd\n\n"


def test_startup_environment_per_cpu_and_job():
    zen3, zen4, skylake = cpu.parse_cpuinfo(ZEN3), cpu.parse_cpuinfo(ZEN4), cpu.parse_cpuinfo(SKYLAKE)
    for job in cpu.STARTUP_JOBS:
        # TensorFlow turns oneDNN on by itself on Zen 4 (avx512_vnni, avx512_bf16): the same, written out.
        assert cpu.startup_environment(job, zen4, {}) == {"TF_ENABLE_ONEDNN_OPTS": "1"}
        # AVX2 only (Zen 3), or AVX-512 without VNNI/BF16 (Skylake-SP: TensorFlow leaves oneDNN off there too).
        assert cpu.startup_environment(job, zen3, {}) == cpu.AVX2_STARTUP[job]
        assert cpu.startup_environment(job, skylake, {}) == cpu.AVX2_STARTUP[job]
        assert cpu.startup_environment(job, cpu.parse_cpuinfo(ARM), {}) == {}  # no x86 flags: TensorFlow's defaults
        # Zen 4 capped to AVX2 is judged as the Zen 3 it emulates; the emulation's own oneDNN setting is kept.
        caps = {k: v for k, v in cpu.EMULATIONS["zen3"].items() if k != "TF_ENABLE_ONEDNN_OPTS"}
        assert cpu.startup_environment(job, zen4, caps) == cpu.AVX2_STARTUP[job]
        assert "TF_ENABLE_ONEDNN_OPTS" not in cpu.startup_environment(job, zen4, cpu.EMULATIONS["zen3_onednn"])
        # Whatever the user set stays theirs.
        mine = {"TF_ENABLE_ONEDNN_OPTS": "1", "TF_CPU_ALLOCATOR_USE_BFC": "0", "MALLOC_ARENA_MAX": "8"}
        assert cpu.startup_environment(job, zen3, mine) == {}
    # Mixed precision never meets oneDNN on an AVX2 CPU: the start-up leaves it off for every job there.
    assert all(cpu.AVX2_STARTUP[job].get("TF_ENABLE_ONEDNN_OPTS") == "0" for job in cpu.STARTUP_JOBS)
    assert set(k for job in cpu.STARTUP_JOBS for k in cpu.AVX2_STARTUP[job]) <= set(cpu.STARTUP_KEYS)
    assert cpu.tensorflow_onednn_default(zen4, {}) and not cpu.tensorflow_onednn_default(zen3, {})
    with pytest.raises(ValueError, match="train, inference"):
        cpu.startup_environment("serve", zen3, {})


ARENA_COUNT = """
import ctypes, sys, threading
sys.path.insert(0, sys.argv[1])
from ff3d_tf import cpu
applied = cpu.limit_malloc_arenas({"MALLOC_ARENA_MAX": sys.argv[2]})
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
ready, hold = threading.Barrier(7), threading.Event()
def work():  # each thread's first malloc takes an arena of its own while the limit allows
    p = libc.malloc(4096)
    ready.wait()
    hold.wait()
    libc.free(p)
threads = [threading.Thread(target=work) for _ in range(6)]
[t.start() for t in threads]
ready.wait()
libc.malloc_stats()  # one "Arena N:" block per arena, on stderr
hold.set()
[t.join() for t in threads]
print(applied)
"""


def test_limit_malloc_arenas_caps_the_arenas_threads_get():
    """Six threads that each hold a block: with the default limit (8 per core) glibc gives each its own arena; limited
    to 2 (what the training start-up sets on an AVX2 CPU) they share two."""
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    counts = {}
    for value in ("", "2"):
        out = subprocess.run([sys.executable, "-c", ARENA_COUNT, root, value], capture_output=True, text=True,
                             timeout=60, env={k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"})
        assert out.returncode == 0, out.stderr
        counts[value] = (out.stdout.strip(), out.stderr.count("Arena "))
    assert counts[""] == ("None", 7)  # the main arena and one per thread
    assert counts["2"] == ("2", 2)
    for bad in ("0", "x", "-1"):
        assert cpu.limit_malloc_arenas({"MALLOC_ARENA_MAX": bad}) is None

