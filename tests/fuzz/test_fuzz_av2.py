"""Damaged Argoverse 2 logs, read by the AV2 reader as a labelled pair reads them, end as a finite read or an
`Argoverse2FormatError` naming the damaged file and column."""
import os

import numpy as np

from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.fuzz import av2

AV2_LOG = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "data",
                       "av2_sample_log")


def test_av2_mutants(tmp_path):
    report = av2.fuzz_log(AV2_LOG, str(tmp_path), 6 * len(av2.KINDS), seed=2)
    assert not report.defects, report.format("defects")
    table = report.table()
    assert set(table) == set(av2.KINDS)
    # Every kind damaged something the reader noticed: the mutators are not no-ops.
    assert all(counts["named_error"] > 0 for counts in table.values()), report.format("kinds never detected")


def test_a_clean_copy_reads_both_sweeps_with_their_cuboids(tmp_path):
    clean = av2.small_copy(AV2_LOG, str(tmp_path / "clean"), max_points=500)
    stamps = argoverse2.sweep_timestamps(clean)
    sweeps = av2.read_pair(clean, stamps)
    assert len(sweeps) == 2
    for (frame, boxes), ts in zip(sweeps, stamps):
        assert len(frame["points_xyz"]) == 500 and len(boxes["center"]) > 0
        np.testing.assert_array_equal(frame["pose"], argoverse2.ego_pose(clean, ts))
    outcome, detail = av2.classify(lambda: sweeps, os.path.join(clean, "annotations.feather"))
    assert outcome == "decoded" and detail.startswith("500 points"), detail


def test_a_deleted_sweep_is_named(tmp_path):
    clean = av2.small_copy(AV2_LOG, str(tmp_path / "clean"), max_points=100)
    stamps = argoverse2.sweep_timestamps(clean)
    path = os.path.join(clean, "sensors", "lidar", f"{stamps[1]}.feather")
    os.remove(path)
    outcome, detail = av2.classify(lambda: av2.read_pair(clean, stamps), path)
    assert outcome == "named_error" and f"{stamps[1]}.feather" in detail, detail
