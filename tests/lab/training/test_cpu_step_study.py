"""lab.training.cpu_step_study: the variants' environments and modes, the step's parts, the summary and the Zen 3
projection (no child processes: lab/tools/benchmark_cpu_step.py runs them; one tiny training child in this process)."""
import numpy as np
import pytest

from ff3d_tf import cpu
from ff3d_tf.model import compile as compile_lib
from lab.training import cpu_step_study as study


def test_variant_environment_before_is_the_emulation_after_the_startup_rule():
    base = {"PATH": "/bin", "TF_ENABLE_ONEDNN_OPTS": "1", "TF_CPU_ALLOCATOR_USE_BFC": "false", "XLA_FLAGS": "x"}
    before = study.variant_environment("before", "train", "zen3", base)
    assert before == {"PATH": "/bin", **cpu.EMULATIONS["zen3"]}  # the caller's knobs never leak in
    after = study.variant_environment("after", "forward", "zen3", base)
    caps = {k: v for k, v in cpu.EMULATIONS["zen3"].items() if k != "TF_ENABLE_ONEDNN_OPTS"}
    assert after == {"PATH": "/bin", **caps, **cpu.startup_environment("inference", environ=caps)}
    info = cpu.read_cpuinfo()
    if info is not None and "avx2" in info.flags:  # an x86 CPU: capped to AVX2, it gets the AVX2 start-up
        assert after["TF_ENABLE_ONEDNN_OPTS"] == cpu.AVX2_STARTUP["inference"]["TF_ENABLE_ONEDNN_OPTS"]


def test_after_remat_is_after_with_the_encoder_recomputed(monkeypatch):
    assert study.variant_environment("after_remat", "train", "zen3", {}) == \
        study.variant_environment("after", "train", "zen3", {})
    calls = []
    monkeypatch.setattr(study.children, "run_child", lambda fn, kwargs, **kw: calls.append(kwargs) or {
        "mode": kwargs["mode"], "onednn_enabled": False, "step_median_ms": 1.0, "peak_rss_gb": 1.0})
    study.study("", ["train.seed=1"], 100, [100], ["xla"], ["train"], ["after", "after_remat"], "zen3", 1, 0, 1,
                False, 1, 1, log_fn=lambda line: None)
    assert [c["overrides"] for c in calls] == [["train.seed=1"], ["train.seed=1", study.REMAT_OVERRIDE]]


def test_before_and_after_plain_convolutions_run_the_plain_forms(monkeypatch):
    """"before" is the model as the issue measured it: its convolutions in their plain forms, as in the setting that
    isolates them ("after_plain_convolutions", otherwise "after"); "after" runs the model's own forms."""
    assert study.variant_environment("after_plain_convolutions", "train", "zen3", {}) == \
        study.variant_environment("after", "train", "zen3", {})
    calls = []
    monkeypatch.setattr(study.children, "run_child", lambda fn, kwargs, **kw: calls.append(kwargs) or {
        "mode": kwargs["mode"], "onednn_enabled": False, "step_median_ms": 1.0, "peak_rss_gb": 1.0})
    study.study("", [], 100, [100], ["xla"], ["train", "forward"], ["before", "after", "after_plain_convolutions"],
                "zen3", 1, 0, 1, False, 1, 1, log_fn=lambda line: None)
    assert [c["convolution_forms"] for c in calls] == ["plain", "fast", "plain"] * 2


def test_the_child_limits_malloc_arenas_as_a_tool_does(monkeypatch):
    """MALLOC_ARENA_MAX of the start-up reaches a child as an argument that it applies after its start (as
    tools/_common.py), not in the environment glibc reads at exec; "after_default_arenas" leaves it out."""
    caps = {k: v for k, v in cpu.EMULATIONS["zen3"].items() if k != "TF_ENABLE_ONEDNN_OPTS"}
    expected = cpu.startup_environment("train", environ=caps).get("MALLOC_ARENA_MAX")
    assert study.variant_environment("after", "train", "zen3", {}).get("MALLOC_ARENA_MAX") == expected
    assert "MALLOC_ARENA_MAX" not in study.variant_environment("after_default_arenas", "train", "zen3", {})
    calls = []
    monkeypatch.setattr(study.children, "run_child", lambda fn, kwargs, env, **kw: calls.append((kwargs, env)) or {
        "mode": kwargs["mode"], "onednn_enabled": False, "step_median_ms": 1.0, "peak_rss_gb": 1.0})
    study.study("", [], 100, [100], ["xla"], ["train"], ["after", "after_default_arenas"], "zen3", 1, 0, 1, False, 1,
                1, log_fn=lambda line: None)
    assert [kwargs["malloc_arena_max"] for kwargs, _ in calls] == [expected, None]
    assert not any("MALLOC_ARENA_MAX" in env for _, env in calls)


