"""ff3d_tf.cpu: /proc/cpuinfo parsing, the ISA caps read from the environment, the flags left usable under them."""
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
    zen3 = cpu.EMULATIONS["zen3_tf_default"]
    assert cpu.isa_limits({**zen3, "XLA_FLAGS": "--xla_dump_to=/x --xla_cpu_max_isa=AVX2"}) == {
        "onednn_max_isa": "AVX2", "xla_cpu_max_isa": "AVX2", "tf_enable_onednn_opts": "0"}
    assert cpu.usable_flags(info, zen3) == {"fpu", "sse2", "avx2", "fma"}
    assert "TF_ENABLE_ONEDNN_OPTS" not in cpu.EMULATIONS["zen3"]  # the project's own setting applies (prefer_onednn)
    assert cpu.usable_flags(info, {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_VNNI"}) == info.flags - {"avx512_bf16"}
    assert cpu.usable_flags(info, {}) == info.flags


def test_description_names_the_cpu_its_flags_and_the_caps():
    info = cpu.parse_cpuinfo(ZEN4)
    described = cpu.describe(info, cpu.EMULATIONS["zen3_tf_default"])
    assert described["flags"] == ["avx2", "fma", "avx512f", "avx512_vnni", "avx512_bf16"]
    assert described["usable_flags"] == ["avx2", "fma"]
    line = cpu.one_line(described)
    assert line.startswith("AMD EPYC 9B14 (AuthenticAMD, family/model 25/17, 2 cores): avx2 fma avx512f avx512_vnni avx512_bf16; "
                           "usable under the limits: avx2 fma; limits: onednn_max_isa=AVX2")
    assert cpu.one_line(cpu.describe(info, {})).endswith("avx512_bf16; limits: none")
    assert cpu.describe(None, {})["cpu_count"] >= 1  # this machine (or the fallback where it has no cpuinfo)


def test_onednn_is_preferred_on_x86_unless_the_environment_says():
    env = {}
    assert cpu.prefer_onednn(env, "x86_64") and env == {"TF_ENABLE_ONEDNN_OPTS": "1"}
    env = {"TF_ENABLE_ONEDNN_OPTS": "0"}
    assert not cpu.prefer_onednn(env, "x86_64") and env == {"TF_ENABLE_ONEDNN_OPTS": "0"}  # the user's word stands
    env = {}
    assert not cpu.prefer_onednn(env, "aarch64") and env == {}


def test_importing_the_package_turns_onednn_on_before_tensorflow_starts():
    """In a child process on this (x86) machine without the variable: TensorFlow reports oneDNN on whatever its own
    default for this CPU; with TF_ENABLE_ONEDNN_OPTS=0 set by the user, off."""
    import os
    import subprocess
    import sys
    from conftest import ROOT
    code = "import ff3d_tf; from ff3d_tf import internals; print(internals.onednn_enabled())"
    seen = {}
    for value in (None, "0"):
        env = {k: v for k, v in os.environ.items() if k != "TF_ENABLE_ONEDNN_OPTS"}
        if value is not None:
            env["TF_ENABLE_ONEDNN_OPTS"] = value
        env["TF_CPP_MIN_LOG_LEVEL"] = "3"
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                             check=True)
        seen[value] = out.stdout.strip().splitlines()[-1]
    assert seen == {None: "True", "0": "False"}
