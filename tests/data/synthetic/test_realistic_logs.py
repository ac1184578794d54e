"""Synthetic logs under the realistic profile, read back through the readers, each sensor feature checked against the
simulator's truth or an independent computation: per-point firing times (AV2 offset_ns), static points that stay on
their surfaces across sweeps within the range noise, moving points where their object was at their firing time,
labels that are the boxes' motion (Argoverse's rule; the paper's bootstrap on WOD), boxes that brake, the sloped
ground and its raster, and the tool's --realistic flag."""
import glob
import os
import subprocess
import sys

import numpy as np
import pyarrow.feather as feather
import pytest

from ff3d_tf import geometry
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.synthetic import av2 as sav2
from ff3d_tf.data.synthetic import files as synthetic_files
from ff3d_tf.data.synthetic import lidar, realism
from ff3d_tf.data.synthetic import wod as synthetic_wod
from ff3d_tf.data.wod import waymo
from ff3d_tf.labels.box_flow import bootstrap_flow

from conftest import ROOT

AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")
SWEEPS, POINTS, SEED = 12, 3000, 1
SIGMA = realism.REALISTIC.range_noise_std_m
FLOAT16_STEP_32M = 2.0 ** -6  # float16 spacing of coordinates in [16, 32) m: rounding is at most half of it


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    simulated = sav2.simulate_log(sav2.log_id_for(SEED, realism="realistic"), SWEEPS, seed=SEED,
                                  points_per_sweep=POINTS, realism="realistic")
    log_dir = sav2.write_log(simulated, str(tmp_path_factory.mktemp("av2r") / simulated.log_id))
    return simulated, log_dir


def _box_distance(points_world: np.ndarray, centre: np.ndarray, heading: float, size: np.ndarray) -> np.ndarray:
    """Signed distance (m) of world points to the surface of a yaw box: positive outside, negative inside."""
    c, s = np.cos(heading), np.sin(heading)
    rel = points_world - centre
    local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], -1)
    q = np.abs(local) - size / 2
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return np.where(q.max(axis=1) > 0, outside, q.max(axis=1))


def _world_points(simulated, log_dir, k):
    """Sweep k as stored, read by the reader and put in the simulator's world frame with the stored ego pose."""
    frame = argoverse2.read_sweep(log_dir, simulated.sweeps[k].timestamp_ns)
    city = geometry.transform_points_np(frame["points_xyz"], frame["pose"])
    return geometry.transform_points_np(city, np.linalg.inv(simulated.city_from_world)), frame


def test_reads_back_with_the_sample_schemas(log):
    simulated, log_dir = log
    real = glob.glob(os.path.join(AV2_LOG, "sensors", "lidar", "*.feather"))[0]
    ours = glob.glob(os.path.join(log_dir, "sensors", "lidar", "*.feather"))
    assert len(ours) == SWEEPS
    schema = [(f.name, str(f.type)) for f in feather.read_table(real).schema]
    assert [(f.name, str(f.type)) for f in feather.read_table(ours[0]).schema] == schema
    for name in ("annotations.feather", "city_SE3_egovehicle.feather", "flow_labels.feather"):
        assert ([(f.name, str(f.type)) for f in feather.read_table(os.path.join(log_dir, name)).schema] ==
                [(f.name, str(f.type)) for f in feather.read_table(os.path.join(AV2_LOG, name)).schema])
    counts = [len(argoverse2.read_sweep(log_dir, s.timestamp_ns)["points_xyz"]) for s in simulated.sweeps]
    assert all(0.8 * POINTS < c < 1.25 * POINTS for c in counts), counts  # about the wanted count, varying
    assert len(set(counts)) > 1


