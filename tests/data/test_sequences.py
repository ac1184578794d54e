"""Sequences of `data.num_frames` sweeps: each past cloud in the t0 frame by its own pose, the first frames of a log
without a full history give no example, decode-once records carry the past sweeps and refuse another N."""
import dataclasses
import os

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
    # 4 frames, 3 sweeps each: frames 2 and 3 have a full history; frame 1 has a t-1 but no t-2: the file's first
    # frame (its t-1) stands in for it, as the DeltaFlow authors' evaluation loader clamps history.
    assert len(examples) == len(frames) - 1
    assert [bool(ex[schema.FULL_HISTORY_KEY]) for ex in examples] == [False, True, True]
    for i, ex in enumerate(examples):
        f_t0, f_tm1, f_tm2 = frames[i + 1], frames[i], frames[max(i - 1, 0)]
        np.testing.assert_array_equal(ex["points_xyz_t0"], f_t0["points_xyz"])
        np.testing.assert_allclose(ex["points_xyz_tm1_in_t0"], _in_t0(f_tm1["points_xyz"], f_t0["pose"],
                                                                      f_tm1["pose"]), atol=1e-4)
        np.testing.assert_allclose(ex["points_xyz_tm2_in_t0"], _in_t0(f_tm2["points_xyz"], f_t0["pose"],
                                                                      f_tm2["pose"]), atol=1e-4)
        np.testing.assert_array_equal(ex["pose_tm2"], f_tm2["pose"])
        assert ex["num_points_tm2"] == len(f_tm2["points_xyz"])
        np.testing.assert_array_equal(ex["point_features_tm2"][:, 0], f_tm2["intensity"])
        # The check has power: the t-2 cloud moved by t0's own pose (a known, different rotation and translation)
        # is far from the right one.
        wrong = _in_t0(f_tm2["points_xyz"], f_t0["pose"], f_t0["pose"])
        assert np.abs(wrong - ex["points_xyz_tm2_in_t0"]).max() > 0.1


def test_two_frames_are_the_pair(tiny_segment, tiny_config):
    """num_frames 2 (the default) gives the pair's examples, key for key."""
    pair = list(pairs.pair_dataset([tiny_segment], tiny_config))
    seq = list(pairs.pair_dataset([tiny_segment], replace_config(tiny_config, {"model.temporal": "stack"})))
    assert len(pair) == len(seq) and set(pair[0]) == set(seq[0]) == set(schema.PAIR_KEYS)
    for a, b in zip(pair, seq):
        for k in a:
            np.testing.assert_array_equal(a[k].numpy(), b[k].numpy(), err_msg=k)


def test_dropping_ground_from_examples_without_masks_is_a_config_error(tiny_segment, tiny_config):
    with pytest.raises(ConfigError, match=r"data.drop_ground=true: these examples carry no is_ground_t0"):
        pairs.batch_examples(pairs.pair_dataset([tiny_segment], tiny_config), 1, 1024, drop_ground=True)


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
    assert len(read) == len(decoded) == 3
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


def test_training_reads_only_examples_with_their_own_history(tiny_segment, tiny_records, tiny_config):
    """4 frames, 4 sweeps per example: only the last frame has its 3 past ones, so the repeated training stream is
    that example alone (the decoded stream also holds the 2 frames with clamped history)."""
    from ff3d_tf.training import input as training_input
    cfg = replace_config(_sequence_config(tiny_config, 4), {"data.shuffle_buffer": 1})
    assert len(list(pairs.pair_dataset([tiny_segment], cfg))) == 3
    last = len(waymo.decode_frame(tiny_records[-1])["points_xyz"])
    for batch in training_input.training_dataset([tiny_segment], cfg, 1).take(3):
        assert bool(batch[schema.FULL_HISTORY_KEY][0])
        assert int(batch["num_points_t0"][0]) == last


def test_av2_records_of_three_sweeps_hold_the_sweep_before_t0(tiny_config, tmp_path):
    """The real sample log: records of 3 sweeps pair each sweep with the next (the challenge's partner) and hold the
    sweep before it as "tm2", moved into the t0 frame by its own pose; sweep 0 has none before it and repeats itself
    (full_history False)."""
    from conftest import AV2_LOG
    from ff3d_tf.data.av2 import argoverse2
    from ff3d_tf.labels import av2
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta"})
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    out = str(tmp_path / "av2")
    manifest = av2.records_manifest(cfg)
    assert (manifest.num_frames, manifest.partner) == (3, "next")
    pair_records.write_manifest(out, manifest)
    assert av2.write_log_records(AV2_LOG, out, cfg, manifest)["pairs"] == len(stamps) - 1
    examples = [{k: v.numpy() for k, v in ex.items()} for ex in pairs.pair_dataset(
        pairs.list_segment_files(out), replace_config(cfg, {"data.source": "pair_records", "data.crop_to_grid": False}),
        metadata=True)]
    assert [bool(ex[schema.FULL_HISTORY_KEY]) for ex in examples] == [i >= 1 for i in range(len(stamps) - 1)]
    for i, ex in enumerate(examples):
        assert ex[pair_records.TIMESTAMP_KEY] == stamps[i] and ex[pair_records.PARTNER_TIMESTAMP_KEY] == stamps[i + 1]
        before = argoverse2.read_sweep(AV2_LOG, stamps[max(i - 1, 0)])
        np.testing.assert_array_equal(ex["pose_tm2"], before["pose"])
        np.testing.assert_allclose(ex["points_xyz_tm2_in_t0"], _in_t0(before["points_xyz"], ex["pose_t0"],
                                                                      before["pose"]), atol=1e-3)


