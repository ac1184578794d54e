"""Synthetic driving segments written as complete WOD v1 `Frame` records (the project's embedded default).

A street scene is raycast with the five WOD lidars (TOP 64 x 2650 with explicit inclinations and per-pixel poses;
FRONT, SIDE_LEFT, SIDE_RIGHT, REAR 200 x 600 with uniform inclinations): a ground plane, buildings, poles and signs,
and agents (vehicles, pedestrians, cyclists) that follow a curved road (so they rotate), in lanes, parked or standing
for a share, some appearing or disappearing mid-segment. The ego vehicle drives the road with a little roll and pitch.

Flow labels (`range_image_flow_compressed`) come from the simulator's own kinematics in the paper's convention: m/s,
motion t-1 -> t0 of the world point under the object's true rigid motion, expressed in the vehicle frame at t0 (ego
motion removed). An object without a label at the previous frame of the segment (its first labelled frame, or the
segment's first frame) gets class -1; background and static structures get class 0 and flow 0.

Speeds follow the paper's dataset figure (moving means near 5.6, 1.3 and 3.8 m/s for vehicles, pedestrians, cyclists).
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from ff3d_tf import geometry, schema
from ff3d_tf.data import wod_format

DT_S = 0.1
TOP_MAX_RANGE_M = 75.0
SHORT_MAX_RANGE_M = 20.0
LABEL_RANGE_M = 75.0
BOX_LIFT_M = 0.02  # agents float 2 cm above the ground: ground returns are never on a box face


@dataclasses.dataclass(frozen=True)
class LidarSpec:
    name: int
    height: int
    width: int
    extrinsic: np.ndarray  # 4x4 sensor -> vehicle
    max_range_m: float
    beam_inclinations: np.ndarray | None  # ascending (explicit, TOP)
    inclination_min: float = 0.0
    inclination_max: float = 0.0
    half_fov_rad: float = np.pi  # azimuth half-width with returns (short-range lidars see ~200 degrees)


def _extrinsic(x, y, z, roll, pitch, yaw) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = wod_format.rotation_from_rpy(roll, pitch, yaw)
    m[:3, 3] = (x, y, z)
    return m


def _top_inclinations() -> np.ndarray:
    """64 explicit beams from -17.6 to +2.4 degrees, denser near the horizon (ascending, as stored)."""
    u = np.linspace(0.0, 1.0, 64)
    return np.deg2rad(-17.6 + 20.0 * (1.0 - (1.0 - u) ** 1.6))


def wod_lidars(scale: float = 1.0) -> tuple[LidarSpec, ...]:
    """The five WOD lidars with slightly rotated (non-trivial) extrinsics. `scale` < 1 shrinks the images (tests)."""
    def sz(n):
        return max(8, int(round(n * scale)))
    top_h = 64 if scale >= 1 else max(8, int(round(64 * scale)))
    top_incl = _top_inclinations() if top_h == 64 else np.interp(np.linspace(0, 63, top_h), np.arange(64),
                                                                   _top_inclinations())
    short = dict(max_range_m=SHORT_MAX_RANGE_M, beam_inclinations=None, inclination_min=np.deg2rad(-90.0),
                 inclination_max=np.deg2rad(30.0), half_fov_rad=np.deg2rad(100.0))
    return (
        LidarSpec(1, top_h, sz(2650), _extrinsic(1.43, 0.0, 2.18, 0.003, -0.006, 0.0148), TOP_MAX_RANGE_M, top_incl),
        LidarSpec(2, sz(200), sz(600), _extrinsic(4.07, 0.0, 0.69, 0.002, 0.05, 0.004), **short),
        LidarSpec(3, sz(200), sz(600), _extrinsic(3.24, 1.03, 0.98, 0.04, 0.01, np.pi / 2 - 0.01), **short),
        LidarSpec(4, sz(200), sz(600), _extrinsic(3.24, -1.03, 0.98, -0.04, 0.01, -np.pi / 2 + 0.012), **short),
        LidarSpec(5, sz(200), sz(600), _extrinsic(-1.15, 0.0, 0.45, 0.0, 0.04, np.pi - 0.006), **short),
    )


class Road:
    """Centreline by arc length: piecewise-constant curvature, tabulated every 0.1 m."""

    def __init__(self, rng: np.random.Generator, s_min=-400.0, s_max=600.0):
        self.ds = 0.1
        self.s = np.arange(s_min, s_max, self.ds)
        kappa = np.zeros_like(self.s)
        start = 20.0
        while start < s_max:
            length = rng.uniform(25.0, 60.0)
            radius = rng.uniform(35.0, 90.0) * rng.choice([-1.0, 1.0])
            kappa[(self.s >= start) & (self.s < start + length)] = 1.0 / radius
            start += length + rng.uniform(30.0, 80.0)
        i0 = int(np.argmin(np.abs(self.s)))
        theta = np.cumsum(kappa) * self.ds
        self.theta = theta - theta[i0]
        x = np.cumsum(np.cos(self.theta)) * self.ds
        y = np.cumsum(np.sin(self.theta)) * self.ds
        self.x, self.y = x - x[i0], y - y[i0]

    def pose(self, s, d):
        """World (x, y, heading) of lateral offset d (left positive) at arc length s; arrays broadcast."""
        s = np.clip(s, self.s[0], self.s[-1])
        th = np.interp(s, self.s, self.theta)
        x = np.interp(s, self.s, self.x) - d * np.sin(th)
        y = np.interp(s, self.s, self.y) + d * np.cos(th)
        return x, y, th


@dataclasses.dataclass
class Agent:
    """A rigid box moving along the road: s(t) = s0 + v t at lateral offset d."""

    class_id: int  # 0 background structure, 1..4 labelled classes
    track_id: str
    size: np.ndarray  # length, width, height
    s0: float
    d: float
    speed: float  # signed, along the road
    reverse: bool  # heading opposite to the road direction
    z_bottom: float = BOX_LIFT_M
    t_start: float = -np.inf
    t_end: float = np.inf
    material: str = "vehicle"
    labelled: bool = True

    def alive(self, t: float) -> bool:
        return self.t_start <= t <= self.t_end

    def pose(self, road: Road, t: float) -> tuple[np.ndarray, float]:
        x, y, th = road.pose(self.s0 + self.speed * t, self.d)
        return np.array([x, y, self.z_bottom + self.size[2] / 2]), th + (np.pi if self.reverse else 0.0)


_INTENSITY = {"ground": (0.08, 0.03), "building": (0.22, 0.06), "pole": (0.3, 0.05), "sign": (0.9, 0.05),
              "vehicle": (0.45, 0.15), "pedestrian": (0.15, 0.05), "cyclist": (0.3, 0.08)}


def make_scene(rng: np.random.Generator, ego_speed_mps: float) -> tuple[Road, list[Agent]]:
    road = Road(rng)
    agents: list[Agent] = []
    n = 0

    def add(**kw):
        nonlocal n
        agents.append(Agent(track_id=f"obj{n:04d}", **kw))
        n += 1

    span = (-150.0, 450.0)
    # Moving traffic lanes (one speed per lane, so agents in a lane never overlap).
    for d, direction in ((-1.75, 1), (-5.25, 1), (1.75, -1), (5.25, -1)):
        v = ego_speed_mps if d == -1.75 else float(np.clip(rng.normal(5.6, 1.8), 2.0, 10.0))
        s = span[0] + rng.uniform(0, 20)
        while s < span[1]:
            if not (d == -1.75 and -12.0 < s < 12.0):  # keep the ego's own spot free
                size = np.array([rng.uniform(4.0, 5.2), rng.uniform(1.8, 2.1), rng.uniform(1.4, 1.9)])
                add(class_id=1, size=size, s0=s, d=d, speed=direction * v, reverse=direction < 0)
            s += rng.uniform(14.0, 45.0)
    # Parked vehicles along both curbs.
    for d in (-8.5, 8.5):
        s = span[0] + rng.uniform(0, 10)
        while s < span[1]:
            if rng.uniform() < 0.5:
                size = np.array([rng.uniform(4.0, 5.0), rng.uniform(1.8, 2.0), rng.uniform(1.4, 1.8)])
                add(class_id=1, size=size, s0=s, d=d, speed=0.0, reverse=bool(rng.uniform() < 0.3))
            s += rng.uniform(6.5, 9.0)
    # Cyclists on bike lanes, a few standing at the curb.
    for d, direction in ((-6.9, 1), (6.9, -1)):
        v = float(np.clip(rng.normal(3.8, 0.8), 2.0, 6.0))
        s = span[0] + rng.uniform(0, 30)
        while s < span[1]:
            size = np.array([rng.uniform(1.6, 1.9), rng.uniform(0.6, 0.8), rng.uniform(1.6, 1.8)])
            add(class_id=4, size=size, s0=s, d=d, speed=direction * v, reverse=direction < 0, material="cyclist")
            s += rng.uniform(25.0, 70.0)
    for d in (-9.6, 9.6):
        for s in rng.uniform(*span, size=4):
            add(class_id=4, size=np.array([1.7, 0.7, 1.7]), s0=float(s), d=d, speed=0.0,
                reverse=bool(rng.uniform() < 0.5), material="cyclist")
    # Pedestrians on sidewalks: two walking directions, plus standing people; some appear/disappear (doors).
    for d, direction in ((-10.6, 1), (-11.4, -1), (10.6, -1), (11.4, 1)):
        v = float(np.clip(rng.normal(1.35, 0.2), 0.8, 2.0))
        s = span[0] + rng.uniform(0, 5)
        while s < span[1]:
            size = np.array([rng.uniform(0.5, 0.9), rng.uniform(0.5, 0.8), rng.uniform(1.55, 1.9)])
            t_start, t_end = -np.inf, np.inf
            if rng.uniform() < 0.15:
                t_start = rng.uniform(0.0, 15.0)
            elif rng.uniform() < 0.1:
                t_end = rng.uniform(2.0, 18.0)
            add(class_id=2, size=size, s0=s, d=d, speed=direction * v, reverse=direction < 0, t_start=t_start,
                t_end=t_end, material="pedestrian")
            s += rng.uniform(4.0, 15.0)
    for d in (-12.0, 12.0):
        for s in rng.uniform(*span, size=10):
            add(class_id=2, size=np.array([0.6, 0.6, 1.75]), s0=float(s), d=d, speed=0.0,
                reverse=bool(rng.uniform() < 0.5), material="pedestrian")
    # Static structures: poles with signs (signs are labelled, class 3), buildings (background).
    for d in (-12.9, 12.9):
        s = span[0]
        while s < span[1]:
            s += rng.uniform(12.0, 30.0)
            add(class_id=0, size=np.array([0.3, 0.3, 3.0]), s0=s, d=d, speed=0.0, reverse=False, z_bottom=0.0,
                material="pole", labelled=False)
            if rng.uniform() < 0.6:
                add(class_id=3, size=np.array([0.12, 0.8, 0.8]), s0=s, d=d, speed=0.0, reverse=False,
                    z_bottom=3.05, material="sign")
    for side in (-1.0, 1.0):
        s = span[0]
        while s < span[1]:
            length, width = rng.uniform(8.0, 25.0), rng.uniform(6.0, 14.0)
            add(class_id=0, size=np.array([length, width, rng.uniform(5.0, 20.0)]), s0=s + length / 2,
                d=side * (14.5 + width / 2 + rng.uniform(0, 4)), speed=0.0, reverse=False, z_bottom=0.0,
                material="building", labelled=False)
            s += length + rng.uniform(3.0, 12.0)
    return road, agents


def _ego_poses(road: Road, times, ego_speed: float) -> np.ndarray:
    """Vehicle -> world [T, 4, 4] of the ego in the right lane.

    Yaw only: WOD boxes are yaw-only in the vehicle frame, so a pitching ego would tilt every labelled box by the
    ego's pitch and the labels could not hold their points exactly. The rotation code paths are still exercised by
    the rotated lidar extrinsics and by the per-pixel poses (yaw changes within a spin on curves)."""
    times = np.atleast_1d(np.asarray(times, np.float64))
    x, y, th = road.pose(ego_speed * times, -1.75)
    m = np.tile(np.eye(4), (times.size, 1, 1))
    m[:, :3, :3] = wod_format.rotation_from_rpy(np.zeros_like(th), np.zeros_like(th), th)
    m[:, 0, 3], m[:, 1, 3] = x, y
    return m


def _ego_pose(road: Road, t: float, ego_speed: float) -> np.ndarray:
    return _ego_poses(road, [t], ego_speed)[0]


def _wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _raycast(origins, dirs, max_range, boxes, origin_spread_m=1.0):
    """Nearest hit along unit rays against the ground (z = 0) and yaw-oriented boxes.

    origins, dirs: [K, 3] world; boxes: list of (index, center [3], heading, half_size [3]).
    Candidate rays per box come from an azimuth interval (rays sorted by azimuth once): a ray's horizontal projection
    must cross the box's bounding circle, widened by how far the ray origins spread (rolling shutter).
    Returns range [K] (inf = no hit) and hit id [K] (-1 ground, -2 none, else box index).
    """
    k = dirs.shape[0]
    rng = np.full(k, np.inf)
    hit = np.full(k, -2, np.int32)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(dirs[:, 2] < -1e-9, -origins[:, 2] / dirs[:, 2], np.inf)
    ground = t_ground < max_range
    rng[ground], hit[ground] = t_ground[ground], -1
    ray_az = np.arctan2(dirs[:, 1], dirs[:, 0])
    order = np.argsort(ray_az, kind="stable")
    az_sorted = ray_az[order]
    origin_xy = origins.mean(axis=0)[:2]
    for index, center, heading, half in boxes:
        rel = center[:2] - origin_xy
        dist = float(np.hypot(*rel))
        radius = float(np.hypot(half[0], half[1])) + origin_spread_m
        if dist <= radius:
            cand = np.arange(k)
        else:
            mid, width = np.arctan2(rel[1], rel[0]), np.arcsin(radius / dist)
            lo, hi = _wrap(mid - width), _wrap(mid + width)
            if lo <= hi:
                cand = order[np.searchsorted(az_sorted, lo):np.searchsorted(az_sorted, hi, "right")]
            else:
                cand = np.concatenate([order[np.searchsorted(az_sorted, lo):],
                                       order[:np.searchsorted(az_sorted, hi, "right")]])
        if cand.size == 0:
            continue
        c, s = np.cos(heading), np.sin(heading)
        rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box axes
        o = (origins[cand] - center) @ rot.T
        d = dirs[cand] @ rot.T
        d = np.where(np.abs(d) < 1e-12, 1e-12, d)
        t1, t2 = (-half - o) / d, (half - o) / d
        t_near = np.max(np.minimum(t1, t2), axis=1)
        t_far = np.min(np.maximum(t1, t2), axis=1)
        ok = (t_far >= t_near) & (t_near > 0) & (t_near < rng[cand]) & (t_near < max_range)
        rng[cand[ok]], hit[cand[ok]] = t_near[ok], index
    return rng, hit


@dataclasses.dataclass
class SegmentSpec:
    seed: int
    num_frames: int = 20
    name: str = ""
    lidar_scale: float = 1.0
    start_time_s: float = 0.0


@dataclasses.dataclass
class _FrameScene:
    """What one frame sees: time, ego pose, the agents near the ego and their world poses, which are labelled."""
    index: int
    t: float
    pose: np.ndarray  # vehicle -> world at t
    near: list  # agents within reach of the lidars
    poses_t: dict  # track_id -> (centre [3] world, heading world) at t
    labelled_now: set  # track ids with a laser label in this frame


def generate_segment(spec: SegmentSpec):
    """Yields serialized WOD `Frame` records (bytes) of one segment: scene, then per frame header, lidar images and
    laser labels."""
    from waymo_open_dataset import dataset_pb2

    rng = np.random.default_rng(spec.seed)
    ego_speed = float(rng.uniform(4.0, 9.0))
    road, agents = make_scene(rng, ego_speed)
    lidars = wod_lidars(spec.lidar_scale)
    name = spec.name or f"synthetic_seed{spec.seed}"
    t0_micros = 1_550_000_000_000_000 + spec.seed * 1_000_000_000
    prev_labelled: set[str] = set()
    for i in range(spec.num_frames):
        scene = _frame_scene(i, spec.start_time_s + i * DT_S, road, agents, ego_speed)
        frame = dataset_pb2.Frame()
        _frame_header(frame, scene, t0_micros, name, lidars)
        point_counts: dict[str, int] = {}
        for lidar in lidars:
            _write_laser(frame.lasers.add(), lidar, scene, road, ego_speed, prev_labelled, point_counts, rng)
        _laser_labels(frame, scene, road, name, point_counts)
        prev_labelled = scene.labelled_now
        yield frame.SerializeToString()


def _frame_scene(index: int, t: float, road: Road, agents: list, ego_speed: float) -> _FrameScene:
    pose = _ego_pose(road, t, ego_speed)
    ego_xy = pose[:2, 3]
    alive = [a for a in agents if a.alive(t)]
    poses_t = {a.track_id: a.pose(road, t) for a in alive}
    near = [a for a in alive if np.linalg.norm(poses_t[a.track_id][0][:2] - ego_xy) <
            TOP_MAX_RANGE_M + np.linalg.norm(a.size)]
    labelled_now = {a.track_id for a in near if a.labelled and a.class_id > 0 and
                    np.linalg.norm(poses_t[a.track_id][0][:2] - ego_xy) <= LABEL_RANGE_M}
    return _FrameScene(index, t, pose, near, poses_t, labelled_now)


def _frame_header(frame, scene: _FrameScene, t0_micros: int, name: str, lidars) -> None:
    """Timestamp, vehicle pose, segment name and every lidar's calibration."""
    frame.timestamp_micros = t0_micros + int(round(scene.t * 1e6))
    frame.pose.transform[:] = wod_format.encode_transform(scene.pose)
    frame.context.name = name
    for lidar in lidars:
        cal = frame.context.laser_calibrations.add()
        cal.name = lidar.name
        cal.extrinsic.transform[:] = wod_format.encode_transform(lidar.extrinsic)
        if lidar.beam_inclinations is not None:
            cal.beam_inclinations[:] = [float(v) for v in lidar.beam_inclinations]
        else:
            cal.beam_inclination_min, cal.beam_inclination_max = lidar.inclination_min, lidar.inclination_max


