"""Synthetic Argoverse 2 sensor logs: the street world of `ff3d_tf.data.synthetic.scene` written in AV2's layout.

One log directory, as the AV2 Sensor Dataset lays it out (file names, Feather columns, dtypes and LZ4 compression as
the sample log `data/av2_sample_log` has them):

    <log_id>/sensors/lidar/<timestamp_ns>.feather   x, y, z float16 (ego frame, metres), intensity uint8,
                                                    laser_number uint8 (0-31 up lidar, 32-63 down lidar),
                                                    offset_ns int32
    <log_id>/annotations.feather                    cuboids per sweep (ego frame of the sweep, quaternion rotation)
    <log_id>/city_SE3_egovehicle.feather            ego -> city pose at every sweep and every 10 ms between
    <log_id>/calibration/egovehicle_SE3_sensor.feather   the two lidars' mountings (there are no cameras)
    <log_id>/map/<log_id>_ground_height_surface____<CITY>.npy   float16 ground height, 30 cm cells, NaN off the ROI
    <log_id>/map/<log_id>___img_Sim2_city.json      {"R", "t", "s"}: city -> raster pixel
    <log_id>/map/log_map_archive_<log_id>____<CITY>_city_<n>.json   vector map: lanes and the drivable area
    <log_id>/flow_labels.feather                    sweep 0's flow to sweep 1 in Argoverse's convention (as the sample)

The world: `synthetic_scene.make_scene` (curved road, moving and parked vehicles, pedestrians, cyclists, signs, poles,
buildings; flat ground at world z = 0) seen by two 32-beam lidars stacked as in AV2 (the down lidar upside down),
each ray cast at the sweep time with `synthetic_scene.scan`: AV2 sweeps are motion-compensated to their timestamp, so
every point is where its surface was at the sweep time. The city frame is the world moved, turned and tilted by up to
1.5 degrees per seed, so ego poses carry pitch and roll and the ground raster slopes; the ego frame's origin is
EGO_ORIGIN_HEIGHT_M above the ground (the sample log's ego origin is 0.32 m above its raster).

Flow labels come from the simulator's own kinematics (the exact rigid motion of the surface each ray hit, not a
cuboid test): f = (the point at sweep 1, in the sweep-1 ego frame) - (the point at sweep 0), float32 as Argoverse
stores it; `classes` is the category index of the labelled object hit (`argoverse2.scene_flow_category_index`),
`dynamic` and `is_ground_0` follow Argoverse's rules (`argoverse2.SCENE_FLOW_DYNAMIC_THRESHOLD_M`,
`argoverse2.is_ground`).

That is the default profile (`realism.IDEAL`). Under another (`simulate_log(..., realism="realistic")`, the tool's
`--realistic`; `synthetic.av2_sweeps`): the profile's world (the city of `synthetic.city`: its ground a height field,
which the raster holds, the side streets in the ROI), every ray fired at its point's offset_ns after the sweep
timestamp from the ego pose then, against the world then, measured with noise and dropped returns, and written
ego-motion compensated as Argoverse 2 writes sweeps; each sweep holds all its returns (about `points_per_sweep`); the
cuboids are where the up lidar swept over each object, grown by the profile's margin; the flow labels follow
Argoverse's cuboid rule on the stored points (`av2_sweeps.argoverse_flow`). The log ids differ per profile
(`log_id_for`).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import uuid

import numpy as np

from ff3d_tf import geometry, schema
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.synthetic import av2_sweeps
from ff3d_tf.data.synthetic import city as city_lib
from ff3d_tf.data.synthetic import lidar as lidar_lib
from ff3d_tf.data.synthetic import realism as realism_lib
from ff3d_tf.data.synthetic import scene as sim
from ff3d_tf.data.wod import wod_format

_LOG = logging.getLogger(__name__)

DEFAULT_NUM_SWEEPS = 6
DEFAULT_POINTS_PER_SWEEP = 6000
SWEEP_PERIOD_NS = 100_000_000  # 10 Hz
SWEEP_JITTER_NS = 300_000  # the sample's two sweeps are 100.196 ms apart
POSE_PERIOD_NS = 10_000_000  # ego poses between sweeps (AV2 logs hold poses at ~100-200 Hz)
FIRST_TIMESTAMP_NS = 315_970_000_000_000_000  # AV2 timestamps are GPS nanoseconds of 2020
EGO_ORIGIN_HEIGHT_M = 0.33
GROUND_CELL_M = 0.3  # AV2's raster resolution
RASTER_MARGIN_M = 2.0
ROI_HALF_WIDTH_M = 15.0  # ground height where |lateral offset| <= this (road, sidewalks), NaN beyond (buildings)
DRIVABLE_HALF_WIDTH_M = 9.5  # lanes, bike lanes and parking
LANE_SEGMENT_LENGTH_M = 20.0
CITY_TILT_MAX_RAD = np.deg2rad(1.5)
LIDAR_MAX_RANGE_M = sim.TOP_MAX_RANGE_M
MIN_RANGE_M = 0.5
MAX_START_TIME_S = 30.0
REALISTIC_MAX_START_TIME_S = 10.0  # the city's traffic has run `city.WARMUP_S` before t = 0 already
RETURN_SHARE_GUESS = 0.5  # share of rays with a return, to size the scan before drawing the exact point count
DEFAULT_CITY = "SYN"
_UUID_NAMESPACE = uuid.UUID("6f0c3e2a-2b8e-4e58-9a7e-0a6f7c1d2e31")  # this project's namespace for synthetic ids

# Categories the simulator's classes are written as (all of them keys of `argoverse2.AV2_CLASS` with that class).
CATEGORY_OF_CLASS = {schema.CLASS_VEHICLE: "REGULAR_VEHICLE", schema.CLASS_PEDESTRIAN: "PEDESTRIAN",
                     schema.CLASS_SIGN: "SIGN", schema.CLASS_CYCLIST: "BICYCLIST"}

# Arrow schemas of the files, as the sample log's files have them (tests compare the two).
SWEEP_FIELDS = (("x", "float16"), ("y", "float16"), ("z", "float16"), ("intensity", "uint8"),
                ("laser_number", "uint8"), ("offset_ns", "int32"))
POSE_FIELDS = (("timestamp_ns", "int64"), ("qw", "float64"), ("qx", "float64"), ("qy", "float64"),
               ("qz", "float64"), ("tx_m", "float64"), ("ty_m", "float64"), ("tz_m", "float64"))
ANNOTATION_FIELDS = (("timestamp_ns", "int64"), ("track_uuid", "string"), ("category", "string"),
                     ("length_m", "float64"), ("width_m", "float64"), ("height_m", "float64"), ("qw", "float64"),
                     ("qx", "float64"), ("qy", "float64"), ("qz", "float64"), ("tx_m", "float64"),
                     ("ty_m", "float64"), ("tz_m", "float64"), ("num_interior_pts", "int64"))
CALIBRATION_FIELDS = (("sensor_name", "string"),) + POSE_FIELDS[1:]
FLOW_LABEL_FIELDS = (("flow_tx_m", "float32"), ("flow_ty_m", "float32"), ("flow_tz_m", "float32"),
                     ("classes", "uint8"), ("dynamic", "bool"), ("is_ground_0", "bool"))


@dataclasses.dataclass(frozen=True)
class Lidar:
    """One of AV2's two stacked 32-beam lidars: mounting (sensor -> ego), beams (sensor frame), laser numbers."""

    name: str
    quaternion: tuple  # (qw, qx, qy, qz) sensor -> ego
    translation: tuple  # metres, ego frame
    first_laser: int
    spin_phase: float  # share of a turn: the two lidars spin in step, 180 degrees apart

    def extrinsic(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = geometry.rotation_from_quaternion_np(*self.quaternion)
        m[:3, 3] = self.translation
        return m


def _unit(q):
    q = np.asarray(q, np.float64)
    return tuple(float(v) for v in q / np.linalg.norm(q))


# Mountings near the sample log's calibration: the up lidar level, the down lidar upside down and pitched ~11.6 deg.
LIDARS = (Lidar("up_lidar", _unit((0.99999, 0.0, 0.0, -0.0051)), (1.35, 0.0, 1.64), 0, 0.0),
          Lidar("down_lidar", _unit((-0.0005, -0.9949, 0.1007, -0.0001)), (1.347, 0.005, 1.525), 32, 0.5))
# 32 beams from -25 to +15 degrees (sensor frame), densest near the horizon like a VLP-32C (Velodyne VLP-32C datasheet:
# vertical field of view -25 to +15 degrees, non-linear beam spacing); ascending.
BEAM_INCLINATIONS_RAD = np.deg2rad(np.interp(np.linspace(0.0, 1.0, 32), [0.0, 0.12, 0.5, 0.88, 1.0],
                                             [-25.0, -9.0, -1.0, 4.0, 15.0]))


@dataclasses.dataclass
class Sweep:
    """One simulated sweep, as written plus the truth behind it."""

    timestamp_ns: int
    points_xyz: np.ndarray  # [N, 3] float16, ego frame
    intensity: np.ndarray  # [N] uint8
    laser_number: np.ndarray  # [N] uint8
    offset_ns: np.ndarray  # [N] int32
    agent_index: np.ndarray  # [N] int32: index into SyntheticLog.agents of the object hit, -1 ground
    points_world: np.ndarray  # [N, 3] float64 world, the hit points before float16 storage (realism profiles: as
    # measured, where each ray met its surface at its firing time)
    cuboids: list  # rows of annotations.feather at this sweep (dicts of ANNOTATION_FIELDS)


@dataclasses.dataclass
class SyntheticLog:
    log_id: str
    city: str
    seed: int
    road: sim.Road
    agents: list
    track_uuids: list  # per agent
    city_from_world: np.ndarray  # [4, 4]
    times_s: np.ndarray  # [T] simulator time of each sweep
    world_from_ego: np.ndarray  # [T, 4, 4] at the sweep timestamps
    sweeps: list  # [T] Sweep
    pose_timestamps_ns: np.ndarray  # [P] every pose row of city_SE3_egovehicle.feather
    pose_world_from_ego: np.ndarray  # [P, 4, 4]
    ground_height_m: np.ndarray  # [H, W] float16
    sim2: dict  # {"R": [4], "t": [2], "s": float}
    realism: realism_lib.Realism = realism_lib.IDEAL

    def city_from_ego(self, k: int) -> np.ndarray:
        return self.city_from_world @ self.world_from_ego[k]

    def ground_height_world_to_city(self, xy_city: np.ndarray) -> np.ndarray:
        """Exact city ground height (the tilted world ground: the plane z_world = 0, or the city world's terrain)
        under city points [N, 2]."""
        return _ground_height_city(self.city_from_world, np.asarray(xy_city, np.float64), self.road)[0]


def log_id_for(seed: int, index: int = 0, realism: str | realism_lib.Realism = realism_lib.IDEAL.name) -> str:
    """A deterministic AV2-style log id (a UUID string) for a seed (another for each realism profile, so a split of
    one profile never resumes with logs of another)."""
    name = realism_lib.profile(realism).name
    suffix = "" if name == realism_lib.IDEAL.name else f"/{name}"
    return str(uuid.uuid5(_UUID_NAMESPACE, f"log/{seed}/{index}{suffix}"))


def _city_frame(rng: np.random.Generator) -> np.ndarray:
    m = np.eye(4)
    roll, pitch = rng.uniform(-CITY_TILT_MAX_RAD, CITY_TILT_MAX_RAD, 2)
    m[:3, :3] = wod_format.rotation_from_rpy(roll, pitch, rng.uniform(-np.pi, np.pi))
    m[:3, 3] = (rng.uniform(1000.0, 8000.0), rng.uniform(1000.0, 8000.0), rng.uniform(10.0, 60.0))
    return m


def _plane_height(city_from_world: np.ndarray, xy_city: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """City z of the world ground plane (z_world = 0) under city points [N, 2], and those points' world xy [N, 2]."""
    r, c = city_from_world[:3, :3], city_from_world[:3, 3]
    # city = R @ (wx, wy, 0) + c: the xy rows give (wx, wy); the z row gives the height.
    world_xy = np.linalg.solve(r[:2, :2], (xy_city - c[:2]).T).T
    return world_xy @ r[2, :2] + c[2], world_xy


def _ground_height_city(city_from_world: np.ndarray, xy_city: np.ndarray, road: sim.Road):
    """`_plane_height` of the world's ground: the plane z_world = 0, or the terrain's height field (the world xy
    under each city point solved by fixed-point iteration: the tilt is small, so it contracts fast)."""
    if road.ground is None:
        return _plane_height(city_from_world, xy_city)
    r, c = city_from_world[:3, :3], city_from_world[:3, 3]
    world_xy = _plane_height(city_from_world, xy_city)[1]
    for _ in range(6):
        z = road.ground_height(world_xy[:, 0], world_xy[:, 1])
        world_xy = np.linalg.solve(r[:2, :2], (xy_city - c[:2] - np.outer(z, r[:2, 2])).T).T
    z = road.ground_height(world_xy[:, 0], world_xy[:, 1])
    return world_xy @ r[2, :2] + z * r[2, 2] + c[2], world_xy


def _lateral_offset(road: sim.Road, xy_world: np.ndarray, s_lo: float, s_hi: float) -> np.ndarray:
    """|d|: distance of world points [N, 2] from the road centreline (`_road_coordinates`)."""
    return _road_coordinates(road, xy_world, s_lo, s_hi)[1]


def _road_coordinates(road: sim.Road, xy_world: np.ndarray, s_lo: float, s_hi: float):
    """(s, |d|) of world points [N, 2]: the nearest of 2 m centreline samples in [s_lo, s_hi], then two Newton steps
    along the local tangent, and the distance from the centreline."""
    s_grid = np.arange(s_lo, s_hi, 2.0)
    cx, cy, _ = road.pose(s_grid, 0.0)
    s = np.empty(len(xy_world))
    chunk = 8192
    for lo in range(0, len(xy_world), chunk):
        p = xy_world[lo:lo + chunk]
        d2 = (p[:, None, 0] - cx[None]) ** 2 + (p[:, None, 1] - cy[None]) ** 2
        s[lo:lo + chunk] = s_grid[np.argmin(d2, axis=1)]
    for _ in range(2):
        x, y, th = road.pose(s, 0.0)
        s = s + (xy_world[:, 0] - x) * np.cos(th) + (xy_world[:, 1] - y) * np.sin(th)
    x, y, th = road.pose(s, 0.0)
    return s, np.abs(-(xy_world[:, 0] - x) * np.sin(th) + (xy_world[:, 1] - y) * np.cos(th))


def _scan_sweep(width: int, pose_world: np.ndarray, boxes):
    """Every return of both lidars at one pose: world points, hit ids, laser numbers, firing share of the turn."""
    out = []
    for lidar in LIDARS:
        spec = sim.LidarSpec(name=2, height=len(BEAM_INCLINATIONS_RAD), width=width, extrinsic=lidar.extrinsic(),
                             max_range_m=LIDAR_MAX_RANGE_M, beam_inclinations=BEAM_INCLINATIONS_RAD)
        ranges, hits, origins, dirs = sim.scan(spec, None, pose_world, boxes)
        valid = np.isfinite(ranges) & (ranges > MIN_RANGE_M)
        rows, cols = np.nonzero(valid)
        points = origins[rows, cols] + dirs[rows, cols] * ranges[rows, cols][:, None]
        # Row 0 is the highest beam (wod_format.row_inclinations); laser numbers go up with inclination.
        laser = lidar.first_laser + (len(BEAM_INCLINATIONS_RAD) - 1 - rows)
        turn = (cols + 0.5) / width
        out.append((points, hits[rows, cols], laser, (turn + lidar.spin_phase) % 1.0))
    return [np.concatenate(parts) for parts in zip(*out)]


def _intensity(rng: np.random.Generator, materials: np.ndarray) -> np.ndarray:
    values = np.zeros(len(materials))
    for material, (mean, std) in sim.MATERIAL_INTENSITY.items():
        sel = materials == material
        if sel.any():
            values[sel] = rng.normal(mean, std, int(sel.sum()))
    return np.clip(np.round(values * 255.0), 0, 255).astype(np.uint8)


def _yaw(m: np.ndarray) -> float:
    return float(np.arctan2(m[1, 0], m[0, 0]))


def simulate_log(log_id: str, num_sweeps: int = DEFAULT_NUM_SWEEPS, seed: int = 0,
                 points_per_sweep: int = DEFAULT_POINTS_PER_SWEEP, city: str = DEFAULT_CITY,
                 realism: str | realism_lib.Realism = realism_lib.IDEAL.name) -> SyntheticLog:
    """The log in memory (what `write_synthetic_log` writes, with the truth behind it). Deterministic for a seed.

    Each sweep holds `points_per_sweep` points drawn from a denser scan of both lidars (fewer only if the scan has
    fewer returns), in firing order. Under a `realism` profile other than the default, `_simulate_measured`."""
    if num_sweeps < 1 or points_per_sweep < 1:
        raise ValueError(f"num_sweeps ({num_sweeps}) and points_per_sweep ({points_per_sweep}) must be positive")
    profile = realism_lib.profile(realism)
    if profile != realism_lib.IDEAL:
        return _simulate_measured(log_id, num_sweeps, seed, points_per_sweep, city, profile)
    rng = np.random.default_rng(seed)
    ego_speed = float(rng.uniform(4.0, 9.0))
    road, agents = sim.make_scene(rng, ego_speed)
    track_uuids = [str(uuid.uuid5(_UUID_NAMESPACE, f"{log_id}/{a.track_id}")) for a in agents]
    city_from_world = _city_frame(rng)
    stamps = _sweep_stamps(rng, seed, num_sweeps)
    # The log starts somewhere along the road (so the ego may be turning and its heading is not the world's x).
    times = float(rng.uniform(0.0, MAX_START_TIME_S)) + (stamps - stamps[0]) * 1e-9

    def world_from_ego_at(t):
        m = sim.ego_poses(road, t, ego_speed)
        m[:, 2, 3] += EGO_ORIGIN_HEIGHT_M
        return m

    world_from_ego = world_from_ego_at(times)
    width = max(16, int(np.ceil(points_per_sweep / (2 * len(BEAM_INCLINATIONS_RAD) * RETURN_SHARE_GUESS))))
    index_of = {a.track_id: i for i, a in enumerate(agents)}
    sweeps = []
    for k, (ts, t) in enumerate(zip(stamps, times)):
        scene = sim.frame_scene(k, float(t), road, agents, ego_speed)
        near = np.array([index_of[a.track_id] for a in scene.near], np.int64)
        boxes = [(j, scene.poses_t[a.track_id][0], scene.poses_t[a.track_id][1], a.size / 2)
                 for j, a in enumerate(scene.near)]
        w = width
        for _ in range(4):  # widen the scan until it has enough returns
            points_w, hits, laser, turn = _scan_sweep(w, world_from_ego[k], boxes)
            if len(points_w) >= points_per_sweep:
                break
            w = int(np.ceil(w * 1.2 * points_per_sweep / max(len(points_w), 1)))
        keep = np.sort(rng.choice(len(points_w), min(points_per_sweep, len(points_w)), replace=False))
        points_w, hits, laser, turn = points_w[keep], hits[keep], laser[keep], turn[keep]
        agent_index = np.full(len(hits), -1, np.int64)  # hits: -1 ground, else the index into scene.near
        agent_index[hits >= 0] = near[hits[hits >= 0]]
        offset_ns = np.round(turn * SWEEP_PERIOD_NS).astype(np.int32)
        order = np.lexsort((laser, offset_ns))
        points_w, agent_index, laser, offset_ns = points_w[order], agent_index[order], laser[order], offset_ns[order]
        materials = np.array([agents[i].material if i >= 0 else "ground" for i in agent_index], dtype=object)
        ego_from_world = np.linalg.inv(world_from_ego[k])
        points_ego = geometry.transform_points_np(points_w, ego_from_world).astype(np.float16)
        counts = np.bincount(agent_index[agent_index >= 0], minlength=len(agents))
        ego_yaw = _yaw(world_from_ego[k])
        cuboids = []
        for a in scene.near:
            if a.track_id not in scene.labelled_now:
                continue
            i = index_of[a.track_id]
            center_w, heading_w = scene.poses_t[a.track_id]
            center = ego_from_world[:3, :3] @ center_w + ego_from_world[:3, 3]
            yaw = float(np.arctan2(np.sin(heading_w - ego_yaw), np.cos(heading_w - ego_yaw)))
            cuboids.append(_cuboid_row(ts, track_uuids[i], CATEGORY_OF_CLASS[a.class_id], a.size, center, yaw,
                                       counts[i]))
        sweeps.append(Sweep(int(ts), points_ego, _intensity(rng, materials), laser.astype(np.uint8), offset_ns,
                            agent_index.astype(np.int32), points_w, cuboids))
    # Ego poses: the sweeps' and every POSE_PERIOD_NS from 50 ms before the first to 50 ms after the last sweep.
    grid = np.arange(stamps[0] - 50_000_000 + 3_000_001, stamps[-1] + 50_000_000, POSE_PERIOD_NS, dtype=np.int64)
    pose_ts = np.union1d(grid, stamps)
    pose_w = world_from_ego_at(times[0] + (pose_ts - stamps[0]) * 1e-9)
    pose_w[np.searchsorted(pose_ts, stamps)] = world_from_ego  # the sweeps' poses bit for bit
    s_ego = ego_speed * np.asarray(times)
    height, sim2 = _ground_raster(road, city_from_world, sweeps, float(s_ego.min()), float(s_ego.max()))
    return SyntheticLog(log_id, city, seed, road, agents, track_uuids, city_from_world, times, world_from_ego,
                        sweeps, pose_ts, pose_w, height, sim2)


def _sweep_stamps(rng: np.random.Generator, seed: int, num_sweeps: int) -> np.ndarray:
    """[T] int64 sweep timestamps (ns): 10 Hz with the sample's jitter, from a GPS time of 2020 set by the seed."""
    steps = SWEEP_PERIOD_NS + rng.integers(-SWEEP_JITTER_NS, SWEEP_JITTER_NS + 1, num_sweeps - 1)
    stamps = FIRST_TIMESTAMP_NS + (seed % 1_000_000) * 100_000_000_000 + np.concatenate([[0], np.cumsum(steps)])
    return stamps.astype(np.int64)


def _cuboid_row(ts, track_uuid: str, category: str, size, center, yaw: float, count) -> dict:
    """One annotations.feather row (ANNOTATION_FIELDS): a yaw-only cuboid in the ego frame of its sweep."""
    return {"timestamp_ns": int(ts), "track_uuid": track_uuid, "category": category, "length_m": float(size[0]),
            "width_m": float(size[1]), "height_m": float(size[2]), "qw": float(np.cos(yaw / 2)), "qx": 0.0,
            "qy": 0.0, "qz": float(np.sin(yaw / 2)), "tx_m": float(center[0]), "ty_m": float(center[1]),
            "tz_m": float(center[2]), "num_interior_pts": int(count)}


def _simulate_measured(log_id: str, num_sweeps: int, seed: int, points_per_sweep: int, city: str,
                       profile: realism_lib.Realism) -> SyntheticLog:
    """`simulate_log` under a realism profile (`synthetic.av2_sweeps`): the profile's world (the city world, or the
    street world), every sweep scanned at a fixed width per log chosen on sweep 0 so that sweeps hold about
    `points_per_sweep` returns (all of them, no subsampling: the count varies with the scene), cuboids where the up
    lidar swept over each object."""
    rng = np.random.default_rng(seed)
    stamps = _sweep_stamps(rng, seed, num_sweeps)
    times = float(rng.uniform(0.0, REALISTIC_MAX_START_TIME_S)) + (stamps - stamps[0]) * 1e-9
    world = city_lib.world_for(profile, rng, float(times[-1]) + 1.0)
    road, agents = world.road, world.agents
    track_uuids = [str(uuid.uuid5(_UUID_NAMESPACE, f"{log_id}/{a.track_id}")) for a in agents]
    city_from_world = _city_frame(rng)

    def world_from_ego_at(t):
        m = world.ego_poses(t)
        m[:, 2, 3] += EGO_ORIGIN_HEIGHT_M
        return m

    world_from_ego = world_from_ego_at(times)
    spin_offset = av2_sweeps.up_lidar_offset_s(LIDARS[0].spin_phase, SWEEP_PERIOD_NS)
    index_of = {a.track_id: i for i, a in enumerate(agents)}
    width = max(16, int(np.ceil(points_per_sweep / (2 * len(BEAM_INCLINATIONS_RAD) * RETURN_SHARE_GUESS))))
    sweeps = []
    for k, (ts, t) in enumerate(zip(stamps, times)):
        scene = world.frame_scene(k, float(t))

        def scan(w):
            return av2_sweeps.scan_sweep(LIDARS, BEAM_INCLINATIONS_RAD, w, scene, world_from_ego_at, road, rng,
                                         profile, SWEEP_PERIOD_NS, LIDAR_MAX_RANGE_M, MIN_RANGE_M)
        if k == 0:  # the log's width: a first scan's return share scaled to the wanted count
            width = max(16, int(np.ceil(width * points_per_sweep / max(len(scan(width)[0]), 1))))
        points_w, hits, laser, offset_ns = scan(width)
        near = np.array([index_of[a.track_id] for a in scene.near], np.int64)
        agent_index = np.where(hits >= 0, near[np.maximum(hits, 0)] if len(near) else -1, -1)
        order = np.lexsort((laser, offset_ns))
        points_w, agent_index, laser, offset_ns = points_w[order], agent_index[order], laser[order], offset_ns[order]
        materials = np.array([agents[i].material if i >= 0 else "ground" for i in agent_index], dtype=object)
        points_ego = geometry.transform_points_np(points_w, np.linalg.inv(world_from_ego[k])).astype(np.float16)
        by_x = lidar_lib.PointsByX(points_ego.astype(np.float64))
        cuboids = []
        for a in scene.near:
            if a.track_id in scene.labelled_now:
                centre, yaw, size = av2_sweeps.cuboid_box(road, a, float(t), world_from_ego[k], spin_offset, profile)
                cuboids.append(_cuboid_row(ts, track_uuids[index_of[a.track_id]],
                                           a.category or CATEGORY_OF_CLASS[a.class_id], size, centre, yaw,
                                           len(by_x.inside(centre, yaw, size))))
        sweeps.append(Sweep(int(ts), points_ego, _intensity(rng, materials), laser.astype(np.uint8),
                            offset_ns.astype(np.int32), agent_index.astype(np.int32), points_w, cuboids))
    grid = np.arange(stamps[0] - 50_000_000 + 3_000_001, stamps[-1] + 50_000_000, POSE_PERIOD_NS, dtype=np.int64)
    pose_ts = np.union1d(grid, stamps)
    pose_w = world_from_ego_at(times[0] + (pose_ts - stamps[0]) * 1e-9)
    pose_w[np.searchsorted(pose_ts, stamps)] = world_from_ego
    s_ego = [road.s[np.argmin(np.hypot(road.x - m[0, 3], road.y - m[1, 3]))] for m in world_from_ego[[0, -1]]]
    height, sim2 = _ground_raster(road, city_from_world, sweeps, float(min(s_ego)), float(max(s_ego)),
                                  world.intersections)
    return SyntheticLog(log_id, city, seed, road, agents, track_uuids, city_from_world, times, world_from_ego,
                        sweeps, pose_ts, pose_w, height, sim2, profile)


def _ground_raster(road, city_from_world, sweeps, s_ego_min: float, s_ego_max: float, intersections=()):
    """Float16 ground height of the (tilted) world ground over every point of the log, NaN beyond the ROI (the road
    and its sidewalks; the side streets of `intersections`)."""
    city_xy = np.concatenate([geometry.transform_points_np(s.points_world, city_from_world)[:, :2] for s in sweeps])
    lo = np.round(np.floor((city_xy.min(axis=0) - RASTER_MARGIN_M) / GROUND_CELL_M) * GROUND_CELL_M, 6)
    hi = city_xy.max(axis=0) + RASTER_MARGIN_M
    cols, rows = (np.ceil((hi - lo) / GROUND_CELL_M)).astype(int)
    scale = 1.0 / GROUND_CELL_M
    # Cell (row, col) spans pixel [col, col + 1) x [row, row + 1); its centre in the city is (pixel + 0.5) / s - t.
    cx = (np.arange(cols) + 0.5) / scale + lo[0]
    cy = (np.arange(rows) + 0.5) / scale + lo[1]
    grid_xy = np.stack(np.meshgrid(cx, cy), -1).reshape(-1, 2)
    height, world_xy = _ground_height_city(city_from_world, grid_xy, road)
    reach = np.sqrt(2.0) * (LIDAR_MAX_RANGE_M + RASTER_MARGIN_M) + ROI_HALF_WIDTH_M
    s, lateral = _road_coordinates(road, world_xy, s_ego_min - reach, s_ego_max + reach)
    roi = lateral <= ROI_HALF_WIDTH_M
    for s_int in intersections:
        roi |= np.abs(s - s_int) <= city_lib.INTERSECTION_CLEAR_M
    height = np.where(roi, height, np.nan).reshape(rows, cols).astype(np.float16)
    sim2 = {"R": [1.0, 0.0, 0.0, 1.0], "t": [float(-lo[0]), float(-lo[1])], "s": scale}
    return height, sim2


def _table(fields, columns: dict):
    import pyarrow as pa
    types = {"float16": pa.float16(), "float32": pa.float32(), "float64": pa.float64(), "uint8": pa.uint8(),
             "int32": pa.int32(), "int64": pa.int64(), "string": pa.string(), "bool": pa.bool_()}
    schema_ = pa.schema([(name, types[kind]) for name, kind in fields])
    arrays = []
    for name, kind in fields:
        values = columns[name]
        if kind == "string":
            arrays.append(pa.array([str(v) for v in values], pa.string()))
        else:
            arrays.append(pa.array(np.asarray(values, dtype=kind), types[kind]))
    return pa.Table.from_arrays(arrays, schema=schema_)


def _write_feather(path: str, fields, columns: dict) -> None:
    import pyarrow.feather as feather
    os.makedirs(os.path.dirname(path), exist_ok=True)
    feather.write_feather(_table(fields, columns), path, compression="lz4")


def _pose_columns(stamps, matrices) -> dict:
    quats = np.array([_quaternion(m[:3, :3]) for m in matrices]).reshape(-1, 4)
    return {"timestamp_ns": np.asarray(stamps, np.int64), "qw": quats[:, 0], "qx": quats[:, 1], "qy": quats[:, 2],
            "qz": quats[:, 3], "tx_m": matrices[:, 0, 3], "ty_m": matrices[:, 1, 3], "tz_m": matrices[:, 2, 3]}


def _quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's branch on the largest diagonal term)."""
    t = np.trace(r)
    if t > 0:
        w = np.sqrt(1.0 + t) / 2
        q = np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        v = np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) / 2
        q = np.zeros(4)
        q[1 + i] = v
        q[0] = (r[k, j] - r[j, k]) / (4 * v)
        q[1 + j] = (r[j, i] + r[i, j]) / (4 * v)
        q[1 + k] = (r[k, i] + r[i, k]) / (4 * v)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _vector_map(log: SyntheticLog) -> dict:
    """Lane segments (four lanes, 20 m pieces) and the drivable area along the road stretch the raster covers, in
    city coordinates quantized to 1 cm as AV2's vector maps are; no pedestrian crossings."""
    height = log.ground_height_m
    t, s = np.asarray(log.sim2["t"]), log.sim2["s"]
    corners = np.array([[0, 0], [height.shape[1], 0], [0, height.shape[0]], [height.shape[1], height.shape[0]]]) / s - t
    _, corner_world = _ground_height_city(log.city_from_world, corners, log.road)
    s_ego = log.road.s[np.argmin(np.hypot(log.road.x - log.world_from_ego[0, 0, 3],
                                          log.road.y - log.world_from_ego[0, 1, 3]))]
    reach = float(np.max(np.hypot(*(corner_world - log.world_from_ego[0, :2, 3]).T)))
    s_lo = np.floor((s_ego - reach) / LANE_SEGMENT_LENGTH_M) * LANE_SEGMENT_LENGTH_M
    s_hi = s_ego + reach

    def polyline(s0, s1, d):
        ss = np.linspace(s0, s1, 5)
        x, y, _ = log.road.pose(ss, d)
        city = geometry.transform_points_np(np.stack([x, y, log.road.ground_height(x, y)], -1), log.city_from_world)
        return [{"x": round(float(p[0]), 2), "y": round(float(p[1]), 2), "z": round(float(p[2]), 2)} for p in city]

    lanes = ((-1.75, 1, "right_inner"), (-5.25, 1, "right_outer"), (1.75, -1, "left_inner"), (5.25, -1, "left_outer"))
    marks = {0.0: "DOUBLE_SOLID_YELLOW", 3.5: "DASHED_WHITE", 7.0: "SOLID_WHITE"}
    starts = np.arange(s_lo, s_hi, LANE_SEGMENT_LENGTH_M)
    ids = {(lane, n): 1000 * (li + 1) + n for li, (_, _, lane) in enumerate(lanes) for n in range(len(starts))}
    segments = {}
    for d, direction, lane in lanes:
        for n, s0 in enumerate(starts):
            s1 = s0 + LANE_SEGMENT_LENGTH_M
            a, b = (s0, s1) if direction > 0 else (s1, s0)
            # Left/right of the direction of travel: for direction +1, left is +d.
            left_d, right_d = (d + 1.75, d - 1.75) if direction > 0 else (d - 1.75, d + 1.75)
            nxt, prev = (n + 1, n - 1) if direction > 0 else (n - 1, n + 1)
            inner = lane.endswith("inner")
            side = lane.split("_")[0]
            neighbour = ids.get((f"{side}_{'outer' if inner else 'inner'}", n))
            segments[str(ids[(lane, n)])] = {
                "id": ids[(lane, n)], "is_intersection": False, "lane_type": "VEHICLE",
                "left_lane_boundary": polyline(a, b, left_d), "left_lane_mark_type": marks[abs(left_d)],
                "right_lane_boundary": polyline(a, b, right_d), "right_lane_mark_type": marks[abs(right_d)],
                "successors": [ids[(lane, nxt)]] if (lane, nxt) in ids else [],
                "predecessors": [ids[(lane, prev)]] if (lane, prev) in ids else [],
                "right_neighbor_id": neighbour if inner else None, "left_neighbor_id": None if inner else neighbour}
    left = polyline(s_lo, s_hi, DRIVABLE_HALF_WIDTH_M)
    right = polyline(s_lo, s_hi, -DRIVABLE_HALF_WIDTH_M)
    area = {"area_boundary": right + left[::-1], "id": 1}
    return {"pedestrian_crossings": {}, "lane_segments": segments, "drivable_areas": {"1": area}}


def _flow_label_columns(log: SyntheticLog, log_dir: str) -> dict:
    """Sweep 0 -> sweep 1 in Argoverse's convention, from the simulator's motion of the surface each point hit (under
    a realism profile: Argoverse's cuboid rule, `av2_sweeps.argoverse_flow`)."""
    s0 = log.sweeps[0]
    p0 = s0.points_xyz.astype(np.float64)  # the stored (float16) point is the one labelled
    if log.realism != realism_lib.IDEAL:
        flow, owner = av2_sweeps.argoverse_flow(p0, s0.cuboids, log.sweeps[1].cuboids, log.city_from_ego(0),
                                                log.city_from_ego(1))
        classes = np.array([argoverse2.scene_flow_category_index(s0.cuboids[i]["category"]) if i >= 0 else 0
                            for i in owner], np.uint8)
        return _flow_columns(log, log_dir, p0, flow, classes)
    world_p = geometry.transform_points_np(p0, log.world_from_ego[0])
    t0, t1 = log.times_s[:2]
    moved = world_p.copy()
    classes = np.zeros(len(p0), np.uint8)
    labelled = {c["track_uuid"]: c["category"] for c in s0.cuboids}
    for i in np.unique(s0.agent_index[s0.agent_index >= 0]):
        a = log.agents[i]
        sel = s0.agent_index == i
        b0 = geometry.box_matrices_np(*a.pose(log.road, t0))[0]
        b1 = geometry.box_matrices_np(*a.pose(log.road, t1))[0]
        moved[sel] = geometry.transform_points_np(world_p[sel], b1 @ np.linalg.inv(b0))
        if log.track_uuids[i] in labelled:
            classes[sel] = argoverse2.scene_flow_category_index(labelled[log.track_uuids[i]])
    p1 = geometry.transform_points_np(moved, np.linalg.inv(log.world_from_ego[1]))
    return _flow_columns(log, log_dir, p0, p1 - p0, classes)


def _flow_columns(log: SyntheticLog, log_dir: str, p0: np.ndarray, flow: np.ndarray, classes: np.ndarray) -> dict:
    """FLOW_LABEL_FIELDS of sweep 0's flow: `dynamic` and `is_ground_0` by Argoverse's rules."""
    ego1_from_ego0 = np.linalg.inv(log.world_from_ego[1]) @ log.world_from_ego[0]
    rigid = geometry.transform_points_np(p0, ego1_from_ego0) - p0
    dynamic = np.linalg.norm(flow - rigid, axis=1) >= argoverse2.SCENE_FLOW_DYNAMIC_THRESHOLD_M
    ground = argoverse2.is_ground(log_dir, p0, log.city_from_ego(0))
    flow = flow.astype(np.float32)
    return {"flow_tx_m": flow[:, 0], "flow_ty_m": flow[:, 1], "flow_tz_m": flow[:, 2], "classes": classes,
            "dynamic": dynamic, "is_ground_0": ground}


def write_log(log: SyntheticLog, log_dir: str) -> str:
    """Writes a simulated log into `log_dir` (created; existing files are overwritten). Returns `log_dir`."""
    map_dir = os.path.join(log_dir, "map")
    os.makedirs(map_dir, exist_ok=True)
    np.save(os.path.join(map_dir, f"{log.log_id}_ground_height_surface____{log.city}.npy"), log.ground_height_m)
    with open(os.path.join(map_dir, f"{log.log_id}___img_Sim2_city.json"), "w") as f:
        json.dump(log.sim2, f)
    city_map_id = 10000 + log.seed % 90000
    with open(os.path.join(map_dir, f"log_map_archive_{log.log_id}____{log.city}_city_{city_map_id}.json"), "w") as f:
        json.dump(_vector_map(log), f)
    for sweep in log.sweeps:
        p = sweep.points_xyz
        _write_feather(os.path.join(log_dir, "sensors", "lidar", f"{sweep.timestamp_ns}.feather"), SWEEP_FIELDS,
                       {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2], "intensity": sweep.intensity,
                        "laser_number": sweep.laser_number, "offset_ns": sweep.offset_ns})
    rows = [c for sweep in log.sweeps for c in sweep.cuboids]
    _write_feather(os.path.join(log_dir, "annotations.feather"), ANNOTATION_FIELDS,
                   {name: [r[name] for r in rows] for name, _ in ANNOTATION_FIELDS})
    city_from_ego = log.city_from_world[None] @ log.pose_world_from_ego
    _write_feather(os.path.join(log_dir, "city_SE3_egovehicle.feather"), POSE_FIELDS,
                   _pose_columns(log.pose_timestamps_ns, city_from_ego))
    quats, trans = np.array([lidar.quaternion for lidar in LIDARS]), np.array([lidar.translation for lidar in LIDARS])
    calib = {"sensor_name": [lidar.name for lidar in LIDARS], "qw": quats[:, 0], "qx": quats[:, 1],
             "qy": quats[:, 2], "qz": quats[:, 3], "tx_m": trans[:, 0], "ty_m": trans[:, 1], "tz_m": trans[:, 2]}
    _write_feather(os.path.join(log_dir, "calibration", "egovehicle_SE3_sensor.feather"), CALIBRATION_FIELDS, calib)
    if len(log.sweeps) >= 2:
        _write_feather(os.path.join(log_dir, "flow_labels.feather"), FLOW_LABEL_FIELDS,
                       _flow_label_columns(log, log_dir))
    return log_dir


