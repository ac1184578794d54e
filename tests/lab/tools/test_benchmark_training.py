"""lab/tools/benchmark_training.py: its flags reach `bench_steps.training_benchmark`, whose result it writes; a real run
writes every measurement."""
import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT, TINY_OVERRIDES

sys.path.append(os.path.join(ROOT, "lab", "tools"))  # appended: lab/tools/ module names must not shadow others
import benchmark_training  # noqa: E402


def _started(monkeypatch) -> list:
    """The jobs `main` starts up as; in this process TensorFlow is imported already, so the start-up is recorded
    instead of applied (tests/tools/test_startup.py tests the start-up itself)."""
    jobs = []
    monkeypatch.setattr(benchmark_training._common, "start", jobs.append)
    return jobs


def test_flags_reach_the_library_and_its_result_is_written(tmp_path, monkeypatch):
    from lab.training import bench_steps
    calls = []

    def training_benchmark(*args, **kwargs):
        calls.append(args)
        return {"input": [], "config": args[0]}
    monkeypatch.setattr(bench_steps, "training_benchmark", training_benchmark)
    jobs = _started(monkeypatch)
    out = tmp_path / "sub" / "training.json"
    benchmark_training.main(["--config", "", "--set", "train.global_batch_size=1", "--data_dir", "D", "--cores",
                             "1,2", "--input_batches", "3", "--train_steps", "4", "--out", str(out)])
    assert calls == [("", ["train.global_batch_size=1"], "D", 2, 4, 1.0, [1, 2], 3, 4)] and jobs == ["train"]
    assert json.loads(out.read_text()) == {"input": [], "config": ""}


def test_a_config_error_ends_the_tool_named(tmp_path, monkeypatch):
    _started(monkeypatch)
    with pytest.raises(SystemExit, match="config error: .*no_such_key"):
        benchmark_training.main(["--set", "train.no_such_key=1", "--out", str(tmp_path / "t.json")])


@pytest.mark.slow
def test_tool_writes_every_measurement(tmp_path):
    sets = [a for s in TINY_OVERRIDES + ("train.global_batch_size=1",) for a in ("--set", s)]
    out = tmp_path / "training.json"
    run = subprocess.run([sys.executable, "lab/tools/benchmark_training.py", "--config", "", *sets, "--segments", "1",
                          "--frames_per_segment", "3", "--lidar_scale", "0.12", "--cores", "1", "--input_batches",
                          "2", "--train_steps", "1", "--out", str(out)], cwd=ROOT, capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(out.read_text())
    (child,) = result["input"]
    assert child["cpus"] and len(child["cpus"]) == 1 and child["pairs_per_s"] > 0  # pinned to one CPU
    assert result["decode_count"]["decodes"] == result["decode_count"]["frames"] == 3
    assert result["train_step"]["steps_per_s"] > 0 and result["end_to_end"]["steps_per_s"] > 0
    assert 0.0 <= result["end_to_end"]["input_bound_fraction"] < 1.0
    assert result["input_headroom"] == child["pairs_per_s"] * result["train_step"]["mean_step_s"]  # batch 1