def _point_labels(scene: _FrameScene, road: Road, valid, hits, points_w, prev_labelled: set, point_counts: dict):
    """Per pixel: material, flow class and flow (m/s, vehicle frame at t) from the agent each ray hit.

    A labelled agent without a label in the previous frame (or at the first frame) gets class -1: no box at t-1.
    """
    mat = np.full(hits.shape, "ground", dtype=object)
    classes = np.zeros(hits.shape, np.int32)
    flow_v = np.zeros(hits.shape + (3,), np.float64)
    vehicle_from_world = np.linalg.inv(scene.pose)
    t_prev = scene.t - DT_S
    for j, a in enumerate(scene.near):
        sel = valid & (hits == j)
        if not sel.any():
            continue
        mat[sel] = a.material
        if a.class_id == 0 or not a.labelled or a.track_id not in scene.labelled_now:
            continue
        point_counts[a.track_id] = point_counts.get(a.track_id, 0) + int(sel.sum())
        if a.track_id not in prev_labelled or scene.index == 0 or not a.alive(t_prev):
            classes[sel] = schema.CLASS_NO_LABEL
            continue
        c0, h0 = scene.poses_t[a.track_id]
        c1, h1 = a.pose(road, t_prev)
        moved = geometry.box_matrices_np(c1, h1)[0] @ np.linalg.inv(geometry.box_matrices_np(c0, h0)[0])  # world point at t0 -> t-1
        p0 = points_w[sel]
        p1 = p0 @ moved[:3, :3].T + moved[:3, 3]
        flow_v[sel] = ((p0 - p1) / DT_S) @ vehicle_from_world[:3, :3].T
        classes[sel] = a.class_id
    return mat, classes, flow_v


