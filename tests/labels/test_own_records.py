"""Pair records of your own sweeps (`ff3d_tf.labels.own_records`): the synthetic WOD segment written out as a sweeps
directory with its box table gives the WOD path's records (same points, same box rule, same labels, same boxes per
point); unlabelled records; refusals before any work (no poses, no boxes); the job resumes; a gap is skipped."""
import os

import numpy as np
import pytest

from ff3d_tf import schema
from ff3d_tf.config import replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.files import sequences
from ff3d_tf.data.files.point_file_errors import PointFileError
from ff3d_tf.data.synthetic import files as synthetic_files
from ff3d_tf.data.wod import waymo, write_records
from ff3d_tf.labels import own_records, pipeline


def _examples(out_dir, extras=()):
    (path,) = [os.path.join(out_dir, f) for f in os.listdir(out_dir) if f.endswith(pair_records.FILE_SUFFIX)]
    manifest = pair_records.read_manifest(out_dir)
    return [{k: v.numpy() for k, v in ex.items()} for ex in pair_records.records_dataset(path, manifest, extras)]


def _own_records(seq_dir, out_dir, cfg, options=own_records.OwnRecordsOptions()):
    manifest = own_records.records_manifest(cfg, options.labels)
    pair_records.write_manifest(out_dir, manifest)
    return own_records.write_sequence_records(seq_dir, out_dir, cfg, manifest, options)


@pytest.fixture(scope="module")
def sequence_dir(tiny_records, tmp_path_factory):
    """The tiny synthetic segment as a sweeps directory with poses, timestamps and boxes."""
    d = str(tmp_path_factory.mktemp("own") / "segment-tiny")
    assert synthetic_files.write_frames_as_sequence(tiny_records, d) == len(tiny_records)
    return d


def test_round_trip_equals_the_wod_paths_records(tiny_segment, tiny_records, tiny_config, sequence_dir, tmp_path):
    # The WOD path: the segment labelled by the paper's box rule (tools/annotate_flow.py), then its pair records with
    # each point's box (tools/write_pair_records.py --source wod on labelled segments).
    annotated = str(tmp_path / "annotated" / os.path.basename(tiny_segment))
    pipeline.annotate_segment(tiny_segment, annotated)
    wod_manifest = write_records.wod_manifest(tiny_config, extras=pipeline.WOD_RECORD_EXTRAS)
    pair_records.write_manifest(str(tmp_path / "wod"), wod_manifest)
    write_records.write_segment(annotated, str(tmp_path / "wod"), tiny_config, wod_manifest,
                                pipeline.instance_ids_of_segment)
    counts = _own_records(sequence_dir, str(tmp_path / "own"), tiny_config)
    assert counts["pairs"] == len(tiny_records) - 1 and counts["skipped_pairs"] == 0
    wod = _examples(str(tmp_path / "wod"), pipeline.WOD_RECORD_EXTRAS)
    own = _examples(str(tmp_path / "own"), own_records.OWN_EXTRAS)
    assert len(own) == len(wod) == len(tiny_records) - 1
    for w, o in zip(wod, own):
        for key in ("points_xyz_t0", "points_xyz_tm1_in_t0", "pose_t0", "pose_tm1", "class_id_t0", "instance_id_t0",
                    pair_records.TIMESTAMP_KEY, pair_records.PARTNER_TIMESTAMP_KEY):
            np.testing.assert_array_equal(o[key], w[key], err_msg=key)
        np.testing.assert_allclose(o["flow_mps_t0"], w["flow_mps_t0"], rtol=1e-6, atol=1e-6)  # float32
        np.testing.assert_array_equal(o["point_features_t0"][:, 0], w["point_features_t0"][:, 0])  # intensity
        assert (o["class_id_t0"] > 0).sum() > 100 and (o["instance_id_t0"] >= 0).sum() > 100
    assert o[pair_records.SEQUENCE_KEY].decode() == "segment-tiny"


def test_labels_are_the_synthetic_scenes_ground_truth(tiny_records, tiny_config, sequence_dir, tmp_path):
    """The simulator's own flow (the segment's flow channel, from the agents' true rigid motion) is what the box rule
    gives: same classes, flow within a millimetre per second."""
    _own_records(sequence_dir, str(tmp_path / "own"), tiny_config)
    own = _examples(str(tmp_path / "own"), own_records.OWN_EXTRAS)
    for i, ex in enumerate(own, start=1):
        truth = waymo.decode_frame(tiny_records[i])
        np.testing.assert_array_equal(ex["class_id_t0"], truth["class_id"])
        moving = np.linalg.norm(truth["flow_mps"], axis=1) > schema.MOVING_THRESHOLD_MPS
        assert moving.sum() > 50
        assert np.abs(ex["flow_mps_t0"] - truth["flow_mps"]).max() <= 1e-3
        # each point of a box is that box's (the -1 of class -1 points is the box's, not "no box")
        assert np.all((ex["instance_id_t0"] >= 0) == (ex["class_id_t0"] != 0))


