"""The synthetic world behind `ff3d_tf.data.synthetic.wod`: a street scene, its agents' motion and what the lidars see.

A curved road (so agents rotate) carries agents in lanes: vehicles, pedestrians, cyclists, parked or standing for a
share, some appearing or disappearing mid-segment; poles, signs and buildings line it. The ego vehicle drives the right
lane. Lidar rays (`scan`, rolling shutter for TOP) are cast against the ground plane and the yaw-oriented boxes.

Ground truth comes from the simulator's own kinematics: per pixel, flow in the paper's convention (`point_labels`: m/s,
motion t-1 -> t0 of the world point under the object's true rigid motion, in the vehicle frame at t0, ego motion
removed); per tracked box, velocity and acceleration of its trajectory (`box_motion`). Speeds follow the paper's
dataset figure (moving means near 5.6, 1.3 and 3.8 m/s for vehicles, pedestrians, cyclists).

This is the default profile's world and scan (`realism.IDEAL`). The realistic profile builds on its parts: the city
world (`synthetic.city`: agents on `traffic.Track`s, porous vegetation, the road's `ground` a height field) held in a
`World`, and the timed scan of `synthetic.lidar` (`slab_interval`, `RaysByAzimuth` shared with `_raycast`).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ff3d_tf import geometry, schema
from ff3d_tf.data.wod import wod_format

DT_S = 0.1  # frame interval (Waymo Open Dataset paper and Argoverse 2 paper: lidars at 10 Hz)
TOP_MAX_RANGE_M = 75.0  # Waymo Open Dataset paper: the top lidar's range truncated to 75 m
LABEL_RANGE_M = 75.0
BOX_LIFT_M = 0.02  # agents float 2 cm above the ground: ground returns are never on a box face


@dataclasses.dataclass(frozen=True)
class LidarSpec:
    """One simulated lidar: its range image size, mounting and beams (what `scan` casts and the writer calibrates)."""

    name: int
    height: int
    width: int
    extrinsic: np.ndarray  # 4x4 sensor -> vehicle
    max_range_m: float
    beam_inclinations: np.ndarray | None  # ascending (explicit, TOP)
    inclination_min: float = 0.0
    inclination_max: float = 0.0
    half_fov_rad: float = np.pi  # azimuth half-width with returns (short-range lidars see ~200 degrees)


class Road:
    """Centreline by arc length: piecewise-constant curvature, tabulated every 0.1 m.

    `radius_range_m` bounds the curves' radii; with `max_heading_rad` (the city world) each curve after the first
    turns back towards the road's heading at s = 0 and no further than that bound from it, so a long road never
    winds back onto itself."""

    def __init__(self, rng: np.random.Generator, s_min=-400.0, s_max=600.0, radius_range_m=(35.0, 90.0),
                 max_heading_rad: float | None = None):
        self.ds = 0.1
        self.s = np.arange(s_min, s_max, self.ds)
        kappa = np.zeros_like(self.s)
        start, heading = 20.0, 0.0
        while start < s_max:
            length = rng.uniform(25.0, 60.0)
            radius = rng.uniform(*radius_range_m) * rng.choice([-1.0, 1.0])
            if max_heading_rad is not None:
                radius = abs(radius) * -np.sign(heading) if heading else radius
                length = min(length, (max_heading_rad - heading * np.sign(radius)) * abs(radius))
                heading += length / radius
            kappa[(self.s >= start) & (self.s < start + length)] = 1.0 / radius
            start += length + rng.uniform(30.0, 80.0)
        self.kappa = kappa  # curvature (1/m) at each tabulated s
        self.ground = None  # the ground's height field (`city.Terrain`); None: flat at z = 0
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

    def ground_height(self, x, y) -> np.ndarray:
        """World z of the ground under world (x, y) (arrays broadcast): 0 on the flat street world."""
        if self.ground is None:
            return np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)
        return self.ground.height(x, y)


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
    # The city world (`synthetic.city`): a `traffic.Track` replaces s0 + speed t (z_bottom is then its lift above
    # the ground), an Argoverse category other than its class's, and porous volumes (vegetation): the extinction
    # coefficient of a ray inside (0: solid).
    track: object = None
    category: str | None = None
    extinction_per_m: float = 0.0
    _standing_pose: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    def alive(self, t: float) -> bool:
        return self.t_start <= t <= self.t_end

    def pose(self, road: Road, t: float) -> tuple[np.ndarray, float]:
        if self.track is not None:
            centres, headings = self.track.poses(road, [t], self.size)
            return centres[0], float(headings[0])
        if self.speed == 0.0:  # a standing agent: computed once
            if self._standing_pose is None:
                x, y, th = road.pose(self.s0, self.d)
                self._standing_pose = (np.array([x, y, self.z_bottom + self.size[2] / 2]),
                                       th + (np.pi if self.reverse else 0.0))
            return self._standing_pose[0].copy(), self._standing_pose[1]
        x, y, th = road.pose(self.s0 + self.speed * t, self.d)
        return np.array([x, y, self.z_bottom + self.size[2] / 2]), th + (np.pi if self.reverse else 0.0)

    def poses(self, road: Road, times) -> tuple[np.ndarray, np.ndarray]:
        """World box centres [M, 3] and headings [M] at `times` [M] (`pose` at each)."""
        times = np.atleast_1d(np.asarray(times, np.float64))
        if self.track is not None:
            return self.track.poses(road, times, self.size)
        x, y, th = road.pose(self.s0 + self.speed * times, self.d)
        centres = np.stack([x, y, np.full(times.shape, self.z_bottom + self.size[2] / 2)], -1)
        return centres, th + (np.pi if self.reverse else 0.0)

    def moves(self) -> bool:
        return self.track is not None or self.speed != 0.0

    def max_speed_mps(self, road: Road) -> float:
        """A bound on the speed of the box centre (m/s): along-road speed stretched by a curve's offset lanes."""
        stretch = 1.0 + float(np.abs(road.kappa).max()) * (abs(self.d) + 5.0)
        return (self.track.max_speed_mps() if self.track is not None else abs(self.speed)) * stretch


