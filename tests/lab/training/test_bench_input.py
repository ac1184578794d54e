"""lab.training.bench_input: decodes counted once per frame, every reading present and positive, each read in a
process pinned to the cores asked, failures named."""
import os

import pytest

from conftest import TINY_OVERRIDES, TINY_SCALE

from lab import children
from lab.training import bench_input

FIRST_CPU = sorted(os.sched_getaffinity(0))[:1]
BATCH = 2  # TINY_OVERRIDES' train.global_batch_size


def test_each_frame_decoded_once_although_in_two_pairs(tiny_segment, tiny_config):
    # 4 frames 0.1 s apart -> pairs (0,1), (1,2), (2,3): frames 1 and 2 are in two pairs each, decoded once.
    counted = bench_input.count_decodes([tiny_segment], tiny_config)
    assert counted == {"frames": 4, "pairs": 3, "decodes": 4, "decodes_if_each_pair_decoded_both_frames": 6,
                       "decode_once_per_frame": True}


def test_input_rate_of_the_training_pipeline(tiny_segment, tiny_config):
    r = bench_input.input_pairs_per_s([tiny_segment], tiny_config, cores=1, batches=3)
    assert r["cores"] == 1 and r["pairs_timed"] == 3 * BATCH and r["pairs_per_s"] > 0 and r["first_batch_s"] > 0
    assert r["mean_points_t0"] > 100  # tiny range images still give thousands of points per frame


@pytest.mark.slow  # every stage and record kind: ~45 s; lab/tools/benchmark_input.py runs the same
def test_every_stage_and_record_kind_read_on_the_cores_asked():
    lines = []
    result = bench_input.input_benchmark(None, TINY_OVERRIDES, {"tiny": TINY_SCALE}, [1], segments=1,
                                         frames_per_segment=3, batches=1, progress=lines.append)
    tiny = result["densities"]["tiny"]
    run = tiny["runs"]["1"]
    assert run["cpus"] == FIRST_CPU  # the child was pinned to one CPU
    stages = {"read_frames", "decode_frames", "decode_and_pair", "decode_pair_batch", "records_exact",
              "records_compact"}
    assert set(tiny["per_core_per_s"]["1"]) == stages and all(v > 0 for v in tiny["per_core_per_s"]["1"].values())
    assert run["read_frames"]["timed"] == 4 * BATCH and run["decode_frames"]["timed"] == BATCH
    assert run["decode_pair_batch"]["timed"] == run["records_exact"]["timed"] == BATCH  # one batch of pairs
    sizes = tiny["sizes"]
    assert sizes["points_per_frame"] > 100 and sizes["exact_write_pairs_per_s"] > 0
    assert 0 < sizes["compact_bytes_per_pair"] < sizes["exact_bytes_per_pair"]
    assert sizes["exact_wod_train_split_tb"] == pytest.approx(
        sizes["exact_bytes_per_pair"] * bench_input.WOD_TRAIN_PAIRS / 1e12)
    assert result["batch_size"] == BATCH and result["overrides"] == list(TINY_OVERRIDES) and len(lines) == 1


def test_core_counts_checked_before_any_work():
    available = len(os.sched_getaffinity(0))
    for wrong in ([0], [available + 1], []):
        with pytest.raises(ValueError, match=f"each must be 1 to {available}"):
            bench_input.input_benchmark(None, TINY_OVERRIDES, {"tiny": TINY_SCALE}, wrong)


def test_a_failed_reading_is_named_with_its_core_count():
    # pin_cores returns a list, not a measurement's dict: the child fails after it ran
    with pytest.raises(children.ChildError, match=r"(?s)^pinning on 1 core\(s\): its process ended with exit 1.*"
                                                  r"returned list"):
        bench_input.per_core("lab.children:pin_cores", {}, [1], "pinning")