def test_unlabelled_records_keep_every_point_and_carry_no_labels(tiny_config, sequence_dir, tmp_path):
    options = own_records.OwnRecordsOptions(labels=False)
    _own_records(sequence_dir, str(tmp_path / "raw"), tiny_config, options)
    manifest = pair_records.read_manifest(str(tmp_path / "raw"))
    assert not manifest.human_labels and manifest.extras == () and manifest.source == own_records.OWN_SOURCE
    for ex in _examples(str(tmp_path / "raw")):
        assert np.all(ex["class_id_t0"] == schema.CLASS_NO_LABEL) and not ex["flow_mps_t0"].any()
    # read through the training input as raw LiDAR: only the pseudo-label route takes them
    from ff3d_tf.config import ConfigError
    cfg = replace_config(tiny_config, {"data.source": "pair_records"})
    with pytest.raises(ConfigError, match="no human flow labels"):
        pairs.pair_dataset(pairs.list_segment_files(str(tmp_path / "raw")), cfg)


def test_no_poses_and_no_boxes_are_refused_saying_what_to_give(sequence_dir, tmp_path):
    import shutil
    bare = str(tmp_path / "bare")
    shutil.copytree(sequence_dir, bare)
    os.remove(os.path.join(bare, "poses.txt"))
    with pytest.raises(PointFileError) as err:
        own_records.check_sequence(bare, own_records.OwnRecordsOptions())
    assert err.value.field == "pose" and "poses.txt" in str(err.value) and ".pose.txt" in str(err.value)
    with pytest.raises(PointFileError, match="no poses"):  # unlabelled records need them too
        own_records.check_sequence(bare, own_records.OwnRecordsOptions(labels=False))
    shutil.copy(os.path.join(sequence_dir, "poses.txt"), bare)
    os.remove(os.path.join(bare, "boxes.csv"))
    with pytest.raises(PointFileError, match="--no_labels"):
        own_records.check_sequence(bare, own_records.OwnRecordsOptions())
    assert own_records.check_sequence(bare, own_records.OwnRecordsOptions(labels=False)).box_table is None


def test_a_gap_is_named_or_skipped_and_the_job_resumes(tiny_config, sequence_dir, tmp_path):
    import shutil
    gappy = str(tmp_path / "gappy")
    shutil.copytree(sequence_dir, gappy)
    stamps = sequences.read_timestamps(os.path.join(gappy, "timestamps.txt"), 4)
    stamps[2] += 200_000_000  # sweep 2 comes 0.3 s after sweep 1: over data.max_frame_gap_s
    stamps[3] += 200_000_000
    with open(os.path.join(gappy, "timestamps.txt"), "w") as f:
        f.write("".join(f"{t // 10 ** 9}.{t % 10 ** 9:09d}\n" for t in stamps))  # exact to the ns
    out = str(tmp_path / "out")
    manifest = own_records.records_manifest(tiny_config, True)
    os.makedirs(out)
    with pytest.raises(PointFileError, match=f"at {stamps[2]} ns comes 0.300 s after") as err:
        own_records.write_sequence_records(gappy, out, tiny_config, manifest, own_records.OwnRecordsOptions())
    sweep_2 = own_records.check_sequence(gappy, own_records.OwnRecordsOptions()).sweeps[2]
    assert err.value.path == sweep_2 and err.value.field == "timestamp"
    assert not [f for f in os.listdir(out) if f.endswith(pair_records.FILE_SUFFIX)]  # nothing half-written
    skip = replace_config(tiny_config, {"data.skip_bad_records": True})
    counts = own_records.run_records_job([gappy], out, skip, own_records.OwnRecordsOptions())
    assert counts["pairs"] == 2 and counts["skipped_pairs"] == 1
    assert [int(ex[pair_records.TIMESTAMP_KEY]) for ex in _examples(out)] == [stamps[1], stamps[3]]
    again = own_records.run_records_job([gappy], out, skip, own_records.OwnRecordsOptions())
    assert again.get("already_done") == 1 and "pairs" not in again


def test_records_of_three_sweeps_equal_the_wod_paths(tiny_segment, tiny_records, tiny_config, sequence_dir, tmp_path):
    """With data.num_frames=3 the own-sequence records hold the sweep before t-1, clamped to the first sweep at the
    start, exactly as the WOD path's records of the same frames."""
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta"})
    wod_manifest = write_records.wod_manifest(cfg)
    pair_records.write_manifest(str(tmp_path / "wod"), wod_manifest)
    wod_counts = write_records.write_segment(tiny_segment, str(tmp_path / "wod"), cfg, wod_manifest)
    own_counts = _own_records(sequence_dir, str(tmp_path / "own"), cfg, own_records.OwnRecordsOptions(labels=False))
    assert wod_counts["pairs_without_full_history"] == own_counts["pairs_without_full_history"] == 1  # the first
    wod, own = _examples(str(tmp_path / "wod")), _examples(str(tmp_path / "own"))
    assert len(own) == len(wod) == len(tiny_records) - 1
    assert [bool(o[schema.FULL_HISTORY_KEY]) for o in own] == [False] + [True] * (len(own) - 1)
    for w, o in zip(wod, own):
        for key in ("points_xyz_tm2_in_t0", "pose_tm2", "num_points_tm2", schema.FULL_HISTORY_KEY):
            np.testing.assert_array_equal(o[key], w[key], err_msg=key)
