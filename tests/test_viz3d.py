"""The Rerun recording: written for two pairs, read back from the .rrd file (rerun.chunk.RrdReader) and compared with
what was logged: entity paths, time line, counts of points and arrows, positions, vectors, colours, transforms."""
import sys

import matplotlib
import numpy as np
import pytest

from ff3d_tf import geometry, schema, viz3d

RNG = np.random.default_rng(11)


def _pose(yaw, t):
    """4x4 vehicle -> world pose of a yaw rotation and a translation."""
    return geometry.box_matrices_np(t, yaw)[0]


def _pair(n0, n1):
    xyz = RNG.uniform(-20, 20, (n0, 3)).astype(np.float32)
    tm1 = RNG.uniform(-20, 20, (n1, 3)).astype(np.float32)
    flow = np.zeros((n0, 3), np.float32)
    flow[: n0 // 2] = RNG.normal(0, 5, (n0 // 2, 3))
    flow[0] = (0.3, 0.0, 0.0)  # below the 0.5 m/s arrow threshold
    flow[1] = (20.0, 0.0, 0.0)  # above the colour scale's top
    valid = RNG.random(n0) > 0.2
    valid[:2] = True
    return xyz, tm1, flow, valid


def test_recording_read_back_equals_what_was_logged(tmp_path):
    path = str(tmp_path / "flow.rrd")
    poses = {3: _pose(0.2, (100.0, 50.0, 2.0)), 4: _pose(0.35, (101.0, 50.5, 2.0))}
    pairs = {3: _pair(60, 45), 4: _pair(80, 70)}
    counts = {}
    with viz3d.FlowRecording(path) as rec:
        for sweep, (xyz, tm1, flow, valid) in pairs.items():
            counts[sweep] = rec.log_pair(sweep, xyz, tm1, flow, valid, poses[sweep])
    frames = viz3d.recording_frames(path)
    assert set(frames) == {viz3d.ENTITY_WORLD, viz3d.ENTITY_EGO, viz3d.ENTITY_POINTS_T0, viz3d.ENTITY_POINTS_TM1,
                           viz3d.ENTITY_FLOW}
    assert set(frames[viz3d.ENTITY_WORLD]) == {None}  # static: the view coordinates
    view = frames["world"][None]["ViewCoordinates:xyz"].reshape(-1)
    np.testing.assert_array_equal(view, [5, 4, 1])  # rerun's ViewDir: Forward, Left, Up
    for entity in (viz3d.ENTITY_EGO, viz3d.ENTITY_POINTS_T0, viz3d.ENTITY_POINTS_TM1, viz3d.ENTITY_FLOW):
        assert set(frames[entity]) == {3, 4}, entity  # one step of the `sweep` time line per pair
    for sweep, (xyz, tm1, flow, valid) in pairs.items():
        moving = valid & (np.linalg.norm(flow, axis=1) >= schema.MOVING_THRESHOLD_MPS)
        assert counts[sweep] == {"points_t0": len(xyz), "points_tm1": len(tm1), "arrows": int(moving.sum())}
        p0 = frames[viz3d.ENTITY_POINTS_T0][sweep]
        np.testing.assert_array_equal(p0["Points3D:positions"], xyz)
        colors = p0["Points3D:colors"]
        assert colors.shape == (len(xyz), 4) and np.all(colors[:, 3] == 255)
        np.testing.assert_array_equal(colors[~valid, :3], np.tile(viz3d.NO_PREDICTION_COLOR, ((~valid).sum(), 1)))
        # colour = matplotlib's turbo at speed / 15 m/s, clipped: 20 m/s gets the top colour
        speed = np.linalg.norm(flow.astype(np.float64), axis=1)
        turbo = matplotlib.colormaps["turbo"]
        want = np.round(np.array([turbo(min(s / 15.0, 1.0))[:3] for s in speed]) * 255).astype(np.uint8)
        np.testing.assert_array_equal(colors[valid, :3], want[valid])
        np.testing.assert_array_equal(colors[1, :3], np.round(np.array(turbo(1.0)[:3]) * 255).astype(np.uint8))
        p1 = frames[viz3d.ENTITY_POINTS_TM1][sweep]
        np.testing.assert_array_equal(p1["Points3D:positions"], tm1)
        np.testing.assert_array_equal(p1["Points3D:colors"][:, :3], np.tile(viz3d.TM1_COLOR, (len(tm1), 1)))
        arrows = frames[viz3d.ENTITY_FLOW][sweep]
        assert len(arrows["Arrows3D:origins"]) == moving.sum() and not moving[0] and moving[1]
        np.testing.assert_array_equal(arrows["Arrows3D:origins"], xyz[moving])
        np.testing.assert_allclose(arrows["Arrows3D:vectors"], flow[moving] * 0.1, rtol=1e-6)  # 0.1 s of motion
        np.testing.assert_array_equal(arrows["Arrows3D:colors"][:, :3], want[moving])
    # world = the vehicle frame of the first t0 sweep: identity there, inv(pose_3) @ pose_4 at the next sweep
    ego = frames[viz3d.ENTITY_EGO]
    np.testing.assert_allclose(ego[3]["Transform3D:translation"].reshape(3), 0.0, atol=1e-5)
    np.testing.assert_allclose(ego[3]["Transform3D:mat3x3"].reshape(3, 3), np.eye(3), atol=1e-6)
    rel = np.linalg.inv(poses[3]) @ poses[4]
    np.testing.assert_allclose(ego[4]["Transform3D:translation"].reshape(3), rel[:3, 3], atol=1e-5)
    np.testing.assert_allclose(ego[4]["Transform3D:mat3x3"].reshape(3, 3), rel[:3, :3], atol=1e-6)
    # by hand: yaw 0.15 rad between the two poses, ~1.05 m forward in the first frame's axes
    assert abs(np.arctan2(rel[1, 0], rel[0, 0]) - 0.15) < 1e-9


def test_without_poses_every_pair_stays_in_its_own_frame(tmp_path):
    path = str(tmp_path / "p.rrd")
    rec = viz3d.FlowRecording(path, arrow_seconds=1.0, min_arrow_speed_mps=0.0)
    xyz, tm1, flow, valid = _pair(10, 0)  # an empty t-1 cloud is fine
    for sweep in (1, 2):
        rec.log_pair(sweep, xyz, tm1, flow, valid)
    rec.close()
    frames = viz3d.recording_frames(path)
    for sweep in (1, 2):
        np.testing.assert_array_equal(frames[viz3d.ENTITY_EGO][sweep]["Transform3D:mat3x3"].reshape(3, 3), np.eye(3))
        arrows = frames[viz3d.ENTITY_FLOW][sweep]
        np.testing.assert_array_equal(arrows["Arrows3D:vectors"], flow[valid])  # every valid point, 1 s arrows
        assert frames[viz3d.ENTITY_POINTS_TM1][sweep]["Points3D:positions"].size == 0


def test_speed_colors_by_hand():
    c = viz3d.speed_colors(np.array([[0.0, 0, 0], [3.0, 4.0, 0.0], [100.0, 0, 0]]), np.array([True, True, False]))
    turbo = matplotlib.colormaps["turbo"]
    np.testing.assert_array_equal(c[0], np.round(np.array(turbo(0.0)[:3]) * 255))
    np.testing.assert_array_equal(c[1], np.round(np.array(turbo(5.0 / 15.0)[:3]) * 255))  # |(3, 4, 0)| = 5
    np.testing.assert_array_equal(c[2], viz3d.NO_PREDICTION_COLOR)


def test_missing_extra_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` now raises ImportError
    with pytest.raises(viz3d.Viz3dUnavailableError, match=r"viz3d extra \(rerun-sdk==0\.41\.0\)"):
        viz3d.FlowRecording(str(tmp_path / "x.rrd"))
    assert not (tmp_path / "x.rrd").exists()


def test_mismatched_lengths_are_refused(tmp_path):
    rec = viz3d.FlowRecording(str(tmp_path / "m.rrd"))
    with pytest.raises(ValueError, match="5 t0 points, 4 flows"):
        rec.log_pair(0, np.zeros((5, 3)), np.zeros((2, 3)), np.zeros((4, 3)), np.ones(5, bool))
    rec.close()