MATERIAL_INTENSITY = {"ground": (0.08, 0.03), "building": (0.22, 0.06), "pole": (0.3, 0.05), "sign": (0.9, 0.05),
              "vehicle": (0.45, 0.15), "pedestrian": (0.15, 0.05), "cyclist": (0.3, 0.08),
              "vegetation": (0.35, 0.1), "trunk": (0.2, 0.05)}


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


def ego_poses(road: Road, times, ego_speed: float) -> np.ndarray:
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


def ego_pose(road: Road, t: float, ego_speed: float) -> np.ndarray:
    """`ego_poses` at one time, [4, 4]."""
    return ego_poses(road, [t], ego_speed)[0]


@dataclasses.dataclass
class World:
    """What a generator draws from: the road, the agents, and the ego's motion (the street world: `ego_speed` in the
    right lane, `ego_poses`; the city world, `synthetic.city`: a `traffic.Track`, yaw-only poses on the ground)."""

    road: Road
    agents: list
    ego_speed: float = 0.0
    ego_track: object = None
    intersections: tuple = ()  # road s of the city world's intersections (side streets on both sides)
    _coarse: tuple | None = dataclasses.field(default=None, repr=False, compare=False)

    def ego_poses(self, times) -> np.ndarray:
        """Vehicle -> world [T, 4, 4] at `times` (s)."""
        if self.ego_track is None:
            return ego_poses(self.road, times, self.ego_speed)
        times = np.atleast_1d(np.asarray(times, np.float64))
        s, d, h = self.ego_track.path.at(self.ego_track.progress(times))
        x, y, th = self.road.pose(s, d)
        m = np.tile(np.eye(4), (times.size, 1, 1))
        m[:, :3, :3] = wod_format.rotation_from_rpy(np.zeros_like(th), np.zeros_like(th), th + h)
        m[:, 0, 3], m[:, 1, 3], m[:, 2, 3] = x, y, self.road.ground_height(x, y)
        return m

    def frame_scene(self, index: int, t: float) -> "FrameScene":
        """`frame_scene` at time t with this world's ego pose. In the city world, only the agents whose coarse
        track (every 0.5 s) comes within reach of the ego are posed exactly."""
        pose = self.ego_poses([t])[0]
        agents = self.agents
        if self.ego_track is not None and self.agents:
            agents = [self.agents[i] for i in self._within_reach(t, pose[:2, 3])]
        return frame_scene(index, t, self.road, agents, self.ego_speed, pose)

    def _within_reach(self, t: float, ego_xy: np.ndarray) -> np.ndarray:
        if self._coarse is None:
            times = self.ego_track.times[::10]
            xy = np.empty((len(self.agents), len(times), 2))
            for i, a in enumerate(self.agents):
                xy[i] = a.poses(self.road, times)[0][:, :2] if a.moves() else a.pose(self.road, 0.0)[0][:2]
            margin = np.array([np.linalg.norm(a.size) + a.max_speed_mps(self.road) * 0.5 for a in self.agents])
            self._coarse = (times, xy, margin)
        times, xy, margin = self._coarse
        g = int(np.clip(np.searchsorted(times, t), 0, len(times) - 1))
        g = g if g == 0 or abs(times[g] - t) < abs(times[g - 1] - t) else g - 1
        dist = np.linalg.norm(xy[:, g] - ego_xy, axis=1)
        return np.flatnonzero(dist < TOP_MAX_RANGE_M + margin + 5.0)


