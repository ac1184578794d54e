"""lab.training.bench_steps.training_benchmark: the input's rate read pinned to the cores asked, decodes counted,
the step timed in memory and end to end, the headroom computed from them."""
import os

import pytest

from conftest import TINY_OVERRIDES

from lab.training import bench_steps

FIRST_CPU = sorted(os.sched_getaffinity(0))[:1]
BATCH = 2  # TINY_OVERRIDES' train.global_batch_size


@pytest.mark.slow  # decodes and steps a whole segment: ~45 s
def test_input_decodes_and_steps_of_one_segment(tiny_segment):
    lines = []
    result = bench_steps.training_benchmark(None, TINY_OVERRIDES, data_dir=os.path.dirname(tiny_segment), cores=[1],
                                            input_batches=2, train_steps=1, progress=lines.append)
    (child,) = result["input"]
    assert child["cpus"] == FIRST_CPU and child["cores"] == 1  # read in a process pinned to one CPU
    assert child["pairs_timed"] == 2 * BATCH and child["pairs_per_s"] > 0 and child["mean_points_t0"] > 100
    assert result["decode_count"]["decodes"] == result["decode_count"]["frames"] == 4  # 3 pairs of 4 frames
    assert result["batch_size"] == BATCH and result["replicas"] >= 1 and result["train_step"]["steps"] == 1
    assert result["train_step"]["steps_per_s"] > 0 and result["end_to_end"]["steps_per_s"] > 0
    assert 0.0 <= result["end_to_end"]["input_bound_fraction"] < 1.0
    headroom = child["pairs_per_s"] * result["train_step"]["mean_step_s"] / BATCH
    assert result["input_headroom"] == pytest.approx(headroom)
    assert len(lines) == 3 and lines[0].startswith("input on 1 core(s): ")


def test_core_counts_checked_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="core counts \\[0\\] asked"):
        bench_steps.training_benchmark(None, TINY_OVERRIDES, data_dir=str(tmp_path), cores=[0])
