"""`model.compile=auto` per device, per job and per kind of CPU (`compile.AUTO_CPU`, `compile.cpu_class`), and
bfloat16 kept away from oneDNN where it has no bfloat16 convolutions."""
import pytest

from ff3d_tf import cpu
from ff3d_tf.model import compile as compile_lib

ZEN4 = cpu.parse_cpuinfo("processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: avx2 fma avx512f avx512_vnni "
                         "avx512_bf16\n\n")
ZEN3 = cpu.parse_cpuinfo("processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: avx2 fma\n\n")


def test_cpu_class_from_onednn_and_the_usable_isa():
    assert compile_lib.cpu_class(True, ZEN4, {}) == "onednn_avx512"
    assert compile_lib.cpu_class(True, ZEN4, cpu.EMULATIONS["zen3_onednn"]) == "onednn_avx2"  # capped to AVX2
    assert compile_lib.cpu_class(True, ZEN3, {}) == "onednn_avx2"
    assert compile_lib.cpu_class(False, ZEN3, {}) == compile_lib.cpu_class(False, ZEN4, {}) == "eigen"
    assert compile_lib.cpu_class() in compile_lib.CPU_CLASSES  # this process


def test_auto_per_device_job_and_cpu():
    for job in compile_lib.JOBS:
        assert compile_lib.resolve_compile_mode("auto", "GPU", job=job) == "xla"
        assert compile_lib.resolve_compile_mode("auto", "TPU", job=job) == "xla"
        for kind in compile_lib.CPU_CLASSES:
            mode = compile_lib.resolve_compile_mode("auto", "CPU", job=job, cpu_kind=kind)
            assert mode == compile_lib.AUTO_CPU[(kind, job)] and mode in compile_lib.RESOLVED_MODES
            assert compile_lib.resolve_compile_mode("none", "CPU", job=job, cpu_kind=kind) == "none"
    # Where TensorFlow's graph has oneDNN's AVX-512 kernels, hybrid for both jobs (benchmarks/latency_cpu.json); with
    # Eigen's kernels, the leanest mode per job (benchmarks/cpu_step_avx2.json); oneDNN's AVX2 kernels: xla.
    assert {compile_lib.AUTO_CPU[("onednn_avx512", j)] for j in compile_lib.JOBS} == {"hybrid"}
    assert {compile_lib.AUTO_CPU[("onednn_avx2", j)] for j in compile_lib.JOBS} == {"xla"}
    assert (compile_lib.AUTO_CPU[("eigen", "train")], compile_lib.AUTO_CPU[("eigen", "inference")]) == ("xla", "hybrid")
    assert set(compile_lib.AUTO_CPU) == {(k, j) for k in compile_lib.CPU_CLASSES for j in compile_lib.JOBS}
    with pytest.raises(ValueError, match="train, inference"):
        compile_lib.resolve_compile_mode("auto", "CPU", job="serve")
    with pytest.raises(ValueError, match="cpu_kind"):
        compile_lib.resolve_compile_mode("auto", "CPU", cpu_kind="zen3")
    assert compile_lib.resolve_compile_mode("auto", "CPU") in compile_lib.RESOLVED_MODES  # this process


def test_bfloat16_never_meets_onednn_without_bfloat16_convolutions():
    amd_avx2 = ("AuthenticAMD", ())
    with pytest.raises(ValueError, match="TF_ENABLE_ONEDNN_OPTS=0"):
        compile_lib.resolve_precision(True, "hybrid", "CPU", amd_avx2, onednn_enabled=True)
    with pytest.raises(ValueError, match="TF_ENABLE_ONEDNN_OPTS=0"):
        compile_lib.resolve_precision(True, "none", "CPU", amd_avx2, onednn_enabled=True)
    # oneDNN off (the start-up's choice there), XLA's convolutions, another device, or bfloat16 kernels: as set.
    assert compile_lib.resolve_precision(True, "hybrid", "CPU", amd_avx2, onednn_enabled=False) == ("bfloat16",
                                                                                                     "as set")
    assert compile_lib.resolve_precision(True, "xla", "CPU", amd_avx2, onednn_enabled=True)[0] == "bfloat16"
    assert compile_lib.resolve_precision(True, "hybrid", "GPU", amd_avx2, onednn_enabled=True)[0] == "bfloat16"
    assert compile_lib.resolve_precision(True, "hybrid", "CPU", ("AuthenticAMD", ("avx512_bf16",)),
                                         onednn_enabled=True)[0] == "bfloat16"
    # auto never asks for bfloat16 there.
    assert compile_lib.resolve_precision("auto", "hybrid", "CPU", amd_avx2, onednn_enabled=True)[0] == "float32"
