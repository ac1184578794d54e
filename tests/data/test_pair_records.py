"""Pair records (decode-once path): the examples they give equal, bit for bit, the decoding path's under any config;
compact precision, bad records, manifests and resumable writing."""
import dataclasses
import os

import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.data import pair_records, pairs, wod_errors
from ff3d_tf.data.wod import write_records


@pytest.fixture(scope="module")
def records_dir(tiny_segment, tiny_config, tmp_path_factory):
    out = str(tmp_path_factory.mktemp("records"))
    manifest = write_records.wod_manifest(tiny_config)
    pair_records.write_manifest(out, manifest)
    counts = write_records.write_segment(tiny_segment, out, tiny_config, manifest)
    assert counts["pairs"] == 3  # 4 frames
    return out


def _records_config(cfg):
    return replace_config(cfg, {"data.source": "pair_records"})


def _numpy(ds):
    return [{k: v.numpy() for k, v in ex.items()} for ex in ds]


@pytest.mark.parametrize("changes", [
    {},
    {"data.point_keep_fraction": 0.5, "data.class_ablation": "pedestrian_ignored"},
    {"data.remove_ground_below_z_m": -1.0, "data.crop_to_grid": False},
])
def test_records_give_the_decoding_paths_examples(records_dir, tiny_segment, tiny_config, changes):
    cfg = replace_config(tiny_config, changes)
    want = _numpy(pairs.pair_dataset([tiny_segment], cfg))
    files = pairs.list_segment_files(records_dir)
    assert [os.path.basename(f) for f in files] == ["segment-tiny" + pair_records.FILE_SUFFIX]
    got = _numpy(pairs.pair_dataset(files, _records_config(cfg)))
    assert len(got) == len(want) == 3
    for g, w in zip(got, want):
        assert sorted(g) == sorted(w)
        for k in w:
            assert g[k].dtype == w[k].dtype, k
            np.testing.assert_array_equal(g[k], w[k], err_msg=k)


def test_metadata_and_batches(records_dir, tiny_segment, tiny_config):
    files = pairs.list_segment_files(records_dir)
    got = _numpy(pairs.pair_dataset(files, _records_config(tiny_config), metadata=True))
    frames = _numpy(pairs.pair_dataset([tiny_segment], tiny_config, metadata=True))
    for key in (pair_records.TIMESTAMP_KEY, pair_records.PARTNER_TIMESTAMP_KEY):
        assert [g[key] for g in got] == [f[key] for f in frames]
    assert all(g[pair_records.TIMESTAMP_KEY] - g[pair_records.PARTNER_TIMESTAMP_KEY] == 100_000_000 for g in got)
    assert all(g[pair_records.SEQUENCE_KEY] == b"segment-tiny.tfrecord" for g in got)
    batch = next(iter(pairs.batch_examples(pairs.pair_dataset(files, _records_config(tiny_config)), 2, 1024)))
    assert batch["points_xyz_t0"].shape[1] % 1024 == 0


def test_compact_precision_keeps_coordinates_exact(tiny_segment, tiny_config, tmp_path):
    out = str(tmp_path)
    manifest = write_records.wod_manifest(tiny_config, precision="compact", compression="zlib")
    pair_records.write_manifest(out, manifest)
    write_records.write_segment(tiny_segment, out, tiny_config, manifest)
    got = _numpy(pairs.pair_dataset(pairs.list_segment_files(out), _records_config(tiny_config)))
    want = _numpy(pairs.pair_dataset([tiny_segment], tiny_config))
    for g, w in zip(got, want):
        for k in ("points_xyz_t0", "points_xyz_tm1_in_t0", "class_id_t0", "pose_t0"):
            np.testing.assert_array_equal(g[k], w[k], err_msg=k)
        for k in ("flow_mps_t0", "point_features_t0", "point_features_tm1"):
            # float16 rounds to nearest with 11 significant bits: |error| <= 2^-11 |x| (normal range).
            np.testing.assert_allclose(g[k], w[k], rtol=2.0 ** -11, atol=6.2e-5, err_msg=k)
        assert np.any(g["flow_mps_t0"] != w["flow_mps_t0"])  # it is float16 indeed


def _first_example(records_dir, tiny_config):
    return _numpy(pairs.pair_dataset(pairs.list_segment_files(records_dir), _records_config(tiny_config),
                                     metadata=True))[0]