def write_synthetic_log(out_dir: str, log_id: str | None = None, num_sweeps: int = DEFAULT_NUM_SWEEPS, seed: int = 0,
                        points_per_sweep: int = DEFAULT_POINTS_PER_SWEEP, city: str = DEFAULT_CITY,
                        realism: str | realism_lib.Realism = realism_lib.IDEAL.name) -> str:
    """Writes one synthetic AV2 log as `<out_dir>/<log_id>/...` (log_id defaults to `log_id_for(seed)`); returns the
    log directory. Deterministic for (log_id, seed, num_sweeps, points_per_sweep, realism)."""
    log_id = log_id or log_id_for(seed, realism=realism)
    return write_log(simulate_log(log_id, num_sweeps, seed, points_per_sweep, city, realism),
                     os.path.join(out_dir, log_id))


def write_synthetic_split(out_dir: str, num_logs: int, split: str = "val", num_sweeps: int = DEFAULT_NUM_SWEEPS,
                          seed: int = 0, points_per_sweep: int = DEFAULT_POINTS_PER_SWEEP,
                          city: str = DEFAULT_CITY, progress=None, realism: str = realism_lib.IDEAL.name) -> list[str]:
    """Writes `num_logs` logs as `<out_dir>/<split>/<log_id>/...` (AV2's `sensor/<split>/<log_id>` layout below the
    dataset root); log k uses seed `seed * 100003 + k` and id `log_id_for(seed, k)`. Resumable: each log is written
    to `<log_id>.partial` and renamed when complete; complete logs already there are kept. `progress(k, n, log_dir,
    skipped)` is called after each log (default: a log line). Returns the log directories in order. `realism`: the
    profile of `synthetic.realism` (its logs have their own ids, `log_id_for`)."""
    split_dir = os.path.join(out_dir, split)
    os.makedirs(split_dir, exist_ok=True)
    dirs = []
    for k in range(num_logs):
        log_id = log_id_for(seed, k, realism)
        final = os.path.join(split_dir, log_id)
        skipped = os.path.isdir(final)
        if not skipped:
            partial = final + ".partial"
            if os.path.exists(partial):
                shutil.rmtree(partial)
            write_log(simulate_log(log_id, num_sweeps, seed * 100003 + k, points_per_sweep, city, realism), partial)
            os.replace(partial, final)
        dirs.append(final)
        if progress is not None:
            progress(k, num_logs, final, skipped)
        else:
            _LOG.info("[%d/%d] %s %s", k + 1, num_logs, "exists, kept:" if skipped else "wrote", final)
    return dirs
