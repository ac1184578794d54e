"""lab.training.cpu_studies: variant environments, children run in exactly them, medians and speed-ups over
rounds, the memory summary, a failed child recorded (the real measurements: lab/tools/benchmark_onednn.py,
tests/lab/tools/test_profile_memory.py)."""
import os

import pytest

from lab import children
from lab.training import cpu_studies


def test_a_variant_environment_drops_every_knob_of_the_study_and_adds_its_own():
    base = {"PATH": "/bin", "A": "caller", "B": "caller"}
    variants = [{"A": "1"}, {"A": "2", "B": "x"}]
    # B is set by some variant, so the caller's B is gone even where this variant does not set it
    assert cpu_studies.variant_environment({"A": "1"}, variants, base) == {"PATH": "/bin", "A": "1"}
    caller = {"PATH": "/bin", "ONEDNN_MAX_CPU_ISA": "AVX512_CORE", "XLA_FLAGS": "--xla_cpu_max_isa=AVX512",
              "TF_ENABLE_ONEDNN_OPTS": "1"}
    # `none`: the CPU's own ISA, whatever caps the caller set
    assert cpu_studies.onednn_environment("none", "0", caller) == {"PATH": "/bin", "TF_ENABLE_ONEDNN_OPTS": "0"}
    assert cpu_studies.onednn_environment("avx2", "1", caller) == {
        "PATH": "/bin", "ONEDNN_MAX_CPU_ISA": "AVX2", "XLA_FLAGS": "--xla_cpu_max_isa=AVX2",
        "TF_ENABLE_ONEDNN_OPTS": "1"}


def test_a_child_runs_in_exactly_its_environment(monkeypatch):
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX2")
    env = cpu_studies.onednn_environment("none", "1", os.environ)
    # ff3d_tf.cpu.isa_limits reads the child's own environment
    got = children.run_child("ff3d_tf.cpu:isa_limits", base=env)
    assert got == {"onednn_max_isa": None, "xla_cpu_max_isa": None, "tf_enable_onednn_opts": "1"}


def test_onednn_summary_is_the_median_over_rounds_and_off_over_on():
    def rounds(*train_ms):
        return [{"onednn_enabled": True, "train_step_ms": t, "forward_ms": 10.0 * i} for i, t in enumerate(train_ms)]
    runs = {"avx2_onednn_0": rounds(300.0, 100.0, 200.0), "avx2_onednn_1": rounds(50.0, 40.0, 60.0)}
    summary = cpu_studies.onednn_summary(runs, ["avx2"])
    # medians: 200 (of 300, 100, 200) and 50 (of 50, 40, 60); forward 10 (of 0, 10, 20) in both
    assert summary["avx2_onednn_0"] == {"train_step_ms": 200.0, "forward_ms": 10.0}
    assert summary["avx2_onednn_1"] == {"train_step_ms": 50.0, "forward_ms": 10.0}
    assert summary["avx2_onednn_speedup"] == {"train_step_ms": 4.0, "forward_ms": 1.0}  # 200 / 50, 10 / 10
    # of an even count, the upper middle value (a measured one)
    assert cpu_studies.medians([{"ms": 1.0}, {"ms": 4.0}, {"ms": 2.0}, {"ms": 3.0}], ["ms"]) == {"ms": 3.0}
    with pytest.raises(ValueError, match="unknown caps"):
        cpu_studies.onednn_study("", 1000, ["avx3"], 1, 1)


def _child_result(rss_between_gb):
    snap = {"rss_gb": 1.5, "mallinfo2": {"uordblks": 0.2, "fordblks": 0.1, "hblkhd": 0.3, "hblks": 4, "arena": 9},
            "smaps_gb": {"file_tensorflow": 0.25, "file_other": 0.5}, "smaps_rollup_gb": {"Anonymous": 0.75}}
    return {"built": {"rss_gb": 1.0}, "after_gc_and_malloc_trim": {"rss_gb": 0.9},
            "between_calls": {**snap, "tf_allocator": {"current_gb": 0.0, "peak_gb": 0.1}},
            "timed": {"rss_between_gb": rss_between_gb, "peak_rss_gb": 2.0, "median_ms": 30.0, "median_cpu_ms": 50.0,
                      "median_sys_ms": 5.0, "median_minor_faults": 100}}


def test_memory_round_summary_takes_the_readings_and_leaves_out_a_failed_child():
    summary = cpu_studies.memory_round_summary({"train": _child_result(1.25), "infer": {"error": "boom"}})
    assert list(summary) == ["train"]
    assert summary["train"] == {
        "rss_between_gb": 1.25, "peak_rss_gb": 2.0, "rss_built_gb": 1.0, "rss_after_trim_gb": 0.9,
        "median_ms": 30.0, "median_cpu_ms": 50.0, "median_sys_ms": 5.0, "median_minor_faults": 100,
        "mallinfo2_gb": {"uordblks": 0.2, "fordblks": 0.1, "hblkhd": 0.3, "hblks": 4},
        "smaps_anon_gb": 0.75, "smaps_file_gb": 0.75,  # 0.25 TensorFlow's files + 0.5 others
        "tf_allocator": {"current_gb": 0.0, "peak_gb": 0.1}}


def test_a_failed_child_is_recorded_not_raised():
    lines = []
    result = cpu_studies.memory_study("", ["model.no_such_key=1"], ["tf_bfc_pool"], 1000, 1, 1, ["infer"],
                                      note="a note", log_fn=lines.append)
    variant = result["variants"]["tf_bfc_pool"]
    assert "tf_bfc_pool infer: its process ended with exit 1" in variant["infer"]["error"]
    assert "no_such_key" in variant["infer"]["error"]
    assert variant["rounds"] == [{}] and variant["summary"] == {}
    assert "infer failed" in lines[0] and result["note"].endswith("a note")
    assert result["variants"]["tf_bfc_pool"]["env"] == cpu_studies.MEMORY_VARIANTS["tf_bfc_pool"]["env"]


def test_memory_study_checks_its_names_before_any_child():
    with pytest.raises(ValueError, match="unknown variants"):
        cpu_studies.memory_study("", [], ["no_such_variant"], 1000, 1, 1)
    with pytest.raises(ValueError, match="not all in the variants"):
        cpu_studies.memory_study("", [], ["tf_bfc_pool"], 1000, 1, 1, repeat=2, repeat_variants=["bfc_trim"])
    with pytest.raises(ValueError, match="kinds"):
        cpu_studies.memory_study("", [], ["tf_bfc_pool"], 1000, 1, 1, kinds=["both"])