def test_offset_ns_is_each_points_firing_time(log):
    """offset_ns spans the 0.1 s sweep from its timestamp on (av2-api: offsets from the start of the sweep); for the
    up lidar (upright, turning clockwise seen from above) a point at ego azimuth a fired at (1 - a / pi) / 2 of the
    turn (hand formula), within the ego's motion over the sweep for points beyond 15 m."""
    simulated, log_dir = log
    for sweep in simulated.sweeps:
        offsets = feather.read_table(os.path.join(log_dir, "sensors", "lidar", f"{sweep.timestamp_ns}.feather")
                                     ).column("offset_ns").to_numpy()
        assert offsets.min() >= 0 and offsets.max() < sav2.SWEEP_PERIOD_NS
        assert offsets.min() < 0.05 * sav2.SWEEP_PERIOD_NS and offsets.max() > 0.95 * sav2.SWEEP_PERIOD_NS
        up = (sweep.laser_number < 32) & (np.hypot(*sweep.points_xyz[:, :2].astype(np.float64).T) > 15.0)
        azimuth = np.arctan2(sweep.points_xyz[up, 1].astype(np.float64), sweep.points_xyz[up, 0].astype(np.float64))
        expected = ((1.0 - azimuth / np.pi) / 2.0 % 1.0) * sav2.SWEEP_PERIOD_NS
        error = (offsets[up] - expected + sav2.SWEEP_PERIOD_NS / 2) % sav2.SWEEP_PERIOD_NS - sav2.SWEEP_PERIOD_NS / 2
        assert np.abs(error).max() < 0.03 * sav2.SWEEP_PERIOD_NS


def test_static_points_stay_on_their_surfaces_across_sweeps(log):
    """Points of poles, trunks, signs and buildings within 32 m, from every sweep, through the stored poses: each lies
    on its (static) surface within the range noise (a ray's error projects onto the face normal, so no more than the
    range error) plus float16 rounding; their spread is the noise's order, not zero."""
    simulated, log_dir = log
    distances = []
    for k, sweep in enumerate(simulated.sweeps):
        world, frame = _world_points(simulated, log_dir, k)
        near = np.linalg.norm(frame["points_xyz"], axis=1) < 30.0
        for i in np.unique(sweep.agent_index[sweep.agent_index >= 0]):
            agent = simulated.agents[i]
            if agent.moves() or agent.extinction_per_m > 0:
                continue
            sel = (sweep.agent_index == i) & near
            centre, heading = agent.pose(simulated.road, simulated.times_s[k])
            distances.append(_box_distance(world[sel], centre, heading, agent.size))
    d = np.concatenate(distances)
    assert len(d) > 200
    rounding = np.sqrt(3) * FLOAT16_STEP_32M / 2
    assert np.abs(d).max() < 5 * SIGMA + rounding
    assert 0.2 * SIGMA < d.std() < 1.1 * SIGMA + rounding


def test_moving_points_are_where_their_object_was_when_fired(log):
    """Each point of a moving object lies on the object's box at its own firing time (sweep timestamp + offset_ns)
    within noise and rounding; against the box at the sweep timestamp, fast objects' points on faces across their
    motion are off by their motion over the offset: motion distortion."""
    simulated, log_dir = log
    at_firing, at_stamp, shift = [], [], []
    for k, sweep in enumerate(simulated.sweeps):
        world, frame = _world_points(simulated, log_dir, k)
        near = np.linalg.norm(frame["points_xyz"], axis=1) < 30.0
        for i in np.unique(sweep.agent_index[sweep.agent_index >= 0]):
            agent = simulated.agents[i]
            sel = np.flatnonzero((sweep.agent_index == i) & near)
            if not agent.moves() or agent.material not in ("vehicle", "cyclist", "pedestrian") or not len(sel):
                continue
            fired = simulated.times_s[k] + sweep.offset_ns[sel] * 1e-9
            centres, headings = agent.poses(simulated.road, fired)
            at_firing += [_box_distance(world[j:j + 1], c, h, agent.size) for j, c, h in zip(sel, centres, headings)]
            centre, heading = agent.pose(simulated.road, simulated.times_s[k])
            at_stamp.append(_box_distance(world[sel], centre, heading, agent.size))
            shift.append(np.linalg.norm(centres - centre, axis=1))
    at_firing, at_stamp, shift = np.concatenate(at_firing), np.concatenate(at_stamp), np.concatenate(shift)
    assert len(at_firing) > 100
    assert np.abs(at_firing).max() < 5 * SIGMA + np.sqrt(3) * FLOAT16_STEP_32M / 2
    # Off the stamp's box: points of faces across the motion (the front and back of a vehicle) by about the shift.
    moved = shift > 0.3
    assert moved.sum() > 20 and (at_stamp[moved] > 0.1).sum() > 10 and at_stamp[moved].max() > 0.25


