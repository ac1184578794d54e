"""lab.training.bf16_study: oneDNN's verbose lines captured and read, the speed-ups and differences computed right,
a failing tool named (the real measurement: lab/tools/benchmark_bf16.py)."""
import ctypes
import os

import pytest

from lab import children
from lab.training import bf16_study

_DESCRIPTORS = {"f32": "src:f32::blocked:acdb::f0 wei:f32::blocked:cdba::f0 dst:f32::blocked:acdb::f0",
                "bf16": "src:bf16::blocked:acdb::f0 wei:bf16:ap:blocked:AcdB16a2b::f0 dst:bf16::blocked:acdb::f0"}


def _exec(primitive, implementation, direction, data_type, ms):
    return (f"onednn_verbose,v1,primitive,exec,cpu,{primitive},{implementation},{direction},{_DESCRIPTORS[data_type]},"
            f"attr-scratchpad:user,alg:convolution_direct,mb2_ic64oc64_ih512oh512kh3sh1dh0ph1,{ms}")


def test_stdout_lines_holds_what_c_writes_to_fd_1(capfd):
    libc = ctypes.CDLL(None)
    lines = []
    with bf16_study.stdout_lines(lines):
        libc.printf(b"from C, buffered by stdio\n")  # as oneDNN writes its verbose lines
        os.write(1, b"from fd 1\n")
    os.write(1, b"after\n")
    # C's stdio buffers when standard output is a file (as under Bazel) and is flushed as the block ends, so the two
    # lines' order depends on where the test runs; that both are captured, and nothing else, does not.
    assert sorted(lines) == ["from C, buffered by stdio", "from fd 1"]
    assert capfd.readouterr().out == "after\n"  # the real standard output is back, and got nothing of the block


def test_onednn_lines_are_read_by_data_type_and_primitive():
    lines = ["onednn_verbose,v1,info,oneDNN v3.2.1", "some other line",
             _exec("convolution", "brg_conv_fwd:avx512_core", "forward_training", "f32", 30.0),
             _exec("convolution", "brg_conv_fwd:avx512_core_bf16", "forward_training", "bf16", 8.0),
             _exec("reorder", "jit:uni", "undef", "bf16", 0.5),
             _exec("convolution", "brg_conv_fwd:avx512_core", "forward_training", "f32", 10.0),
             _exec("convolution", "brg_conv_fwd:avx512_core_bf16", "forward_training", "bf16", 12.0),
             _exec("convolution", "brg_conv_fwd:avx512_core", "forward_training", "f32", 20.0),
             _exec("convolution", "jit:avx512_core_bf16", "forward_training", "bf16", 4.0)]
    assert bf16_study.convolution_kernels(lines)["bfloat16"] == [("brg_conv_fwd:avx512_core_bf16", 8.0),
                                                                 ("brg_conv_fwd:avx512_core_bf16", 12.0),
                                                                 ("jit:avx512_core_bf16", 4.0)]
    timings = bf16_study.convolution_timings(lines, {"float32": [100.0, 300.0, 200.0], "bfloat16": [1.0, 2.0]})
    # exec medians: float32 of 30, 10, 20 -> 20; bfloat16 of 8, 12, 4 -> 8: 20 / 8 = 2.5. Wall: 200; (1 + 2) / 2.
    assert timings == {"float32": {"onednn_implementation": ["brg_conv_fwd:avx512_core"],
                                   "onednn_exec_median_ms": 20.0, "wall_median_ms": 200.0},
                       "bfloat16": {"onednn_implementation": ["brg_conv_fwd:avx512_core_bf16", "jit:avx512_core_bf16"],
                                    "onednn_exec_median_ms": 8.0, "wall_median_ms": 1.5},
                       "bfloat16_speedup": 2.5}
    by_primitive = bf16_study.onednn_ms_by_primitive(lines)
    # 30 + 8 + 0.5 + 10 + 12 + 20 + 4 = 84.5, summed per (primitive, direction, implementation), largest first
    assert by_primitive == {"total_ms": 84.5, "by_primitive": {
        "convolution forward_training brg_conv_fwd:avx512_core": 60.0,
        "convolution forward_training brg_conv_fwd:avx512_core_bf16": 20.0,
        "convolution forward_training jit:avx512_core_bf16": 4.0, "reorder undef jit:uni": 0.5}}
    # without oneDNN (its operations off) no lines, no speed-up
    assert bf16_study.convolution_timings(["no oneDNN here"], {"float32": [1.0]}) == {}


