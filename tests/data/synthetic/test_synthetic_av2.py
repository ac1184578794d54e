"""Synthetic Argoverse 2 logs: the real sample's layout and schemas, read back by the AV2 reader, points on their
cuboids and moving with them, the ground raster under the ground points, determinism."""
import filecmp
import glob
import json
import os
import re

import numpy as np
import pyarrow.feather as feather
import pytest

from ff3d_tf import schema
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.synthetic import av2 as sav2
from ff3d_tf.data.synthetic import scene as sim

from conftest import ROOT
AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")
NUM_SWEEPS, POINTS = 4, 4000
FLOAT16_TOL_M = 0.04  # half a float16 step at 64-128 m is 0.031 m: stored points sit this close to their surface


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    simulated = sav2.simulate_log(sav2.log_id_for(3), NUM_SWEEPS, seed=3, points_per_sweep=POINTS)
    log_dir = sav2.write_log(simulated, str(tmp_path_factory.mktemp("av2") / simulated.log_id))
    return simulated, log_dir


def _schema(path):
    return [(f.name, str(f.type)) for f in feather.read_table(path).schema]


def _cuboid_local(points, box):
    """Points [N, 3] in the frame of a yaw-only cuboid row (qx = qy = 0)."""
    yaw = 2 * np.arctan2(box["qz"], box["qw"])
    d = points - [box["tx_m"], box["ty_m"], box["tz_m"]]
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)


def _box_matrix(box):
    m = np.eye(4)
    yaw = 2 * np.arctan2(box["qz"], box["qw"])
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:3, 3] = box["tx_m"], box["ty_m"], box["tz_m"]
    return m


def _rows(log_dir):
    rows = feather.read_table(os.path.join(log_dir, "annotations.feather")).to_pylist()
    return {(r["timestamp_ns"], r["track_uuid"]): r for r in rows}


def test_layout_and_schemas_match_the_real_sample(log):
    simulated, log_dir = log
    real_lidar = glob.glob(os.path.join(AV2_LOG, "sensors", "lidar", "*.feather"))[0]
    ours_lidar = glob.glob(os.path.join(log_dir, "sensors", "lidar", "*.feather"))
    assert len(ours_lidar) == NUM_SWEEPS and all(re.fullmatch(r"\d{18}\.feather", os.path.basename(p))
                                                 for p in ours_lidar)
    assert _schema(ours_lidar[0]) == _schema(real_lidar)
    assert [t for _, t in _schema(real_lidar)] == ["halffloat"] * 3 + ["uint8", "uint8", "int32"]
    for name in ("annotations.feather", "city_SE3_egovehicle.feather", "flow_labels.feather",
                 os.path.join("calibration", "egovehicle_SE3_sensor.feather")):
        assert _schema(os.path.join(log_dir, name)) == _schema(os.path.join(AV2_LOG, name)), name
    # Map files named as AV2 names them (log id, city), the raster float16 2-D, the Sim(2) json with R, t, s.
    names = sorted(os.listdir(os.path.join(log_dir, "map")))
    lid, city = simulated.log_id, simulated.city
    assert names[0] == f"{lid}___img_Sim2_city.json" and names[1] == f"{lid}_ground_height_surface____{city}.npy"
    assert re.fullmatch(rf"log_map_archive_{lid}____{city}_city_\d+\.json", names[2])
    real_npy = np.load(glob.glob(os.path.join(AV2_LOG, "map", "*.npy"))[0])
    ours_npy = np.load(os.path.join(log_dir, "map", names[1]))
    assert ours_npy.dtype == real_npy.dtype == np.float16 and ours_npy.ndim == 2
    with open(os.path.join(log_dir, "map", names[0])) as f, \
            open(glob.glob(os.path.join(AV2_LOG, "map", "*Sim2*"))[0]) as g:
        ours_sim2, real_sim2 = json.load(f), json.load(g)
    assert sorted(ours_sim2) == sorted(real_sim2) and ours_sim2["R"] == real_sim2["R"]
    assert ours_sim2["s"] == pytest.approx(real_sim2["s"])
    with open(os.path.join(log_dir, "map", names[2])) as f:
        vector_map = json.load(f)
    with open(glob.glob(os.path.join(AV2_LOG, "map", "log_map_archive_*"))[0]) as g:
        real_map = json.load(g)
    assert sorted(vector_map) == sorted(real_map)
    lane, real_lane = next(iter(vector_map["lane_segments"].values())), next(iter(real_map["lane_segments"].values()))
    assert sorted(lane) == sorted(real_lane) and len(vector_map["lane_segments"]) > 8
    # Ego poses at every sweep timestamp and between them; no pose row repeated.
    stamps = feather.read_table(os.path.join(log_dir, "city_SE3_egovehicle.feather")).column("timestamp_ns")
    stamps = stamps.to_numpy()
    assert np.all(np.diff(stamps) > 0) and set(argoverse2.sweep_timestamps(log_dir)) <= set(stamps.tolist())
    assert len(stamps) > 5 * NUM_SWEEPS


