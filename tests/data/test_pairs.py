"""Frame pairing, ego-motion compensation and bucketed batching."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import replace_config
from ff3d_tf.data import pair_records, pairs, wod_errors
from ff3d_tf.data.wod import waymo


def test_pairs_move_previous_cloud_into_t0_frame(tiny_segment, tiny_records, tiny_config):
    cfg = tiny_config.__class__(grid=tiny_config.grid, data=tiny_config.data.__class__(crop_to_grid=False),
                                model=tiny_config.model, train=tiny_config.train)
    examples = list(pairs.pair_dataset([tiny_segment], cfg))
    assert len(examples) == len(tiny_records) - 1
    f0 = waymo.decode_frame(tiny_records[0])
    f1 = waymo.decode_frame(tiny_records[1])
    ex = {k: v.numpy() for k, v in examples[0].items()}
    t = np.linalg.inv(f1["pose"]) @ f0["pose"]  # T = inv(pose_t0) @ pose_tm1
    expected = f0["points_xyz"].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
    np.testing.assert_allclose(ex["points_xyz_tm1_in_t0"], expected, atol=1e-4)
    np.testing.assert_array_equal(ex["points_xyz_t0"], f1["points_xyz"])
    np.testing.assert_array_equal(ex["class_id_t0"], f1["class_id"])
    np.testing.assert_array_equal(ex["pose_tm1"], f0["pose"])
    # Ego moved: the raw t-1 cloud differs from the compensated one.
    assert np.abs(t[:3, 3]).max() > 0.1


@pytest.mark.parametrize("order, bad_record, gap_us", [((0, 2, 3), 1, 200_000), ((1, 0, 2), 1, -100_000)],
                         ids=["missing", "out_of_order"])
def test_a_missing_or_reordered_frame_is_named(tiny_records, tiny_config, tmp_path, order, bad_record, gap_us):
    """Frames 0.1 s apart: without frame 1, record 1 comes 0.2 s after record 0; with frames 0 and 1 swapped, record
    1 comes 0.1 s before record 0. Either is an error naming the file, the record and its timestamp."""
    path = str(tmp_path / "gap.tfrecord")
    with tf.io.TFRecordWriter(path) as w:
        for i in order:
            w.write(tiny_records[i])
    stamp = waymo.decode_frame(tiny_records[order[bad_record]])["timestamp_micros"]
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        with pairs.input_errors_named([path]):
            list(pairs.pair_dataset([path], tiny_config))
    assert (err.value.path, err.value.record_index, err.value.field) == (path, bad_record, "timestamp_micros")
    assert f"timestamp_micros {stamp} comes {gap_us} us after" in str(err.value)
    if gap_us > 0:  # skip_bad_records drops the examples across the gap: frames (3, 2) are left
        skip = replace_config(tiny_config, {"data.skip_bad_records": True})
        assert len(list(pairs.pair_dataset([path], skip))) == 1
        three = replace_config(skip, {"data.num_frames": 3, "model.temporal": "delta"})
        assert len(list(pairs.pair_dataset([path], three))) == 0  # (3, 2, 0) reaches across the gap


def test_a_bad_record_is_the_only_error_when_reading_goes_on(tiny_records, tiny_config, tmp_path):
    """An input pipeline may read on after an error (prefetching, parallel calls): the record after a bad one then
    follows the record before it, which is no missing frame of its own. Reading on after each error, only the bad
    record's error comes, and the pair after it (frames 3, 2) still does."""
    import corrupt_records
    path = corrupt_records.write_records(str(tmp_path / "bad.tfrecord"), [
        tiny_records[0], corrupt_records.nan_range_image(tiny_records[1], 4), tiny_records[2], tiny_records[3]])
    iterator, errors, examples = iter(pairs.pair_dataset([path], tiny_config, metadata=True)), [], []
    while True:
        try:
            examples.append(next(iterator))
        except StopIteration:
            break
        except tf.errors.OpError as err:
            errors.append(wod_errors.parse_tagged_error(err.message))
    assert errors and all(e.field.startswith("lasers[SIDE_RIGHT].ri_return1") for e in errors), errors
    stamp_us = waymo.decode_frame(tiny_records[3])["timestamp_micros"]
    assert [int(ex[pair_records.TIMESTAMP_KEY]) for ex in examples] == [stamp_us * 1000]


def test_bucketed_batches(tiny_segment, tiny_config):
    ds = pairs.batch_examples(pairs.pair_dataset([tiny_segment], tiny_config), 2, 1024)
    batch = next(iter(ds))
    n = int(batch["points_xyz_t0"].shape[1])
    assert n == pairs.bucket_size(int(tf.reduce_max(batch["num_points_t0"])), 1024)
    mask = batch["point_mask_t0"].numpy()
    assert mask.sum() == int(tf.reduce_sum(batch["num_points_t0"]))
    assert np.all(batch["class_id_t0"].numpy()[~mask] == -1)
    assert pairs.bucket_size(1025, 1024) == 1536 and pairs.bucket_size(1, 1024) == 1024
    assert pairs.bucket_size(3000, 1024) == 3072