def _latency():
    def variant(median, minimum, **more):
        return {"median_ms": median, "min_ms": minimum, **more}
    f32, b16 = "auto/float32", "auto/bfloat16"
    diff = f"_flow_diff_norm_vs_{f32}_mps"
    return {"latency": {"32000": {f32: variant(100.0, 80.0, mean_flow_norm_mps=20.0),
                                  b16: variant(50.0, 20.0, **{"max" + diff: 0.5, "mean" + diff: 0.1})},
                        "1000000": {f32: variant(1000.0, 800.0, mean_flow_norm_mps=10.0),
                                    b16: variant(400.0, 400.0, **{"max" + diff: 2.0, "mean" + diff: 0.5})}},
            "train_step": {f32: variant(300.0, 250.0), b16: variant(200.0, 100.0)},
            "conv_floor": {"graph": variant(9.0, 8.0), "graph/bfloat16": variant(3.0, 4.0)},
            "load_average_at_start": ["1.0"], "load_average_at_end": ["2.0"]}


def test_summary_ratios_are_float32_over_bfloat16():
    dense = {f"{p}/{phase}": {"total_ms": ms} for (p, phase), ms in {
        ("float32", "inference"): 60.0, ("bfloat16", "inference"): 20.0, ("float32", "training"): 90.0,
        ("bfloat16", "training"): 60.0}.items()}
    demo = {"relative_difference_vs_float32": {"trained_bfloat16": {"all/moving/mean_l2_mps": 0.1}}}
    s = bf16_study.summary({"latency": _latency(), "convolution": {"bfloat16_speedup": 2.5,
                                                                    "dense_stages_onednn_ms": dense}, "demo": demo})
    assert s["inference_speedup_bfloat16_median"] == {"32000": 2.0, "1000000": 2.5}  # 100 / 50, 1000 / 400
    assert s["inference_speedup_bfloat16_min"] == {"32000": 4.0, "1000000": 2.0}  # 80 / 20, 800 / 400
    assert s["t_max_over_t_min_points_median"] == {"auto/float32": 10.0, "auto/bfloat16": 8.0}  # 1000/100, 400/50
    assert (s["train_step_speedup_bfloat16_median"], s["train_step_speedup_bfloat16_min"]) == (1.5, 2.5)
    assert (s["conv_floor_speedup_bfloat16_median"], s["conv_floor_speedup_bfloat16_min"]) == (3.0, 2.0)
    # mean flow difference over the mean float32 flow: 0.1 / 20, 0.5 / 10
    assert s["flow_difference_bfloat16_vs_float32_mps"]["32000"] == {"max": 0.5, "mean": 0.1, "mean_flow_norm": 20.0,
                                                                     "mean_over_mean_flow_norm": 0.005}
    assert s["flow_difference_bfloat16_vs_float32_mps"]["1000000"]["mean_over_mean_flow_norm"] == 0.05
    assert s["single_convolution_speedup_bfloat16"] == 2.5
    assert (s["dense_stages_onednn_speedup_bfloat16_inference"], s["dense_stages_onednn_speedup_bfloat16_training"]) \
        == (3.0, 1.5)  # 60 / 20, 90 / 60
    assert s["demo_relative_difference_vs_float32"] == demo["relative_difference_vs_float32"]
    assert bf16_study.summary({"convolution": {}}) == {}  # sections not run: no ratios


def test_relative_differences_are_against_the_reference():
    reference = {"moving": 2.0, "stationary": 0.5}
    got = bf16_study.relative_differences({"a": {"moving": 2.5, "stationary": 0.4, "other": 9.0}}, reference)
    assert got == {"a": {"moving": pytest.approx(0.25), "stationary": pytest.approx(-0.2)}}  # 0.5 / 2, -0.1 / 0.5


def test_a_failing_tool_is_named_with_its_output():
    with pytest.raises(children.ChildError, match=r"(?s)benchmark_onednn.py failed \(exit 2\):.*unrecognized"):
        bf16_study.run_tool("lab/tools/benchmark_onednn.py", ["--no_such_flag"])