def test_flow_labels_are_the_cuboids_motion(log):
    """flow_labels.feather (Argoverse's convention) equals the paper's bootstrap from the stored cuboids with
    Argoverse's margin; the moving objects' points mostly lie in their enlarged cuboid despite the distortion."""
    simulated, log_dir = log
    stamps = argoverse2.sweep_timestamps(log_dir)
    f0, f1 = argoverse2.read_sweep(log_dir, stamps[0]), argoverse2.read_sweep(log_dir, stamps[1])
    dt = (stamps[1] - stamps[0]) * 1e-9
    flow, cls = bootstrap_flow(f0["points_xyz"], argoverse2.cuboids(log_dir, stamps[0]),
                               argoverse2.cuboids(log_dir, stamps[1]), f0["pose"], f1["pose"], dt,
                               enlarge_m=argoverse2.CUBOID_MARGIN_M)
    displacement, _ = argoverse2.argoverse_flow_in_paper_convention(log_dir)
    np.testing.assert_allclose(displacement, -flow * dt, atol=1e-5)  # the label is (p0 - p1) / dt
    classes = feather.read_table(os.path.join(log_dir, "flow_labels.feather")).column("classes").to_numpy()
    np.testing.assert_array_equal(classes > 0, cls != 0)
    assert (np.linalg.norm(displacement, axis=1) > 0.1).sum() > 30
    sweep = simulated.sweeps[0]
    rows = {r["track_uuid"]: r for r in sweep.cuboids}
    inside = total = 0
    for i in np.unique(sweep.agent_index[sweep.agent_index >= 0]):
        row = rows.get(simulated.track_uuids[i])
        if row is None or not simulated.agents[i].moves():
            continue
        sel = sweep.agent_index == i
        yaw = 2 * np.arctan2(row["qz"], row["qw"])
        inside += lidar.points_in_box(sweep.points_xyz[sel].astype(np.float64), np.array([row["tx_m"], row["ty_m"],
                                      row["tz_m"]]), yaw, np.array([row["length_m"], row["width_m"],
                                                                    row["height_m"]]),
                                      enlarge_m=argoverse2.CUBOID_MARGIN_M).sum()
        total += sel.sum()
    assert total > 50 and inside > 0.9 * total


def test_cuboids_brake_and_turn_with_their_objects(log):
    """From the stored cuboids and poses alone: some track's speed falls by more than 1 m/s over the log, some
    cuboid's heading turns, and vehicles, pedestrians and cyclists all move."""
    simulated, log_dir = log
    stamps = argoverse2.sweep_timestamps(log_dir)
    tracks: dict = {}
    for ts in stamps:
        pose = argoverse2.ego_pose(log_dir, ts)
        boxes = argoverse2.cuboids(log_dir, ts)
        for tid, centre, heading, cls in zip(boxes["track_id"], boxes["center"], boxes["heading"], boxes["class_id"]):
            yaw_city = heading + np.arctan2(pose[1, 0], pose[0, 0])
            tracks.setdefault(tid, []).append((ts, pose[:3, :3] @ centre + pose[:3, 3], yaw_city, cls))
    braking, moving_classes, turned = 0, set(), 0
    for rows in tracks.values():
        if len(rows) < 4:
            continue
        t = np.array([r[0] for r in rows]) * 1e-9
        c = np.array([r[1] for r in rows])
        speed = np.linalg.norm(np.diff(c[:, :2], axis=0), axis=1) / np.diff(t)
        if speed.max() > 0.5:
            moving_classes.add(int(rows[0][3]))
        braking += np.max(np.maximum.accumulate(speed) - speed) > 1.0
        turned += np.ptp(np.unwrap([r[2] for r in rows])) > np.deg2rad(3.0)
    assert braking >= 1 and turned >= 1 and {1, 2, 4} <= moving_classes, (braking, turned, moving_classes)


