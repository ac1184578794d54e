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