def _write_laser(laser, lidar: LidarSpec, scene: _FrameScene, road: Road, ego_speed: float, prev_labelled: set,
                 point_counts: dict, rng: np.random.Generator) -> None:
    """One lidar's range images (both returns), flow images, camera projections and TOP pixel pose."""
    laser.name = lidar.name
    top_pose = _top_pixel_pose(lidar, road, ego_speed, scene.t) if lidar.name == 1 else None
    boxes = [(j, scene.poses_t[a.track_id][0], scene.poses_t[a.track_id][1], a.size / 2)
             for j, a in enumerate(scene.near)]
    ranges, hits, origins_w, dirs_w = _scan(lidar, top_pose, scene.pose, boxes)
    h, w = lidar.height, lidar.width
    valid = np.isfinite(ranges) & (ranges > 0.5)
    points_w = origins_w + dirs_w * np.where(valid, ranges, 0.0)[..., None]
    mat, classes, flow_v = _point_labels(scene, road, valid, hits, points_w, prev_labelled, point_counts)
    intensity = np.zeros(hits.shape, np.float32)
    for material, (mean, std) in _INTENSITY.items():
        sel = mat == material
        if sel.any():
            intensity[sel] = np.clip(rng.normal(mean, std, int(sel.sum())), 0.0, 1.5)
    range_img = np.full((h, w, 4), -1.0, np.float32)
    range_img[..., 0] = np.where(valid, ranges, -1.0)
    range_img[..., 1] = np.where(valid, intensity, 0.0)
    range_img[..., 2] = np.where(valid, np.clip(rng.gamma(2.0, 0.05, hits.shape), 0.0, 1.5), 0.0)
    flow_img = np.zeros((h, w, 4), np.float32)
    flow_img[..., :3] = np.where(valid[..., None], flow_v, 0.0)
    flow_img[..., 3] = np.where(valid, classes, schema.CLASS_NO_LABEL)
    ri = laser.ri_return1
    ri.range_image_compressed = wod_format.encode_matrix(range_img)
    ri.range_image_flow_compressed = wod_format.encode_matrix(flow_img)
    ri.camera_projection_compressed = wod_format.encode_matrix(np.zeros((h, w, 6), np.int32))
    if lidar.name == 1:
        ri.range_image_pose_compressed = wod_format.encode_matrix(top_pose)
    # No second returns in this scene (empty range image: all -1), written so return 2 decodes.
    empty = np.full((h, w, 4), -1.0, np.float32)
    empty[..., 1:3] = 0.0
    laser.ri_return2.range_image_compressed = wod_format.encode_matrix(empty)
    laser.ri_return2.range_image_flow_compressed = wod_format.encode_matrix(
        np.concatenate([np.zeros((h, w, 3), np.float32), np.full((h, w, 1), -1.0, np.float32)], -1))
    laser.ri_return2.camera_projection_compressed = wod_format.encode_matrix(np.zeros((h, w, 6), np.int32))