def test_sloped_ground_and_its_raster(log):
    """Ground points lie on the terrain within the noise; the map calls the ground points it covers ground (the road,
    sidewalks and side streets: most of them); the raster holds the terrain (float16), and the terrain is not a
    plane: over the raster's extent a plane fit in the world frame leaves residuals of more than 5 cm."""
    simulated, log_dir = log
    terrain = simulated.road.ground
    residual = []
    for k, sweep in enumerate(simulated.sweeps):
        world, frame = _world_points(simulated, log_dir, k)
        near = np.linalg.norm(frame["points_xyz"], axis=1) < 30.0
        on_ground = sweep.agent_index < 0
        residual.append(world[on_ground & near, 2] - terrain.height(world[on_ground & near, 0],
                                                                    world[on_ground & near, 1]))
        is_ground = argoverse2.is_ground(log_dir, frame["points_xyz"], frame["pose"])
        city = geometry.transform_points_np(frame["points_xyz"], frame["pose"])
        mapped = np.isfinite(argoverse2.ground_height_m(log_dir, city))
        assert mapped[on_ground].mean() > 0.8 and is_ground[on_ground & mapped].all()
    assert np.abs(np.concatenate(residual)).max() < 5 * SIGMA + FLOAT16_STEP_32M
    raster = argoverse2.read_ground_raster(log_dir)
    rows, cols = np.nonzero(np.isfinite(raster.height_m))
    pick = np.random.default_rng(0).choice(len(rows), 3000, replace=False)
    xy_city = (np.stack([cols[pick], rows[pick]], -1) + 0.5) / raster.scale - raster.translation
    heights = raster.height_m[rows[pick], cols[pick]].astype(np.float64)
    np.testing.assert_allclose(heights, simulated.ground_height_world_to_city(xy_city), atol=0.04)
    world = geometry.transform_points_np(np.column_stack([xy_city, heights]), np.linalg.inv(simulated.city_from_world))
    design = np.column_stack([world[:, 0], world[:, 1], np.ones(len(world))])
    plane = np.linalg.lstsq(design, world[:, 2], rcond=None)[0]
    assert np.std(world[:, 2] - design @ plane) > 0.05


def test_deterministic_for_a_seed(tmp_path):
    a = sav2.write_synthetic_log(str(tmp_path / "a"), num_sweeps=2, seed=3, points_per_sweep=600, realism="realistic")
    b = sav2.write_synthetic_log(str(tmp_path / "b"), num_sweeps=2, seed=3, points_per_sweep=600, realism="realistic")
    assert os.path.basename(a) == sav2.log_id_for(3, realism="realistic") != sav2.log_id_for(3)
    names = sorted(os.path.relpath(p, a) for p in glob.glob(os.path.join(a, "**", "*"), recursive=True)
                   if os.path.isfile(p))
    for name in names:
        with open(os.path.join(a, name), "rb") as f, open(os.path.join(b, name), "rb") as g:
            assert f.read() == g.read(), name


def test_wod_labels_are_the_bootstrap_of_its_laser_labels():
    """A realistic WOD segment: its flow images equal the paper's bootstrap (`bootstrap_flow`) from its own laser
    labels on the decoded points (float32 rounding aside), with moving vehicles labelled; the TOP pixel poses differ
    across columns (the ego moved within the spin)."""
    from waymo_open_dataset import dataset_pb2
    spec = synthetic_wod.SegmentSpec(seed=8, num_frames=3, lidar_scale=0.15, realism="realistic")
    previous = None
    moving = 0
    for record in synthetic_wod.generate_segment(spec):
        frame = waymo.decode_frame(record)
        boxes = synthetic_files.boxes_of_frame(dataset_pb2.Frame.FromString(record))
        if previous is not None:
            flow, cls = bootstrap_flow(frame["points_xyz"], boxes, previous[1], frame["pose"], previous[0]["pose"],
                                       0.1)
            np.testing.assert_array_equal(cls, frame["class_id"])
            np.testing.assert_allclose(flow, frame["flow_mps"], atol=1e-4)
            moving += int((np.linalg.norm(flow, axis=1)[cls == 1] > 1.0).sum())
        previous = (frame, boxes)
    assert moving > 20


def test_the_tool_writes_realistic_data(tmp_path):
    out = subprocess.run([sys.executable, "tools/make_synthetic_data.py", "--format", "av2", "--realistic", "--out_dir",
                          str(tmp_path), "--num_logs", "1", "--sweeps_per_log", "2", "--points_per_sweep", "500"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    (log_dir,) = glob.glob(os.path.join(tmp_path, "train", "*"))
    assert os.path.basename(log_dir) == sav2.log_id_for(0, 0, "realistic")
    assert len(argoverse2.sweep_timestamps(log_dir)) == 2


@pytest.mark.slow
def test_long_log_fills_a_long_history(tmp_path):
    """40 sweeps (the longest history full for nearly every example) read back in order at 10 Hz."""
    log_dir = sav2.write_synthetic_log(str(tmp_path), num_sweeps=40, seed=5, points_per_sweep=1500,
                                       realism="realistic")
    stamps = argoverse2.sweep_timestamps(log_dir)
    assert len(stamps) == 40 and np.all(np.abs(np.diff(stamps) - sav2.SWEEP_PERIOD_NS) <= sav2.SWEEP_JITTER_NS)
    assert all(len(argoverse2.read_sweep(log_dir, ts)["points_xyz"]) > 1000 for ts in stamps)