def _wrap(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def slab_interval(origins_box, dirs_box, half) -> tuple[np.ndarray, np.ndarray]:
    """(t_near, t_far) [K] of rays [K, 3] in a box's own axes against the box of half extents `half` [3] (or [K, 3])
    centred at the origin: the ray is inside for t_near <= t <= t_far (no crossing when t_far < t_near)."""
    d = np.where(np.abs(dirs_box) < 1e-12, 1e-12, dirs_box)
    t1, t2 = (-half - origins_box) / d, (half - origins_box) / d
    return np.max(np.minimum(t1, t2), axis=1), np.min(np.maximum(t1, t2), axis=1)


class RaysByAzimuth:
    """Unit rays sorted by azimuth once, to find those whose horizontal projection can cross a circle."""

    def __init__(self, dirs: np.ndarray):
        self.count = dirs.shape[0]
        ray_az = np.arctan2(dirs[:, 1], dirs[:, 0])
        self.order = np.argsort(ray_az, kind="stable")
        self.az_sorted = ray_az[self.order]

    def candidates(self, rel_xy, radius: float) -> np.ndarray:
        """Indices of the rays (from an origin near (0, 0)) whose azimuth lies within the circle of `radius` at
        `rel_xy`; all rays when the origin is inside it."""
        dist = float(np.hypot(*rel_xy))
        if dist <= radius:
            return np.arange(self.count)
        mid, width = np.arctan2(rel_xy[1], rel_xy[0]), np.arcsin(radius / dist)
        lo, hi = _wrap(mid - width), _wrap(mid + width)
        order, az_sorted = self.order, self.az_sorted
        if lo <= hi:
            return order[np.searchsorted(az_sorted, lo):np.searchsorted(az_sorted, hi, "right")]
        return np.concatenate([order[np.searchsorted(az_sorted, lo):],
                               order[:np.searchsorted(az_sorted, hi, "right")]])


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
    by_azimuth = RaysByAzimuth(dirs)
    origin_xy = origins.mean(axis=0)[:2]
    for index, center, heading, half in boxes:
        cand = by_azimuth.candidates(center[:2] - origin_xy, float(np.hypot(half[0], half[1])) + origin_spread_m)
        if cand.size == 0:
            continue
        c, s = np.cos(heading), np.sin(heading)
        rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box axes
        t_near, t_far = slab_interval((origins[cand] - center) @ rot.T, dirs[cand] @ rot.T, half)
        ok = (t_far >= t_near) & (t_near > 0) & (t_near < rng[cand]) & (t_near < max_range)
        rng[cand[ok]], hit[cand[ok]] = t_near[ok], index
    return rng, hit


@dataclasses.dataclass
class FrameScene:
    """What one frame sees: time, ego pose, the agents near the ego and their world poses, which are labelled."""
    index: int
    t: float
    pose: np.ndarray  # vehicle -> world at t
    near: list  # agents within reach of the lidars
    poses_t: dict  # track_id -> (centre [3] world, heading world) at t
    labelled_now: set  # track ids with a laser label in this frame


def frame_scene(index: int, t: float, road: Road, agents: list, ego_speed: float, pose=None) -> FrameScene:
    """The scene of frame `index` at time `t`: agents alive and within lidar reach, those labelled (class > 0, within
    LABEL_RANGE_M). `pose`: the ego pose at t (default: the street world's, `ego_pose`)."""
    pose = ego_pose(road, t, ego_speed) if pose is None else pose
    ego_xy = pose[:2, 3]
    alive = [a for a in agents if a.alive(t)]
    poses_t = {a.track_id: a.pose(road, t) for a in alive}
    near = [a for a in alive if np.linalg.norm(poses_t[a.track_id][0][:2] - ego_xy) <
            TOP_MAX_RANGE_M + np.linalg.norm(a.size)]
    labelled_now = {a.track_id for a in near if a.labelled and a.class_id > 0 and
                    np.linalg.norm(poses_t[a.track_id][0][:2] - ego_xy) <= LABEL_RANGE_M}
    return FrameScene(index, t, pose, near, poses_t, labelled_now)


def point_labels(scene: FrameScene, road: Road, valid, hits, points_w, prev_labelled: set, point_counts: dict):
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
        # world point at t0 -> t-1
        moved = geometry.box_matrices_np(c1, h1)[0] @ np.linalg.inv(geometry.box_matrices_np(c0, h0)[0])
        p0 = points_w[sel]
        p1 = p0 @ moved[:3, :3].T + moved[:3, 3]
        flow_v[sel] = ((p0 - p1) / DT_S) @ vehicle_from_world[:3, :3].T
        classes[sel] = a.class_id
    return mat, classes, flow_v


def box_motion(agent: Agent, road: Road, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(velocity [3] m/s, acceleration [3] m/s^2) in the world frame of an agent's box centre at `t`, by backward
    differences over DT_S of its trajectory: velocity from t-DT_S to t, acceleration from the velocity at t-DT_S to
    the one at t (as the tracked boxes of consecutive frames give them)."""
    c0, c1, c2 = (agent.pose(road, t - k * DT_S)[0] for k in range(3))
    velocity = (c0 - c1) / DT_S
    return velocity, (velocity - (c1 - c2) / DT_S) / DT_S


def column_time_offsets(width: int) -> np.ndarray:
    """Firing time of each TOP column relative to the frame timestamp: one 0.1 s spin centred on it."""
    return ((np.arange(width) + 0.5) / width - 0.5) * DT_S


def top_pixel_pose(lidar: LidarSpec, road: Road, ego_speed: float, t: float) -> np.ndarray:
    """[H, W, 6] float32 roll, pitch, yaw, x, y, z of the ego pose at each TOP column's firing time."""
    return pixel_pose_of(lidar, ego_poses(road, t + column_time_offsets(lidar.width), ego_speed))


def pixel_pose_of(lidar: LidarSpec, m: np.ndarray) -> np.ndarray:
    """[H, W, 6] float32 range image pose (schema.TOP_POSE_CHANNELS) of the vehicle -> world poses [W, 4, 4] of the
    columns."""
    r = m[:, :3, :3]
    rpy = np.stack([np.arctan2(r[:, 2, 1], r[:, 2, 2]), -np.arcsin(r[:, 2, 0]), np.arctan2(r[:, 1, 0], r[:, 0, 0])],
                   -1)
    per_col = np.empty((lidar.width, len(schema.TOP_POSE_CHANNELS)), np.float32)
    per_col[:, schema.TOP_POSE_ROTATION], per_col[:, schema.TOP_POSE_TRANSLATION] = rpy, m[:, :3, 3]
    return np.broadcast_to(per_col[None], (lidar.height, lidar.width, len(schema.TOP_POSE_CHANNELS)))


def scan(lidar: LidarSpec, top_pose, pose: np.ndarray, boxes):
    """Rays of one lidar in world coordinates and their nearest hits. Returns [H,W] range, hit id, origins, dirs."""
    h, w = lidar.height, lidar.width
    az = wod_format.column_azimuths(w, lidar.extrinsic)
    incl = wod_format.row_inclinations(h, lidar.beam_inclinations, lidar.inclination_min, lidar.inclination_max)
    d_sensor = np.stack([np.cos(az)[None, :] * np.cos(incl)[:, None], np.sin(az)[None, :] * np.cos(incl)[:, None],
                         np.broadcast_to(np.sin(incl)[:, None], (h, w))], -1)  # [H, W, 3]
    d_vehicle = d_sensor @ lidar.extrinsic[:3, :3].T
    if lidar.name == 1:
        # Rolling shutter: each column fires from the ego pose at its own time (recorded in the pixel pose).
        pix = top_pose[0].astype(np.float64)  # [W, 6] schema.TOP_POSE_CHANNELS (float32 values, as stored)
        rot = wod_format.rotation_from_rpy(*(pix[:, schema.TOP_POSE_CHANNEL[c]] for c in ("roll", "pitch", "yaw")))
        trans = pix[:, schema.TOP_POSE_TRANSLATION]
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

