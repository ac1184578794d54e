"""ff3d_tf.inference.predict_job: which pairs each input gives (the user's clouds with every study off, whatever the
config asks), and what `predict` writes. The tool as a user calls it: tests/tools/test_predict_own_clouds.py."""
import numpy as np
import pytest

from conftest import TINY_OVERRIDES
from ff3d_tf import geometry
from ff3d_tf.config import load_config, replace_config
from ff3d_tf.data.files.point_file_errors import PointFileError
from ff3d_tf.inference import predict_job

RNG = np.random.default_rng(4)
# Every study on, the crop on, ego motion left uncompensated: none of it may touch the user's clouds.
STUDIES_ON = {"data.crop_to_grid": True, "data.point_keep_fraction": 0.5, "data.remove_ground_below_z_m": 0.0,
              "data.class_ablation": "pedestrian_ignored", "data.ego_motion_compensation": False}


def _cloud(n):
    """n points in the tiny grid (x, y in [-40, 40) m; half of them below z = 0) and two outside it."""
    xyz = RNG.uniform([-35, -35, -2], [35, 35, 2], (n, 3))
    return np.concatenate([xyz, [[60.0, 0.0, 0.0], [0.0, 0.0, 9.0]]]).astype(np.float32)


def _sweeps_dir(path, sizes, poses=None):
    """A directory of .npy sweeps 000000.npy, ... (and their .pose.npy files); the clouds."""
    path.mkdir()
    clouds = [_cloud(n) for n in sizes]
    for k, cloud in enumerate(clouds):
        np.save(path / f"{k:06d}.npy", cloud)
        if poses is not None:
            np.save(path / f"{k:06d}.pose.npy", poses[k])
    (path / "notes.txt").write_text("not a sweep")
    return clouds


def test_sweeps_directory_pairs_every_point_moved_by_the_poses_with_studies_off(tmp_path):
    cfg = replace_config(load_config(None, TINY_OVERRIDES), STUDIES_ON)
    poses = [geometry.box_matrices_np((2.0 * k, 0.5 * k, 0.0), 0.1 * k)[0] for k in range(3)]
    clouds = _sweeps_dir(tmp_path / "log", (40, 50, 45), poses)
    lines = []
    found = list(predict_job.SweepsDirectory(str(tmp_path / "log")).pairs(cfg, lines.append))
    assert [(p.name, p.sweep_index) for p in found] == [("000001", 1), ("000002", 2)]
    assert f"{tmp_path / 'log'}: 3 sweeps, 2 pairs, poses given" in lines
    assert sum("no intensity column" in line for line in lines) == 1  # a remark once, not once per sweep
    for k, pair in zip((1, 2), found):
        ex = pair.example
        np.testing.assert_array_equal(ex["points_xyz_t0"], clouds[k])  # every point, in the file's order
        t0_from_tm1 = np.linalg.inv(poses[k]) @ poses[k - 1]
        moved = clouds[k - 1].astype(np.float64) @ t0_from_tm1[:3, :3].T + t0_from_tm1[:3, 3]
        np.testing.assert_allclose(ex["points_xyz_tm1_in_t0"], moved, atol=1e-4)  # compensated despite the config
        assert pair.batch["points_xyz_t0"].shape[0] == 1 and int(pair.batch["num_points_t0"][0]) == len(clouds[k])


def test_one_pair_without_poses_and_mismatched_poses(tmp_path):
    cfg = load_config(None, TINY_OVERRIDES)
    a, b = _cloud(30), _cloud(20)
    np.save(tmp_path / "a.npy", a)
    np.savez(tmp_path / "b.npz", points=b, intensity=np.full(len(b), 200, np.uint8))
    lines = []
    (pair,) = predict_job.PointFilePair(str(tmp_path / "a.npy"), str(tmp_path / "b.npz")).pairs(cfg, lines.append)
    assert (pair.name, pair.sweep_index) == ("b", 1)
    np.testing.assert_array_equal(pair.example["points_xyz_tm1_in_t0"], a)  # no poses: taken as in the t0 frame
    np.testing.assert_allclose(pair.example["point_features_t0"][:, 0], 200 / 255, rtol=1e-6)  # uint8: / 255
    assert any(line.startswith("no poses:") for line in lines)
    with pytest.raises(ValueError, match="go together"):
        predict_job.PointFilePair("a.npy", "b.npz", pose_tm1="p.txt")