def test_huge_pages_reach_the_training_child_at_exec(monkeypatch):
    """"after_huge_pages" gives the training child GLIBC_TUNABLES in the environment it starts with (glibc reads it
    only then); "after" has none, and the forward is not measured with it."""
    calls = []
    monkeypatch.setattr(study.children, "run_child", lambda fn, kwargs, env, **kw: calls.append((fn, env)) or {
        "mode": kwargs["mode"], "onednn_enabled": False, "step_median_ms": 1.0, "peak_rss_gb": 1.0,
        "median_ms": {"100": 1.0}})
    study.study("", [], 100, [100], ["xla"], ["train", "forward"], ["after", "after_huge_pages"], "zen3", 1, 0, 1,
                False, 1, 1, log_fn=lambda line: None)
    tunables = study.HUGE_PAGES["GLIBC_TUNABLES"]
    assert [(fn.split(":")[1], env.get("GLIBC_TUNABLES")) for fn, env in calls] == [
        ("train_child", None), ("train_child", tunables), ("forward_child", None)]


def test_resolved_mode_per_setting_and_job():
    assert study.resolved_mode("before", "auto", "train", {}) == "hybrid"  # the rule before the per-job choice
    assert study.resolved_mode("after", "xla", "forward", {}) == "xla"
    eigen = {**cpu.EMULATIONS["zen3"]}
    for job, startup_job in study.STARTUP_JOB.items():
        assert study.resolved_mode("after", "auto", job, eigen) == compile_lib.AUTO_CPU[("eigen", startup_job)]


def test_stage_summary_splits_backward_and_leaves_the_rest():
    stages = {"point_forward": {"median_ms": 10.0}, "point_forward_backward": {"median_ms": 25.0},
              "conv_forward": {"median_ms": 100.0}, "conv_forward_backward": {"median_ms": 300.0},
              "optimizer": {"median_ms": 5.0}, "loss": {"median_ms": 1.0}, "batchnorm_ms": 20.0}
    out = study.stage_summary(stages, step_ms=350.0)
    assert out == {"point_forward_ms": 10.0, "point_backward_ms": 15.0, "conv_forward_ms": 100.0,
                   "conv_backward_ms": 200.0, "batchnorm_ms": 20.0, "optimizer_ms": 5.0, "loss_ms": 1.0,
                   "rest_ms": 19.0}


def _reading(ms, peak, mode="hybrid", medians=None):
    if medians is not None:
        return {"mode": mode, "onednn_enabled": False, "median_ms": medians, "peak_rss_gb": peak}
    return {"mode": mode, "onednn_enabled": False, "step_median_ms": ms, "peak_rss_gb": peak}


def test_summary_follows_aliases_and_projects_onto_zen3():
    variants = {
        "train/auto": {"before": _reading(2000.0, 4.0), "after": _reading(1000.0, 3.0, "xla"),
                       "after_remat": _reading(1100.0, 2.0, "xla")},
        "train/xla": {"before": _reading(1500.0, 3.5, "xla"), "after": {"same_as": "train/auto", "mode": "xla"}},
        "forward/auto": {"before": _reading(0, 2.0, medians={"32000": 300.0, "1000000": 400.0}),
                         "after": _reading(0, 2.0, medians={"32000": 200.0, "1000000": 220.0})},
        "forward/none": {"before": {"error": "boom"}, "after": _reading(0, 1.0, "none", {"32000": 1.0})}}
    summary = study.summarize(variants)
    assert summary["train/auto"]["before_over_after"] == {"step": 2.0, "peak": pytest.approx(4 / 3)}
    assert summary["train/xla"]["after"]["step_median_ms"] == 1000.0  # the alias's figures
    assert summary["forward/auto"]["after"]["t1m_over_t32k"] == pytest.approx(1.1)
    assert summary["forward/none"]["before"] == {"error": True} and "before_over_after" not in summary["forward/none"]
    projected = study.projection(summary)
    figures = study.peer_figures()
    before, peer = figures["ff3d_tf_before"], figures["peer"]
    assert projected["train_step_32000_ms"] == pytest.approx(before["train_step_32000_ms"] / 2)
    assert projected["train_step_speedup_over_peer"] == pytest.approx(
        peer["train_step_32000_ms"] / (before["train_step_32000_ms"] / 2))
    assert projected["train_step_32000_peak_gb"] == pytest.approx(before["train_step_32000_peak_gb"] * 0.75)
    assert projected["forward_1000000_ms"] == pytest.approx(before["forward_1000000_ms"] * 220 / 400)
    # the encoder recomputed: its own ratios to "before", beside the after's
    assert projected["after_remat"]["train_step_32000_ms"] == pytest.approx(before["train_step_32000_ms"] * 0.55)
    assert projected["after_remat"]["train_step_32000_peak_gb"] == pytest.approx(
        before["train_step_32000_peak_gb"] * 0.5)
    assert study.projection({"train/auto": {"before": {"error": True}}}) == {}