def test_reads_back_through_the_av2_reader(log):
    simulated, log_dir = log
    stamps = argoverse2.sweep_timestamps(log_dir)
    assert stamps == [s.timestamp_ns for s in simulated.sweeps]
    steps = np.diff(stamps)
    assert np.all(np.abs(steps - 100_000_000) <= sav2.SWEEP_JITTER_NS)  # 10 Hz
    moving = {c: 0 for c in (schema.CLASS_VEHICLE, schema.CLASS_PEDESTRIAN, schema.CLASS_CYCLIST)}
    for k, (ts, sweep) in enumerate(zip(stamps, simulated.sweeps)):
        frame = argoverse2.read_sweep(log_dir, ts)
        assert len(frame["points_xyz"]) == POINTS
        np.testing.assert_array_equal(frame["points_xyz"], sweep.points_xyz.astype(np.float32))
        np.testing.assert_allclose(frame["pose"], simulated.city_from_ego(k), atol=1e-9)
        # Both lidars return: laser names 1 (lasers 0-31) and 2 (32-63).
        assert set(np.unique(frame["laser_name"]).tolist()) == {1, 2}
        boxes = argoverse2.cuboids(log_dir, ts)
        assert len(boxes["center"]) == len(sweep.cuboids) > 20
        assert set(boxes["class_id"].tolist()) <= set(sav2.CATEGORY_OF_CLASS)
        for i in np.unique(sweep.agent_index[sweep.agent_index >= 0]):
            agent = simulated.agents[i]
            if agent.speed != 0 and simulated.track_uuids[i] in boxes["track_id"] and agent.class_id in moving:
                moving[agent.class_id] += 1
    assert all(moving.values()), moving  # moving vehicles, pedestrians and cyclists with points in every log
    for class_id, category in sav2.CATEGORY_OF_CLASS.items():
        assert argoverse2.AV2_CLASS[category] == class_id


def test_object_points_lie_on_their_cuboids(log):
    """Every point of a labelled object, as stored (float16) and with its cuboid as stored, is inside the cuboid and
    on one of its faces."""
    simulated, log_dir = log
    rows = _rows(log_dir)
    checked = 0
    for k, sweep in enumerate(simulated.sweeps):
        p = argoverse2.read_sweep(log_dir, sweep.timestamp_ns)["points_xyz"].astype(np.float64)
        for i in np.unique(sweep.agent_index[sweep.agent_index >= 0]):
            box = rows.get((sweep.timestamp_ns, simulated.track_uuids[i]))
            if box is None:  # only unlabelled structures (poles, buildings) and objects beyond the label range
                agent = simulated.agents[i]
                centre = agent.pose(simulated.road, simulated.times_s[k])[0]
                far = np.linalg.norm(centre[:2] - simulated.world_from_ego[k, :2, 3]) > sim.LABEL_RANGE_M
                assert not agent.labelled or agent.class_id == 0 or far
                continue
            sel = sweep.agent_index == i
            local = _cuboid_local(p[sel], box)
            half = np.array([box["length_m"], box["width_m"], box["height_m"]]) / 2
            assert np.all(np.abs(local) <= half + FLOAT16_TOL_M)
            assert np.all(np.max(np.abs(local) - half, axis=1) >= -FLOAT16_TOL_M)  # on a face
            assert box["num_interior_pts"] == sel.sum()
            checked += sel.sum()
    assert checked > 1000


