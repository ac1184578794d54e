"""tools/benchmark_training.py: decodes counted once per frame, input and step rates measured, JSON written."""
import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT, TINY_OVERRIDES

sys.path.append(os.path.join(ROOT, "tools"))  # appended: tools/ module names must not shadow others
import benchmark_training  # noqa: E402


def test_each_frame_decoded_once_although_in_two_pairs(tiny_segment, tiny_config):
    # 4 frames 0.1 s apart -> pairs (0,1), (1,2), (2,3): frames 1 and 2 are in two pairs each, decoded once.
    counted = benchmark_training.count_decodes([tiny_segment], tiny_config)
    assert counted == {"frames": 4, "pairs": 3, "decodes": 4, "decodes_if_each_pair_decoded_both_frames": 6,
                       "decode_once_per_frame": True}


def test_input_rate_of_the_training_pipeline(tiny_segment, tiny_config):
    r = benchmark_training.input_pairs_per_s([tiny_segment], tiny_config, cores=1, batches=3)
    batch = tiny_config.train.global_batch_size
    assert r["cores"] == 1 and r["pairs_timed"] == 3 * batch and r["pairs_per_s"] > 0
    assert r["mean_points_t0"] > 100  # tiny range images still give thousands of points per frame


@pytest.mark.slow
def test_tool_writes_every_measurement(tmp_path):
    sets = [a for s in TINY_OVERRIDES + ("train.global_batch_size=1",) for a in ("--set", s)]
    out = tmp_path / "training.json"
    run = subprocess.run([sys.executable, "tools/benchmark_training.py", "--config", "", *sets, "--segments", "1",
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