def test_study_checks_its_words():
    with pytest.raises(ValueError, match="modes"):
        study.study("", [], 100, [100], ["fast"], ["train"], ["after"], "zen3", 1, 0, 1, False, 1, 1)
    with pytest.raises(ValueError, match="cap"):
        study.study("", [], 100, [100], ["auto"], ["train"], ["after"], "zen5", 1, 0, 1, False, 1, 1)


@pytest.mark.parametrize("mode", ["none", pytest.param("hybrid", marks=pytest.mark.slow)])
def test_train_child_in_this_process(mode):
    from ff3d_tf.config import TINY_OVERRIDES
    out = study.train_child("", list(TINY_OVERRIDES), mode, points=300, steps=1, warmup=0,
                            point_programs="per_cloud", stages=True, stage_runs=1)
    assert out["mode"] == mode and len(out["step_ms"]) == 1 and out["peak_rss_gb"] > 0
    assert set(out["stages"]) == {"point_forward", "point_forward_backward", "conv_forward",
                                  "conv_forward_backward", "optimizer", "loss", "batchnorm_ms"}
    assert np.isfinite(out["stages"]["batchnorm_ms"]) and out["cpu"]["cpu_count"] >= 1


def test_resummarize_recomputes_from_the_variants():
    figures = study.peer_figures()
    result = {"variants": {"train/auto": {"before": {**_reading(2000.0, 4.0), "step_cpu_ms": [900.0, 1000.0, 1100.0]},
                                          "after": {**_reading(1000.0, 3.0, "xla"), "step_cpu_ms": [500.0]}}},
              "summary": {}, "peer": {k: v for k, v in figures.items() if k != "targets"},
              "targets": figures["targets"], "projection_zen3": {}}
    out = study.resummarize(result)
    assert out["summary"]["train/auto"]["before_over_after"]["step_cpu"] == 2.0
    assert out["projection_zen3"]["train_step_32000_ms"] == pytest.approx(
        figures["ff3d_tf_before"]["train_step_32000_ms"] / 2)
    assert result["summary"] == {}  # the input is left as it was


def test_autos_eigen_entries_follow_the_study_they_name():
    """`compile_lib.AUTO_CPU`'s rule on an AVX2-only CPU with Eigen's kernels (its module docstring), checked against
    the study it names, "after" setting: to train, the mode with the lowest peak memory; to serve, the mode with the
    fastest forward at every point count measured."""
    import json
    import os

    with open(os.path.join(os.path.dirname(study.PEER_FILE), "cpu_step_avx2.json")) as f:
        summary = json.load(f)["summary"]
    peaks = {m: summary[f"train/{m}"]["after"]["peak_rss_gb"] for m in compile_lib.RESOLVED_MODES}
    assert compile_lib.AUTO_CPU[("eigen", "train")] == min(peaks, key=peaks.get), peaks
    forward_ms = {m: summary[f"forward/{m}"]["after"]["median_ms"] for m in compile_lib.RESOLVED_MODES}
    for points in forward_ms["hybrid"]:
        at_points = {m: ms[points] for m, ms in forward_ms.items()}
        assert compile_lib.AUTO_CPU[("eigen", "inference")] == min(at_points, key=at_points.get), (points, at_points)
