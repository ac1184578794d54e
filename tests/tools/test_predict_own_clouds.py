"""tools/predict.py on a user's own clouds (a sweeps directory of three formats with poses, a pair without poses),
as a user calls it, against the model run here on the same points moved by NumPy; the Rerun recording read back."""
import os
import struct
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, TINY_OVERRIDES
from ff3d_tf import geometry

RNG = np.random.default_rng(21)


def _pose(yaw, t):
    """4x4 vehicle -> world pose of a yaw rotation and a translation."""
    return geometry.box_matrices_np(t, yaw)[0]


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """(checkpoint prefix of the tiny model with its initial (Glorot) weights, that model restored from it as a
    `ModelPredictor`): no training needed to check the plumbing, and the flows are far from zero."""
    import tensorflow as tf
    from ff3d_tf.checkpoints import restore_model
    from ff3d_tf.config import load_config
    from ff3d_tf.model import build_model
    from ff3d_tf.model.forward import ModelPredictor
    cfg = load_config(None, TINY_OVERRIDES)
    prefix = tf.train.Checkpoint(model=build_model(cfg)).save(str(tmp_path_factory.mktemp("ckpt") / "ckpt"))
    return prefix, ModelPredictor(restore_model(cfg, prefix))


def _run(*args):
    sets = [a for s in TINY_OVERRIDES for a in ("--set", s)]
    return subprocess.run([sys.executable, "tools/predict.py", "--config", "", *sets, *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


def _reference(predictor, xyz_t0, intensity_t0, xyz_tm1, intensity_tm1, t0_from_tm1):
    """The model's flow on the pair built here: t-1 points moved by NumPy, features (intensity, elongation 0)."""
    import tensorflow as tf
    moved = xyz_tm1.astype(np.float64) @ t0_from_tm1[:3, :3].T + t0_from_tm1[:3, 3]

    def cloud(xyz, intensity):
        feats = np.stack([intensity, np.zeros_like(intensity)], -1).astype(np.float32)
        return tf.constant(xyz[None].astype(np.float32)), tf.constant(feats[None]), tf.ones([1, len(xyz)], tf.bool)

    p0, f0, m0 = cloud(xyz_t0, intensity_t0)
    p1, f1, m1 = cloud(moved, intensity_tm1)
    batch = {"points_xyz_t0": p0, "point_features_t0": f0, "point_mask_t0": m0, "points_xyz_tm1_in_t0": p1,
             "point_features_tm1": f1, "point_mask_tm1": m1}
    return predictor.predict(batch, {"num_points_t0": len(xyz_t0)})


def _scene(n):
    """Points in the tiny grid (x, y in [-40, 40) m, z in [-3, 3] m) and three outside it."""
    xyz = np.concatenate([RNG.uniform([-35, -35, -2], [35, 35, 2], (n, 3)),
                          [[60.0, 0.0, 0.0], [0.0, -45.0, 0.0], [5.0, 5.0, 9.0]]]).astype(np.float32)
    return xyz


def test_sweeps_directory_with_poses_and_rerun(tiny_checkpoint, tmp_path):
    from ff3d_tf import viz3d
    import pyarrow.feather as feather
    prefix, predictor = tiny_checkpoint
    d = tmp_path / "log"
    d.mkdir()
    clouds = [_scene(n) for n in (150, 170, 160)]
    intensity_f = [RNG.uniform(0, 1, len(c)).astype(np.float32) for c in clouds]
    intensity_u8 = RNG.integers(0, 256, len(clouds[1])).astype(np.uint8)
    poses = [_pose(0.05 * k, (1.0 * k, 0.2 * k, 0.0)) for k in range(3)]
    # 000000.bin: KITTI float32 x, y, z, intensity
    (d / "000000.bin").write_bytes(np.concatenate([clouds[0], intensity_f[0][:, None]], 1).astype("<f4").tobytes())
    # 000001.pcd: binary PCD, intensity as uint8 (auto scale: / 255), an extra field
    n1 = len(clouds[1])
    head = (f"VERSION 0.7\nFIELDS x y z intensity ring\nSIZE 4 4 4 1 2\nTYPE F F F U U\nCOUNT 1 1 1 1 1\n"
            f"WIDTH {n1}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n1}\nDATA binary\n").encode()
    (d / "000001.pcd").write_bytes(head + b"".join(struct.pack("<fffBH", *clouds[1][i], int(intensity_u8[i]), i % 32)
                                                   for i in range(n1)))
    # 000002.ply: binary big-endian PLY, float intensity
    n2 = len(clouds[2])
    head = (f"ply\nformat binary_big_endian 1.0\nelement vertex {n2}\nproperty float x\nproperty float y\n"
            "property float z\nproperty float intensity\nend_header\n").encode()
    (d / "000002.ply").write_bytes(head + np.concatenate([clouds[2], intensity_f[2][:, None]], 1).astype(">f4")
                                   .tobytes())
    (d / "poses.txt").write_text("".join(" ".join(repr(float(v)) for v in p[:3].reshape(-1)) + "\n" for p in poses))
    out, rrd = tmp_path / "out", tmp_path / "out" / "flow.rrd"
    run = _run("--checkpoint", prefix, "--sweeps_dir", str(d), "--out_dir", str(out), "--rerun", str(rrd))
    assert run.returncode == 0, run.stderr[-3000:]
    assert "3 sweeps, 2 pairs, poses given" in run.stdout
    assert f"{d / '000001.pcd'}: intensity stored as uint8, multiplied by 0.00392157" in run.stdout
    assert f"{d / '000001.pcd'}: columns not used: ring" in run.stdout
    intensities = [intensity_f[0], intensity_u8 / 255.0, intensity_f[2]]
    frames = viz3d.recording_frames(str(rrd))
    for k, stem in ((1, "000001"), (2, "000002")):
        with np.load(out / f"{stem}.npz") as z:
            flow, valid = z["flow_mps"], z["point_valid"]
            np.testing.assert_array_equal(z["points_xyz_t0"], clouds[k])  # every point of the file, in its order
        assert flow.shape == (len(clouds[k]), 3) and flow.dtype == np.float32
        assert not valid[-3:].any() and np.all(flow[-3:] == 0) and valid[:-3].all()  # the 3 outside the grid
        want_flow, want_valid = _reference(predictor, clouds[k], intensities[k], clouds[k - 1], intensities[k - 1],
                                           np.linalg.inv(poses[k]) @ poses[k - 1])
        np.testing.assert_array_equal(valid, want_valid)
        np.testing.assert_allclose(flow, want_flow, atol=1e-4)
        assert np.abs(flow[valid]).max() > 0.1  # initial weights: a real, non-zero flow
        t = feather.read_table(out / f"{stem}.feather")
        np.testing.assert_array_equal(np.stack([t["flow_x_mps"], t["flow_y_mps"], t["flow_z_mps"]], -1), flow)
        np.testing.assert_array_equal(t["point_valid"].to_numpy(zero_copy_only=False), valid)
        assert (out / f"{stem}_bev.png").exists() == (k == 1)  # a PNG every --png_every (10) pairs, first included
        # the recording at this sweep: both clouds, the arrows of moving points, the ego pose in the first frame
        moving = valid & (np.linalg.norm(flow, axis=1) >= 0.5)
        np.testing.assert_array_equal(frames[viz3d.ENTITY_POINTS_T0][k]["Points3D:positions"], clouds[k])
        moved = clouds[k - 1].astype(np.float64) @ (np.linalg.inv(poses[k]) @ poses[k - 1])[:3, :3].T + \
            (np.linalg.inv(poses[k]) @ poses[k - 1])[:3, 3]
        np.testing.assert_allclose(frames[viz3d.ENTITY_POINTS_TM1][k]["Points3D:positions"], moved, atol=1e-4)
        arrows = frames[viz3d.ENTITY_FLOW][k]
        assert len(arrows["Arrows3D:origins"]) == moving.sum() > 0
        np.testing.assert_allclose(arrows["Arrows3D:vectors"], flow[moving] * 0.1, rtol=1e-6)
        rel = np.linalg.inv(poses[1]) @ poses[k]
        np.testing.assert_allclose(frames[viz3d.ENTITY_EGO][k]["Transform3D:translation"].reshape(3), rel[:3, 3],
                                   atol=1e-5)
    assert not (out / "000000.npz").exists()  # the first sweep is only a t-1 cloud
    assert (out / "000001_bev.png").stat().st_size > 10000


@pytest.mark.slow
def test_one_pair_without_poses(tiny_checkpoint, tmp_path):
    prefix, predictor = tiny_checkpoint
    xyz_tm1, xyz_t0 = _scene(90), _scene(100)
    intensity = RNG.uniform(0, 2, len(xyz_t0)).astype(np.float32)
    np.save(tmp_path / "a.npy", xyz_tm1)
    np.savez(tmp_path / "b.npz", points=xyz_t0, intensity=intensity)
    run = _run("--checkpoint", prefix, "--points_tm1", str(tmp_path / "a.npy"), "--points_t0",
               str(tmp_path / "b.npz"), "--out_dir", str(tmp_path / "out"), "--intensity_scale", "1/2")
    assert run.returncode == 0, run.stderr[-3000:]
    assert "no poses: the t-1 cloud of each pair is taken as already in the t0 vehicle frame" in run.stdout
    assert "a.npy: no intensity column" in run.stdout
    with np.load(tmp_path / "out" / "b.npz") as z:
        flow, valid = z["flow_mps"], z["point_valid"]
    want_flow, want_valid = _reference(predictor, xyz_t0, intensity * 0.5, xyz_tm1, np.zeros(len(xyz_tm1)), np.eye(4))
    np.testing.assert_array_equal(valid, want_valid)
    np.testing.assert_allclose(flow, want_flow, atol=1e-4)
    assert (tmp_path / "out" / "b_bev.png").exists() and (tmp_path / "out" / "b.feather").exists()
    # flags that do not go together fail before any work
    run = _run("--checkpoint", prefix, "--points_t0", str(tmp_path / "b.npz"), "--out_dir", str(tmp_path / "o2"))
    assert run.returncode == 2 and "--points_t0 and --points_tm1 go together" in run.stderr
    assert not os.path.exists(tmp_path / "o2")


def test_a_bad_file_stops_the_tool_naming_it(tmp_path):
    bad = _scene(20)
    bad[7, 1] = np.nan
    np.save(tmp_path / "bad.npy", bad)
    np.save(tmp_path / "a.npy", _scene(20))
    # a NaN in the t0 file: the tool stops with the file, the field and the point, before it loads the model (the
    # checkpoint does not even exist)
    run = _run("--checkpoint", str(tmp_path / "no_such_checkpoint"), "--points_tm1", str(tmp_path / "a.npy"),
               "--points_t0", str(tmp_path / "bad.npy"), "--out_dir", str(tmp_path / "out"))
    assert run.returncode == 1
    assert f"error: {tmp_path / 'bad.npy'}: y: non-finite value nan at point 7" in run.stderr, run.stderr[-2000:]
