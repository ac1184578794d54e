"""Sequences of `data.num_frames` sweeps: each past cloud in the t0 frame by its own pose, the first frames of a log
without a full history give no example, decode-once records carry the past sweeps and refuse another N."""
import numpy as np
import pytest

from ff3d_tf import schema
from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.wod import waymo, write_records


def _sequence_config(cfg, num_frames):
    return replace_config(cfg, {"data.num_frames": num_frames, "model.temporal": "delta",
                                "data.crop_to_grid": False})


def _in_t0(points_xyz, pose_t0, pose_tk):
    """NumPy reference: points of sweep t-k in the vehicle frame at t0, T = inv(pose_t0) @ pose_tk."""
    t = np.linalg.inv(pose_t0) @ pose_tk
    return points_xyz.astype(np.float64) @ t[:3, :3].T + t[:3, 3]


def test_every_past_sweep_is_moved_into_t0_by_its_own_pose(tiny_segment, tiny_records, tiny_config):
    cfg = _sequence_config(tiny_config, 3)
    examples = [{k: v.numpy() for k, v in ex.items()} for ex in pairs.pair_dataset([tiny_segment], cfg)]
    frames = [waymo.decode_frame(r) for r in tiny_records]
    # 4 frames, 3 sweeps each: frames 2 and 3 have a full history; frame 1 has a t-1 but no t-2 (no example).
    assert len(examples) == len(frames) - 2
    for i, ex in enumerate(examples):
        f_t0, f_tm1, f_tm2 = frames[i + 2], frames[i + 1], frames[i]
        np.testing.assert_array_equal(ex["points_xyz_t0"], f_t0["points_xyz"])
        np.testing.assert_allclose(ex["points_xyz_tm1_in_t0"], _in_t0(f_tm1["points_xyz"], f_t0["pose"],
                                                                      f_tm1["pose"]), atol=1e-4)
        np.testing.assert_allclose(ex["points_xyz_tm2_in_t0"], _in_t0(f_tm2["points_xyz"], f_t0["pose"],
                                                                      f_tm2["pose"]), atol=1e-4)
        np.testing.assert_array_equal(ex["pose_tm2"], f_tm2["pose"])
        assert ex["num_points_tm2"] == len(f_tm2["points_xyz"])
        np.testing.assert_array_equal(ex["point_features_tm2"][:, 0], f_tm2["intensity"])
        # The check has power: the t-2 cloud moved by t-1's pose (a known, different rotation and translation) is
        # far from the right one.
        wrong = _in_t0(f_tm2["points_xyz"], f_t0["pose"], f_tm1["pose"])
        assert np.abs(wrong - ex["points_xyz_tm2_in_t0"]).max() > 0.1


def test_two_frames_are_the_pair(tiny_segment, tiny_config):
    """num_frames 2 (the default) gives the pair's examples, key for key."""
    pair = list(pairs.pair_dataset([tiny_segment], tiny_config))
    seq = list(pairs.pair_dataset([tiny_segment], replace_config(tiny_config, {"model.temporal": "stack"})))
    assert len(pair) == len(seq) and set(pair[0]) == set(seq[0]) == set(schema.PAIR_KEYS)
    for a, b in zip(pair, seq):
        for k in a:
            np.testing.assert_array_equal(a[k].numpy(), b[k].numpy(), err_msg=k)


def test_batches_pad_and_mask_every_sweep(tiny_segment, tiny_config):
    cfg = _sequence_config(tiny_config, 4)
    batch = next(iter(pairs.batch_examples(pairs.pair_dataset([tiny_segment], cfg), 1, 1024)))
    for cloud in schema.sweep_clouds(4):
        keys = schema.cloud_keys(cloud)
        n = int(batch[keys["count"]][0])
        assert batch[keys["xyz"]].shape[1] == pairs.bucket_size(n, 1024)
        assert int(batch[keys["mask"]].numpy().sum()) == n


def test_records_carry_the_past_sweeps_and_refuse_another_number(tiny_segment, tiny_config, tmp_path):
    cfg = _sequence_config(tiny_config, 3)
    out = str(tmp_path / "records")
    manifest = write_records.wod_manifest(cfg)
    assert manifest.num_frames == 3
    pair_records.write_manifest(out, manifest)
    write_records.write_segment(tiny_segment, out, cfg, manifest)
    files = pairs.list_segment_files(out)
    records_cfg = replace_config(cfg, {"data.source": "pair_records"})
    decoded = list(pairs.pair_dataset([tiny_segment], cfg))
    read = list(pairs.pair_dataset(files, records_cfg))
    assert len(read) == len(decoded) == 2
    for a, b in zip(decoded, read):
        assert set(a) == set(b)
        for k in a:
            np.testing.assert_array_equal(a[k].numpy(), b[k].numpy(), err_msg=k)
    # Records of 3 sweeps serve no config of another number, before any record is read.
    for other in (2, 4):
        changes = {"data.num_frames": other} if other != 2 else {"data.num_frames": 2, "model.temporal": "pair"}
        with pytest.raises(ConfigError, match=f"hold 3 sweeps.*data.num_frames={other}"):
            pairs.pair_dataset(files, replace_config(records_cfg, changes))


def test_a_sequence_of_one_sweep_or_too_many_is_a_config_error(tiny_config):
    for n in (1, schema.MAX_NUM_FRAMES + 1):
        with pytest.raises(ConfigError, match="data.num_frames"):
            replace_config(tiny_config, {"data.num_frames": n, "model.temporal": "delta"})
    with pytest.raises(ConfigError, match="model.temporal=pair"):
        replace_config(tiny_config, {"data.num_frames": 3})