def _laser_labels(frame, scene: _FrameScene, road: Road, name: str, point_counts: dict) -> None:
    """Tracked 3D boxes (vehicle frame at t) with speed, type, track id and point count."""
    vehicle_from_world = np.linalg.inv(scene.pose)
    for a in scene.near:
        if a.track_id not in scene.labelled_now:
            continue
        center_w, heading_w = scene.poses_t[a.track_id]
        c_prev, _ = a.pose(road, scene.t - DT_S)
        label = frame.laser_labels.add()
        center_v = vehicle_from_world[:3, :3] @ center_w + vehicle_from_world[:3, 3]
        heading_v = heading_w - np.arctan2(scene.pose[1, 0], scene.pose[0, 0])
        label.box.center_x, label.box.center_y, label.box.center_z = (float(v) for v in center_v)
        label.box.length, label.box.width, label.box.height = (float(v) for v in a.size)
        label.box.heading = float(np.arctan2(np.sin(heading_v), np.cos(heading_v)))
        vel_v = vehicle_from_world[:3, :3] @ ((center_w - c_prev) / DT_S)
        label.metadata.speed_x, label.metadata.speed_y = float(vel_v[0]), float(vel_v[1])
        label.type = a.class_id  # label.proto Type uses the flow class numbers for these four types
        label.id = f"{name}_{a.track_id}"
        label.num_lidar_points_in_box = point_counts.get(a.track_id, 0)