def test_points_move_with_their_cuboids(log):
    """Sweep-0 points moved by the flow labels land where the cuboid's motion (annotations and poses as stored)
    takes them; every sweep's object points moved by the cuboid's motion to the next sweep lie on the next cuboid;
    background points move with the ego motion only."""
    simulated, log_dir = log
    stamps = argoverse2.sweep_timestamps(log_dir)
    rows = _rows(log_dir)
    labels = feather.read_table(os.path.join(log_dir, "flow_labels.feather"))
    flow = np.stack([labels.column(c).to_numpy() for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m")], -1)
    s0 = simulated.sweeps[0]
    p0 = argoverse2.read_sweep(log_dir, stamps[0])["points_xyz"].astype(np.float64)
    pose0, pose1 = argoverse2.ego_pose(log_dir, stamps[0]), argoverse2.ego_pose(log_dir, stamps[1])
    moved_objects = 0
    for i in np.unique(s0.agent_index[s0.agent_index >= 0]):
        b0, b1 = rows.get((stamps[0], simulated.track_uuids[i])), rows.get((stamps[1], simulated.track_uuids[i]))
        if b0 is None or b1 is None:
            continue
        sel = s0.agent_index == i
        # Same coordinates in the cuboid frame before and after: a rigid motion with the cuboid.
        np.testing.assert_allclose(_cuboid_local(p0[sel] + flow[sel], b1), _cuboid_local(p0[sel], b0), atol=1e-4)
        category = argoverse2.scene_flow_category_index(b0["category"])
        assert np.all(labels.column("classes").to_numpy()[sel] == category)
        moved_objects += simulated.agents[i].speed != 0
    assert moved_objects > 3
    background = s0.agent_index < 0
    ego1_from_ego0 = np.linalg.inv(pose1) @ pose0
    rigid = p0 @ ego1_from_ego0[:3, :3].T + ego1_from_ego0[:3, 3] - p0
    np.testing.assert_allclose(flow[background], rigid[background], atol=1e-4)
    assert not labels.column("dynamic").to_numpy()[background].any()
    # Sweep k -> k + 1 for every k: each cuboid as stored (annotation row + ego pose) is the agent's true box, and
    # it moved by about the agent's speed over the interval. With the points of every sweep on their cuboid's faces
    # (test_object_points_lie_on_their_cuboids), the points of sweep k, carried by the cuboid's motion, lie on the
    # same faces of cuboid k + 1 as the points of sweep k + 1.
    times = simulated.times_s
    moving = 0
    for k in range(NUM_SWEEPS - 1):
        city = [argoverse2.ego_pose(log_dir, stamps[k + j]) for j in (0, 1)]
        for i, agent in enumerate(simulated.agents):
            b = [rows.get((stamps[k + j], simulated.track_uuids[i])) for j in (0, 1)]
            if b[0] is None or b[1] is None:
                continue
            box_city = [city[j] @ _box_matrix(b[j]) for j in (0, 1)]
            for j in (0, 1):
                centre_w, heading_w = agent.pose(simulated.road, times[k + j])
                truth = np.eye(4)
                truth[:2, :2] = [[np.cos(heading_w), -np.sin(heading_w)], [np.sin(heading_w), np.cos(heading_w)]]
                truth[:3, 3] = centre_w
                np.testing.assert_allclose(box_city[j], simulated.city_from_world @ truth, atol=1e-6)
            # The speed is along the centreline; at lateral offset d on a curve (radius >= 35 m, synthetic_scene.Road)
            # the path is up to |d| / 35 longer or shorter.
            shift = np.linalg.norm(box_city[1][:3, 3] - box_city[0][:3, 3])
            along = abs(agent.speed) * (times[k + 1] - times[k])
            assert along * (1 - abs(agent.d) / 35) - 1e-6 <= shift <= along * (1 + abs(agent.d) / 35) + 1e-6
            moving += shift > 0.05
    assert moving > 10


def test_ground_raster_marks_ground_and_not_objects(log):
    simulated, log_dir = log
    for k, sweep in enumerate(simulated.sweeps):
        frame = argoverse2.read_sweep(log_dir, sweep.timestamp_ns)
        ground = argoverse2.is_ground(log_dir, frame["points_xyz"], frame["pose"])
        city = frame["points_xyz"].astype(np.float64) @ frame["pose"][:3, :3].T + frame["pose"][:3, 3]
        height = argoverse2.ground_height_m(log_dir, city)
        on_ground = sweep.agent_index < 0
        mapped = np.isfinite(height)
        assert on_ground.sum() > 300 and mapped[on_ground].mean() > 0.8
        assert ground[on_ground & mapped].all()
        assert not ground[~mapped].any()  # no ground height, never ground (av2's rule)
        # The raster holds the tilted world plane: exact height within float16 rounding and the cell's slope.
        exact = simulated.ground_height_world_to_city(city[mapped, :2])
        np.testing.assert_allclose(height[mapped], exact, atol=0.03)
        # Object points more than 0.35 m above the ground are not ground; those within 0.25 m are (av2's 0.3 m).
        above = sweep.points_world[:, 2]
        assert not ground[~on_ground & (above > 0.35)].any() and (~on_ground & (above > 0.35)).sum() > 1000
        low = ~on_ground & (above < 0.25) & mapped
        assert ground[low].all()
        if k == 0:
            labels = feather.read_table(os.path.join(log_dir, "flow_labels.feather"))
            np.testing.assert_array_equal(labels.column("is_ground_0").to_numpy(), ground)
    # The raster's slope is real: the city frame is tilted, so the ground height varies across the log.
    raster = argoverse2.read_ground_raster(log_dir).height_m
    assert np.nanmax(raster) - np.nanmin(raster) > 0.2


def test_deterministic_for_a_seed(tmp_path):
    a = sav2.write_synthetic_log(str(tmp_path / "a"), num_sweeps=2, seed=11, points_per_sweep=800)
    b = sav2.write_synthetic_log(str(tmp_path / "b"), num_sweeps=2, seed=11, points_per_sweep=800)
    c = sav2.write_synthetic_log(str(tmp_path / "c"), num_sweeps=2, seed=12, points_per_sweep=800)
    files = sorted(os.path.relpath(p, a) for p in glob.glob(os.path.join(a, "**", "*"), recursive=True)
                   if os.path.isfile(p))
    assert len(files) == 9 and os.path.basename(a) == os.path.basename(b) == sav2.log_id_for(11)
    match, mismatch, errors = filecmp.cmpfiles(a, b, files, shallow=False)
    assert not mismatch and not errors and len(match) == len(files)
    ts_a, ts_c = argoverse2.sweep_timestamps(a), argoverse2.sweep_timestamps(c)
    pa, pc = argoverse2.read_sweep(a, ts_a[0])["points_xyz"], argoverse2.read_sweep(c, ts_c[0])["points_xyz"]
    assert len(pa) == len(pc) == 800 and not np.array_equal(pa, pc)


def test_split_layout_is_resumable(tmp_path):
    seen = []
    dirs = sav2.write_synthetic_split(str(tmp_path), 2, split="val", num_sweeps=2, seed=5, points_per_sweep=500,
                                      progress=lambda k, n, d, skipped: seen.append((k, n, skipped)))
    assert [os.path.relpath(d, tmp_path) for d in dirs] == [os.path.join("val", sav2.log_id_for(5, k))
                                                            for k in range(2)]
    assert seen == [(0, 2, False), (1, 2, False)] and len(set(dirs)) == 2
    for d in dirs:
        assert len(argoverse2.sweep_timestamps(d)) == 2
    stamp = os.stat(os.path.join(dirs[0], "annotations.feather")).st_mtime_ns
    seen.clear()
    assert sav2.write_synthetic_split(str(tmp_path), 2, split="val", num_sweeps=2, seed=5, points_per_sweep=500,
                                      progress=lambda k, n, d, skipped: seen.append(skipped)) == dirs
    assert seen == [True, True] and os.stat(os.path.join(dirs[0], "annotations.feather")).st_mtime_ns == stamp
    assert not glob.glob(os.path.join(tmp_path, "val", "*.partial"))
    with pytest.raises(ValueError, match="positive"):
        sav2.simulate_log("x", num_sweeps=0)