def test_av2_records_flag_every_sweeps_ground_and_drop_ground_masks_it_out(tiny_config, tmp_path):
    """Records of 3 sweeps of the real sample log hold every sweep's ground by the log's raster (each sweep's own
    points and pose, `argoverse2.is_ground`); with `data.drop_ground` every cloud's model mask is its real points
    less its ground, while the ground points keep their place and labels in the example (flow 0 is predicted there);
    records without the past sweeps' masks are a ConfigError naming the tool that adds them."""
    from conftest import AV2_LOG
    from ff3d_tf.data.av2 import argoverse2
    from ff3d_tf.labels import av2
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta"})
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    out = str(tmp_path / "av2")
    manifest = av2.records_manifest(cfg)
    assert set(schema.ground_keys(3)) <= set(manifest.extras)
    pair_records.write_manifest(out, manifest)
    av2.write_log_records(AV2_LOG, out, cfg, manifest)
    files = pairs.list_segment_files(out)
    read_cfg = replace_config(cfg, {"data.source": "pair_records", "data.crop_to_grid": False})
    dropping = replace_config(read_cfg, {"data.drop_ground": True})
    examples = list(pairs.pair_dataset(files, read_cfg, extras=schema.ground_keys(3)))
    batches = list(pairs.batch_examples(pairs.pair_dataset(files, dropping), 1, 1024, drop_ground=True))
    assert len(examples) == len(batches) == len(stamps) - 1
    for i, (ex, batch) in enumerate(zip(examples, batches)):
        sweeps = [argoverse2.read_sweep(AV2_LOG, stamps[j]) for j in (i, i + 1, max(i - 1, 0))]  # t0, next, before
        for cloud, sweep in zip(schema.sweep_clouds(3), sweeps):
            ground = ex[schema.GROUND_KEY_FORMAT.format(cloud=cloud)].numpy()
            np.testing.assert_array_equal(ground, argoverse2.is_ground(AV2_LOG, sweep["points_xyz"], sweep["pose"]))
            n = len(ground)
            mask = batch[schema.cloud_keys(cloud)["mask"]].numpy()[0]
            np.testing.assert_array_equal(mask[:n], ~ground)
            assert not mask[n:].any() and 0 < ground.sum() < n
        n0 = int(batch["num_points_t0"][0])
        np.testing.assert_array_equal(batch["class_id_t0"].numpy()[0, :n0], ex["class_id_t0"].numpy())
    older = str(tmp_path / "older")  # as written before the past sweeps' masks
    pair_records.write_manifest(older, dataclasses.replace(manifest, extras=av2.AV2_EXTRAS))
    with pytest.raises(ConfigError, match=r"data.drop_ground.*is_ground_tm2.*tools/add_ground_masks.py"):
        pairs.pair_dataset([os.path.join(older, "x" + pair_records.FILE_SUFFIX)], dropping)


def test_a_dropped_ground_point_is_as_if_absent_from_every_sweep(tiny_config, tmp_path):
    """The authors remove ground points from every sweep; `data.drop_ground` masks them: the model's flow at the
    non-ground t0 points of the masked batch equals its flow on the same example with every sweep's ground points
    taken out (`delta` of 3, DeltaFlow's head, the real sample log's records), and is 0 at the ground points."""
    import tensorflow as tf
    from conftest import AV2_LOG
    from ff3d_tf.labels import av2
    from ff3d_tf.model.fastflow3d import build_model
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta", "model.head": "mlp"})
    out = str(tmp_path / "av2")
    manifest = av2.records_manifest(cfg)
    pair_records.write_manifest(out, manifest)
    av2.write_log_records(AV2_LOG, out, cfg, manifest)
    read_cfg = replace_config(cfg, {"data.source": "pair_records", "data.drop_ground": True})
    ex = next(iter(pairs.pair_dataset(pairs.list_segment_files(out), read_cfg)))
    masked = next(iter(pairs.batch_examples(tf.data.Dataset.from_tensors(ex), 1, 1024, drop_ground=True)))
    removed = dict(ex)
    for cloud in schema.sweep_clouds(3):
        keep = ~ex[schema.GROUND_KEY_FORMAT.format(cloud=cloud)]
        for k in [k for k in ex if k in schema.POINT_KEYS and schema.POINT_KEYS[k].cloud == cloud]:
            removed[k] = tf.boolean_mask(ex[k], keep)
        removed[schema.cloud_keys(cloud)["count"]] = tf.reduce_sum(tf.cast(keep, tf.int32))
    without = next(iter(pairs.batch_examples(tf.data.Dataset.from_tensors(removed), 1, 1024)))
    model = build_model(read_cfg, compile_mode="none")
    flow_masked = model(masked)["flow_mps"].numpy()[0]
    flow_without = model(without)["flow_mps"].numpy()[0]
    ground = ex["is_ground_t0"].numpy()
    n = len(ground)
    assert 0 < ground.sum() < n and np.abs(flow_without[:n - ground.sum()]).max() > 0
    np.testing.assert_allclose(flow_masked[:n][~ground], flow_without[:n - ground.sum()], atol=1e-5)
    assert not flow_masked[:n][ground].any()