def _frame(xyz, flow, cls, pose):
    n = len(xyz)
    return {"points_xyz": tf.constant(xyz, tf.float32), "intensity": tf.zeros([n]), "elongation": tf.zeros([n]),
            "flow_mps": tf.constant(flow, tf.float32), "class_id": tf.constant(cls, tf.int32),
            "pose": tf.constant(pose, tf.float64)}


def test_study_knobs(tiny_config):
    # Points: vehicle, pedestrian, cyclist, background on the ground, background 1 m up (all moving but background).
    xyz = [[1, 0, 1.0], [2, 0, 1.0], [3, 0, 1.0], [4, 0, 0.05], [5, 0, 1.0]]
    flow = [[5, 0, 0], [1, 0, 0], [3, 0, 0], [0, 0, 0], [0, 0, 0]]
    cls = [1, 2, 4, 0, 0]
    pose_tm1, pose_t0 = np.eye(4), np.eye(4)
    pose_t0[0, 3] = 1.0  # ego moved 1 m forward
    f_tm1, f_t0 = _frame(xyz, flow, cls, pose_tm1), _frame(xyz, flow, cls, pose_t0)

    def pair(**data):
        cfg = replace_config(tiny_config, {f"data.{k}": v for k, v in data.items()})
        return {k: v.numpy() for k, v in pairs.make_pair(f_tm1, f_t0, cfg, tf.constant([1, 2])).items()}

    base = pair()
    np.testing.assert_allclose(base["points_xyz_tm1_in_t0"][:, 0], np.array(xyz)[:, 0] - 1.0)  # moved into t0
    np.testing.assert_allclose(pair(ego_motion_compensation=False)["points_xyz_tm1_in_t0"], xyz)
    ped_stat = pair(class_ablation="pedestrian_stationary")
    assert ped_stat["class_id_t0"].tolist() == [1, 0, 4, 0, 0] and ped_stat["flow_mps_t0"][1].tolist() == [0, 0, 0]
    cyc_ign = pair(class_ablation="cyclist_ignored")
    assert cyc_ign["class_id_t0"].tolist() == [1, 2, -1, 0, 0] and cyc_ign["flow_mps_t0"][2, 0] == 3
    assert pair(class_ablation="pedestrian_cyclist_stationary")["class_id_t0"].tolist() == [1, 0, 0, 0, 0]
    no_ground = pair(remove_ground_below_z_m=0.2)
    assert no_ground["num_points_t0"] == 4 and no_ground["num_points_tm1"] == 4
    assert no_ground["points_xyz_t0"][:, 2].min() >= 0.2
    sparse = pair(point_keep_fraction=0.5)  # seeded: the same points on every run
    assert sparse["num_points_t0"] < 5 and sparse["num_points_tm1"] < 5
    np.testing.assert_array_equal(sparse["points_xyz_t0"], pair(point_keep_fraction=0.5)["points_xyz_t0"])


def test_input_pipeline_names_bad_input(tiny_records, tiny_config, tmp_path):
    import pytest

    import corrupt_records
    garbage = corrupt_records.write_records(str(tmp_path / "garbage.tfrecord"),
                                            [tiny_records[0], corrupt_records.GARBAGE, tiny_records[2]])
    truncated = corrupt_records.truncate_file(
        corrupt_records.write_records(str(tmp_path / "truncated.tfrecord"), tiny_records[:3]), 100)
    # A file cut inside its first record used to give no pairs and no error (Dataset.window swallowed it).
    cut_first = corrupt_records.truncate_file(
        corrupt_records.write_records(str(tmp_path / "cut_first.tfrecord"), tiny_records[:1]), 100)
    for path, where in ((garbage, "record 1: field Frame: malformed protobuf Frame"),
                        (truncated, "record 2: field tfrecord: corrupt or truncated"),
                        (cut_first, "record 0: field tfrecord: corrupt or truncated")):
        with pytest.raises(wod_errors.FrameDecodeError, match=f"{path}: {where}"):
            with pairs.input_errors_named([path]):
                list(pairs.pair_dataset([path], tiny_config))
    # Skipping: the garbage record leaves frames 0 and 2 (0.2 s apart: no pair); the truncated file ends after 2.
    skip = replace_config(tiny_config, {"data.skip_bad_records": True})
    assert len(list(pairs.pair_dataset([garbage], skip))) == 0
    assert len(list(pairs.pair_dataset([truncated], skip))) == 1
