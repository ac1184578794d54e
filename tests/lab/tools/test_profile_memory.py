"""lab/tools/profile_memory.py (`lab.training.cpu_studies.memory_study`): variants isolated in their own environment,
medians over rounds, the JSON (the /proc and glibc readings it takes: tests/lab/test_bench.py)."""
import json
import os
import subprocess
import sys

from conftest import ROOT, TINY_OVERRIDES

from ff3d_tf import cpu
from lab.training import cpu_studies


def test_each_variant_gets_its_own_settings_and_none_of_the_others():
    base = {"PATH": "/bin", "MALLOC_ARENA_MAX": "8", "TF_ENABLE_ONEDNN_OPTS": "0",
            "TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "1"}
    env = cpu_studies.memory_environment("tf_bfc_pool", base)
    # the caller's knobs do not leak in
    assert env == {"PATH": "/bin", "TF_ENABLE_ONEDNN_OPTS": "1", "TF_ONEDNN_USE_SYSTEM_ALLOCATOR": "0"}
    env = cpu_studies.memory_environment("bfc_arena_max_2", base)
    assert env["MALLOC_ARENA_MAX"] == "2" and env["TF_ENABLE_ONEDNN_OPTS"] == "1"
    assert cpu_studies.memory_environment("onednn_off", base)["TF_ENABLE_ONEDNN_OPTS"] == "0"
    # every variant says whether oneDNN is on and which TensorFlow CPU allocator it runs with, whatever the caller's
    # environment says and whatever TensorFlow's default for this CPU is (oneDNN off by default on AVX2-only CPUs)
    assert all({"TF_ENABLE_ONEDNN_OPTS", "TF_ONEDNN_USE_SYSTEM_ALLOCATOR"} <= set(v["env"])
               for v in cpu_studies.MEMORY_VARIANTS.values())


def test_times_are_medians_over_rounds_memory_from_the_first():
    def summary(ms, rss):
        return {"train": {"rss_between_gb": rss, "median_ms": ms, "median_cpu_ms": 2 * ms, "median_sys_ms": 1.0,
                          "median_minor_faults": 10}}
    combined = cpu_studies.combine_rounds([summary(300.0, 1.0), summary(100.0, 9.0), summary(200.0, 9.0)])
    assert combined == {"train": {"rss_between_gb": 1.0, "median_ms": 200.0, "median_cpu_ms": 400.0,
                                  "median_sys_ms": 1.0, "median_minor_faults": 10, "rounds": 3}}


def test_tool_writes_every_variant_and_the_pool_shows(tmp_path):
    # Run under the caller's TF_ENABLE_ONEDNN_OPTS=0 (as on an AVX2-only CPU, where it is TensorFlow's default).
    # Inference of the tiny model at 200K points: point tensors of ~13 MB each. TensorFlow's BFC pool keeps them
    # mapped between calls (and counts them); with the system allocator they are unmapped and nothing is counted.
    out = tmp_path / "memory.json"
    sets = [a for s in TINY_OVERRIDES for a in ("--set", s)]
    run = subprocess.run([sys.executable, "lab/tools/profile_memory.py", "--config", "", *sets, "--variants",
                          "tf_bfc_pool,system_allocator", "--kinds", "infer", "--points", "200000", "--calls", "2",
                          "--repeat", "2", "--repeat_variants", "system_allocator", "--note", "test run", "--out",
                          str(out)], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "TF_ENABLE_ONEDNN_OPTS": "0"},
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(out.read_text())
    assert "Load average" in result["note"] and result["note"].endswith("test run")
    assert set(result["variants"]) == {"tf_bfc_pool", "system_allocator"}
    assert [len(result["variants"][k]["rounds"]) for k in ("tf_bfc_pool", "system_allocator")] == [1, 2]
    bfc, system = (result["variants"][k]["summary"]["infer"] for k in ("tf_bfc_pool", "system_allocator"))
    for s in (bfc, system):
        assert s["rss_between_gb"] > 0 and s["peak_rss_gb"] >= s["rss_between_gb"] - 0.01 and s["median_ms"] > 0
        assert s["smaps_anon_gb"] > 0 and s["smaps_file_gb"] > 0 and s["mallinfo2_gb"]["uordblks"] > 0
        assert len(result["variants"]["tf_bfc_pool"]["infer"]["timed"]["calls"]) == 2
    # oneDNN on in both children (set by the variants), whatever this CPU's default
    assert [result["variants"][k]["infer"]["onednn_enabled"] for k in ("tf_bfc_pool", "system_allocator")] == [True] * 2
    assert result["cpu"]["model_name"] == cpu.describe()["model_name"]
    assert bfc["tf_allocator"]["peak_gb"] > 0.01  # the pool counts its tensors
    if "avx512f" in cpu.describe()["usable_flags"]:
        # Where the pool was measured (AVX-512 CPUs): the system allocator counts nothing and maps less. On a real AMD
        # Zen 3 (AVX2) both variants count and map the same, with the code before this session's change too: oneDNN's
        # system-allocator switch does not reach its allocations there (not investigated further).
        assert system["tf_allocator"]["peak_gb"] == 0.0
        assert bfc["mallinfo2_gb"]["hblkhd"] > system["mallinfo2_gb"]["hblkhd"] + 0.02  # the pool's mapped regions