def test_wod_segment_gives_a_pair_per_consecutive_frames(tiny_segment, tiny_config):
    found = list(predict_job.WodSegment(tiny_segment).pairs(tiny_config))
    assert [(p.name, p.sweep_index) for p in found] == [("frame_0000", 1), ("frame_0001", 2), ("frame_0002", 3)]
    assert all((p.example["class_id_t0"] >= 0).any() for p in found)  # the segment's labels come along


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """A checkpoint prefix of the tiny model with its initial weights."""
    import tensorflow as tf
    from ff3d_tf.model import build_model
    cfg = load_config(None, TINY_OVERRIDES)
    return tf.train.Checkpoint(model=build_model(cfg)).save(str(tmp_path_factory.mktemp("ckpt") / "ckpt"))


def test_predict_writes_each_pair_and_a_png_every_png_every_pairs(tiny_checkpoint, tmp_path):
    import pyarrow.feather as feather
    cfg = load_config(None, TINY_OVERRIDES)
    clouds = _sweeps_dir(tmp_path / "log", (30, 35, 25, 40))
    lines = []
    count = predict_job.predict(cfg, tiny_checkpoint, predict_job.SweepsDirectory(str(tmp_path / "log")),
                                str(tmp_path / "out"), png_every=2, log=lines.append)
    assert count == 3 and lines[-1] == f"wrote 3 frames to {tmp_path / 'out'}"
    for k in (1, 2, 3):
        stem = tmp_path / "out" / f"{k:06d}"
        with np.load(f"{stem}.npz") as z:
            flow, valid = z["flow_mps"], z["point_valid"]
            np.testing.assert_array_equal(z["points_xyz_t0"], clouds[k])
        assert flow.shape == (len(clouds[k]), 3) and valid[:-2].all() and not valid[-2:].any()
        np.testing.assert_array_equal(flow[-2:], 0.0)  # outside the grid: no prediction
        table = feather.read_table(f"{stem}.feather")
        np.testing.assert_array_equal(table["flow_x_mps"].to_numpy(), flow[:, 0])
        assert (tmp_path / "out" / f"{k:06d}_bev.png").exists() == (k in (1, 3))  # pairs 0 and 2
    assert not (tmp_path / "out" / "000000.npz").exists()  # the first sweep is only a t-1 cloud
    with pytest.raises(ValueError, match="png_every"):
        predict_job.predict(cfg, tiny_checkpoint, predict_job.SweepsDirectory(str(tmp_path / "log")),
                            str(tmp_path / "o2"), png_every=0)


def test_a_bad_point_file_fails_naming_it(tmp_path, tiny_checkpoint):
    bad = _cloud(10)
    bad[3, 2] = np.inf
    np.save(tmp_path / "a.npy", _cloud(10))
    np.save(tmp_path / "b.npy", bad)
    with pytest.raises(PointFileError, match="z: non-finite value inf at point 3"):
        predict_job.predict(load_config(None, TINY_OVERRIDES), tiny_checkpoint,
                            predict_job.PointFilePair(str(tmp_path / "a.npy"), str(tmp_path / "b.npy")),
                            str(tmp_path / "out"), log=lambda line: None)


def test_point_files_are_refused_for_a_model_that_drops_ground(tmp_path):
    """A `data.drop_ground` model reads no ground point of any sweep; point files carry no ground masks, so their
    pairs stop before any is read, saying what to do instead."""
    from ff3d_tf.config import ConfigError
    cfg = replace_config(load_config(None, list(TINY_OVERRIDES)), {"data.source": "pair_records",
                                                                   "data.drop_ground": True})
    _sweeps_dir(tmp_path / "sweeps", [50, 50])
    paths = [str(tmp_path / "sweeps" / f"{k:06d}.npy") for k in range(2)]
    with pytest.raises(ConfigError, match=r"data.drop_ground=true.*point files carry no ground masks.*"
                                          r"tools/add_ground_masks.py"):
        next(predict_job._user_cloud_pairs(paths, None, None, cfg, print, [0, 100_000_000], [], "previous"))