def _column_time_offsets(width: int) -> np.ndarray:
    """Firing time of each TOP column relative to the frame timestamp: one 0.1 s spin centred on it."""
    return ((np.arange(width) + 0.5) / width - 0.5) * DT_S


def _top_pixel_pose(lidar: LidarSpec, road: Road, ego_speed: float, t: float) -> np.ndarray:
    """[H, W, 6] float32 roll, pitch, yaw, x, y, z of the ego pose at each TOP column's firing time."""
    m = _ego_poses(road, t + _column_time_offsets(lidar.width), ego_speed)
    r = m[:, :3, :3]
    rpy = np.stack([np.arctan2(r[:, 2, 1], r[:, 2, 2]), -np.arcsin(r[:, 2, 0]), np.arctan2(r[:, 1, 0], r[:, 0, 0])],
                   -1)
    per_col = np.concatenate([rpy, m[:, :3, 3]], -1).astype(np.float32)
    return np.broadcast_to(per_col[None], (lidar.height, lidar.width, 6))


def _scan(lidar: LidarSpec, top_pose, pose: np.ndarray, boxes):
    """Rays of one lidar in world coordinates and their nearest hits. Returns [H,W] range, hit id, origins, dirs."""
    h, w = lidar.height, lidar.width
    az = wod_format.column_azimuths(w, lidar.extrinsic)
    incl = wod_format.row_inclinations(h, lidar.beam_inclinations, lidar.inclination_min, lidar.inclination_max)
    d_sensor = np.stack([np.cos(az)[None, :] * np.cos(incl)[:, None], np.sin(az)[None, :] * np.cos(incl)[:, None],
                         np.broadcast_to(np.sin(incl)[:, None], (h, w))], -1)  # [H, W, 3]
    d_vehicle = d_sensor @ lidar.extrinsic[:3, :3].T
    if lidar.name == 1:
        # Rolling shutter: each column fires from the ego pose at its own time (recorded in the pixel pose).
        pix = top_pose[0]  # [W, 6] (float32, as stored)
        rot = wod_format.rotation_from_rpy(pix[:, 0].astype(np.float64), pix[:, 1].astype(np.float64),
                                           pix[:, 2].astype(np.float64))  # [W, 3, 3]
        trans = pix[:, 3:].astype(np.float64)
        dirs = np.einsum("wij,hwj->hwi", rot, d_vehicle)
        origins = np.broadcast_to((np.einsum("wij,j->wi", rot, lidar.extrinsic[:3, 3]) + trans)[None], (h, w, 3))
    else:
        dirs = d_vehicle @ pose[:3, :3].T
        origins = np.broadcast_to(pose[:3, :3] @ lidar.extrinsic[:3, 3] + pose[:3, 3], (h, w, 3))
    # Short-range lidars only return within their horizontal field of view (sensor azimuth).
    in_fov = np.broadcast_to((np.abs(np.arctan2(np.sin(az), np.cos(az))) <= lidar.half_fov_rad)[None, :], (h, w))
    flat_o, flat_d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    sel = np.nonzero(in_fov.reshape(-1))[0]
    max_range = lidar.max_range_m
    sensor_xy = flat_o[0, :2]
    near = [b for b in boxes if np.linalg.norm(b[1][:2] - sensor_xy) < max_range + np.linalg.norm(b[3]) + 1.0]
    rng_sel, hit_sel = _raycast(flat_o[sel], flat_d[sel], max_range, near,
                                origin_spread_m=float(np.ptp(flat_o[:, :2], axis=0).max()) + 0.1)
    ranges = np.full(h * w, np.inf)
    hits = np.full(h * w, -2, np.int32)
    ranges[sel], hits[sel] = rng_sel, hit_sel
    return ranges.reshape(h, w), hits.reshape(h, w), origins, dirs


def write_segment(path: str, spec: SegmentSpec) -> int:
    """Writes one segment as a TFRecord file of `Frame`s; returns the number of frames."""
    import tensorflow as tf

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    n = 0
    with tf.io.TFRecordWriter(path) as writer:
        for record in generate_segment(spec):
            writer.write(record)
            n += 1
    return n