def test_a_record_with_a_short_field_names_file_record_and_field(records_dir, tiny_config, tmp_path):
    ex = _first_example(records_dir, tiny_config)
    good = pair_records.serialize_pair(ex)
    proto = tf.train.Example.FromString(good)
    data = proto.features.feature["flow_mps_t0"].bytes_list.value[0]
    proto.features.feature["flow_mps_t0"].bytes_list.value[0] = data[:-4]  # one float short
    path = str(tmp_path / ("bad" + pair_records.FILE_SUFFIX))
    pair_records.write_manifest(str(tmp_path), write_records.wod_manifest(tiny_config))
    pair_records.write_records_atomically(path, [good, proto.SerializeToString()])
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        with pairs.input_errors_named([path]):
            list(pairs.pair_dataset([path], _records_config(tiny_config)))
    assert (err.value.path, err.value.record_index, err.value.field) == (path, 1, "flow_mps_t0")
    cfg = replace_config(_records_config(tiny_config), {"data.skip_bad_records": True})
    assert len(list(pairs.pair_dataset([path], cfg))) == 1  # skip mode drops it and goes on


def test_a_record_that_is_no_example_and_a_truncated_file_are_named(records_dir, tiny_config, tmp_path):
    good = pair_records.serialize_pair(_first_example(records_dir, tiny_config))
    pair_records.write_manifest(str(tmp_path), write_records.wod_manifest(tiny_config))
    path = str(tmp_path / ("junk" + pair_records.FILE_SUFFIX))
    pair_records.write_records_atomically(path, [good, good, b"\x07not a proto"])
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        with pairs.input_errors_named([path]):
            list(pairs.pair_dataset([path], _records_config(tiny_config)))
    assert (err.value.path, err.value.record_index, err.value.field) == (path, 2, "record")
    cut = str(tmp_path / ("cut" + pair_records.FILE_SUFFIX))
    with open(path, "rb") as f:
        data = f.read()
    with open(cut, "wb") as f:
        f.write(data[: len(good) + 16 + len(good) // 2])  # inside the second record
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        with pairs.input_errors_named([cut]):
            list(pairs.pair_dataset([cut], _records_config(tiny_config)))
    assert (err.value.path, err.value.record_index, err.value.field) == (cut, 1, "file")


def test_records_of_other_lidars_fail_before_any_work(records_dir, tiny_config):
    cfg = replace_config(_records_config(tiny_config), {"data.laser_names": [1]})
    with pytest.raises(ConfigError, match="lasers"):
        pairs.pair_dataset(pairs.list_segment_files(records_dir), cfg)
    with pytest.raises(ConfigError, match="pseudo"):
        pairs.pair_dataset(pairs.list_segment_files(records_dir),
                           replace_config(_records_config(tiny_config), {"data.labels": "pseudo"}))
    with pytest.raises(ConfigError, match="ego_motion"):
        replace_config(_records_config(tiny_config), {"data.ego_motion_compensation": False})


def test_manifest_guards_a_directory(records_dir, tiny_config):
    other = dataclasses.replace(write_records.wod_manifest(tiny_config), precision="compact")
    with pytest.raises(wod_errors.FrameDecodeError, match="another --out_dir"):
        pair_records.write_manifest(records_dir, other)
    pair_records.write_manifest(records_dir, dataclasses.replace(write_records.wod_manifest(tiny_config),
                                                                 written_by="a rerun"))  # same kind: fine
    with open(pair_records.manifest_path(records_dir)) as f:
        assert '"format": "ff3d_tf.pair_records"' in f.read()


def test_writing_resumes_and_an_interrupted_write_leaves_nothing(tiny_segment, tiny_config, tmp_path, monkeypatch):
    out = str(tmp_path)
    manifest = write_records.wod_manifest(tiny_config)
    target = os.path.join(out, pair_records.records_file_name(tiny_segment))

    def interrupted(*args, **kwargs):  # one pair, then the job is interrupted
        yield {k: tf.constant(v) for k, v in {**_fake_pair(), "num_points_t0": 5, "num_points_tm1": 4}.items()}
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(write_records.pairs, "pair_dataset", interrupted)
        with pytest.raises(KeyboardInterrupt):
            write_records.write_segment(tiny_segment, out, tiny_config, manifest)
    assert not os.path.exists(target) and not os.path.exists(target + ".partial")
    first = write_records.write_segment(tiny_segment, out, tiny_config, manifest)
    with open(target, "rb") as f:
        data = f.read()
    assert first["pairs"] == 3 and first["bytes"] == len(data)
    assert write_records.write_segment(tiny_segment, out, tiny_config, manifest) == {"already_done": 1}


def _fake_pair(n0=5, n1=4):
    rng = np.random.default_rng(0)
    return {"points_xyz_t0": rng.normal(size=(n0, 3)).astype(np.float32),
            "point_features_t0": rng.random((n0, 2), np.float32), "flow_mps_t0": np.zeros((n0, 3), np.float32),
            "class_id_t0": np.full(n0, schema.CLASS_BACKGROUND, np.int32),
            "points_xyz_tm1_in_t0": rng.normal(size=(n1, 3)).astype(np.float32),
            "point_features_tm1": rng.random((n1, 2), np.float32), "pose_t0": np.eye(4), "pose_tm1": np.eye(4),
            "flow_mps_pseudo_t0": rng.normal(size=(n0, 3)).astype(np.float32),
            "pseudo_valid_t0": np.array([True, True, False, True, True]),
            "is_ground_t0": np.array([True, False, False, True, False]),
            "is_ground_tm1": np.array([False, True, True, False]),
            "category_t0": np.array([-1, 3, 3, 0, -1], np.int32),
            "instance_id_t0": np.array([-1, 0, 0, 1, -1], np.int32),
            "dynamic_cluster_t0": np.array([-2, -1, 0, 1, 1], np.int32),
            "dynamic_cluster_tm1": np.array([-1, 2, 2, 0], np.int32), pair_records.TIMESTAMP_KEY: 315966265259836000,
            pair_records.PARTNER_TIMESTAMP_KEY: 315966265360032000, pair_records.SEQUENCE_KEY: "log"}


def test_extras_round_trip_and_are_masked_and_padded_with_their_points(tiny_config, tmp_path):
    ex = _fake_pair()
    extras = schema.extra_point_keys(2)  # every extra of a pair's two clouds
    manifest = dataclasses.replace(write_records.wod_manifest(tiny_config), source="av2", extras=extras,
                                   partner="next")
    pair_records.write_manifest(str(tmp_path), manifest)
    path = str(tmp_path / ("log" + pair_records.FILE_SUFFIX))
    pair_records.write_records_atomically(path, [pair_records.serialize_pair(ex, extras=extras)])
    cfg = replace_config(_records_config(tiny_config), {"data.crop_to_grid": False})
    got = _numpy(pairs.pair_dataset([path], cfg, extras=extras, metadata=True))[0]
    for k in extras:
        np.testing.assert_array_equal(got[k], ex[k], err_msg=k)
    assert got[pair_records.TIMESTAMP_KEY] == 315966265259836000
    assert got[pair_records.PARTNER_TIMESTAMP_KEY] == 315966265360032000 and got[pair_records.SEQUENCE_KEY] == b"log"
    # Pseudo-labels train in place of the human flow; evaluation keeps the human flow.
    cfg_pseudo = replace_config(cfg, {"data.labels": "pseudo"})
    trained = _numpy(pairs.pair_dataset([path], cfg_pseudo, training_labels=True))[0]
    np.testing.assert_array_equal(trained["flow_mps_t0"], ex["flow_mps_pseudo_t0"])
    assert "flow_mps_pseudo_t0" not in trained
    np.testing.assert_array_equal(trained["pseudo_valid_t0"], ex["pseudo_valid_t0"])  # the loss skips the others
    scored = _numpy(pairs.pair_dataset([path], cfg_pseudo))[0]
    np.testing.assert_array_equal(scored["flow_mps_t0"], ex["flow_mps_t0"])
    # The ground-removal study drops the extras with their points; batches pad them (category -1 like class).
    cut = _numpy(pairs.pair_dataset([path], replace_config(cfg, {"data.remove_ground_below_z_m": 0.0}),
                                    extras=("category_t0", "is_ground_tm1")))[0]
    np.testing.assert_array_equal(cut["category_t0"], ex["category_t0"][ex["points_xyz_t0"][:, 2] >= 0.0])
    np.testing.assert_array_equal(cut["is_ground_tm1"], ex["is_ground_tm1"][ex["points_xyz_tm1_in_t0"][:, 2] >= 0.0])
    batch = next(iter(pairs.batch_examples(pairs.pair_dataset([path], cfg, extras=(
        "category_t0", "instance_id_t0", "is_ground_t0", "is_ground_tm1")), 1, 8)))
    np.testing.assert_array_equal(batch["instance_id_t0"].numpy()[0], [-1, 0, 0, 1, -1, -1, -1, -1])
    assert batch["category_t0"].shape == (1, 8) and batch["is_ground_tm1"].shape == batch["point_mask_tm1"].shape
    np.testing.assert_array_equal(batch["category_t0"].numpy()[0], [-1, 3, 3, 0, -1, -1, -1, -1])
    np.testing.assert_array_equal(batch["is_ground_t0"].numpy()[0, 5:], False)
