"""The realistic profile's lidar (`realism.REALISTIC`): each column of a range image fired at its own time from the
ego pose at that time, against the objects where they are then, the ground's height field and porous vegetation;
then what the sensor adds (`realism.measure`: range noise, dropped returns).

Firing times: a spinning lidar turns once per 0.1 s (Argoverse 2 paper: VLP-32C at 10 Hz; Waymo Open Dataset paper:
10 Hz). Column c of W looks at vehicle azimuth ((W - c - 0.5) / W * 2 - 1) * pi (`wod_format.column_azimuths`) and
fires at share (c + 0.5) / W of the turn (`firing_share`): azimuth falls as time goes, a clockwise spin seen from above.
Each format places the turn in time: Argoverse 2 from the sweep timestamp on (offset_ns in [0, 0.1 s), av2-api's
`Sweep`: "offsets from the start of the sweep"), WOD centred on the frame timestamp (`scene.column_time_offsets`).

Annotation time: the boxes a generator writes for an object are where the object was when the main lidar (Argoverse
2's up lidar, WOD's TOP) swept over its centre (`annotation_times`), as an annotator fits a box to the points of the
ego-motion compensated sweep; so a moving object's points lie in its box up to the time the spin takes across it and
the noise (the box is grown by `Realism.box_margin_m`); points of another lidar that sees it at another time (the
down lidar spins the other way; the short-range WOD lidars) are displaced by the object's motion in between.
"""
from __future__ import annotations

import numpy as np

from ff3d_tf.data.synthetic import realism as realism_lib
from ff3d_tf.data.synthetic import scene as sim
from ff3d_tf.data.wod import wod_format


def firing_share(azimuth_vehicle_rad) -> np.ndarray:
    """Share of the turn (0..1) at which an upright lidar's column looking at this vehicle-frame azimuth fires."""
    return ((1.0 - np.asarray(azimuth_vehicle_rad, np.float64) / np.pi) / 2.0) % 1.0


def annotation_times(frame_t: float, pose: np.ndarray, centres_world: np.ndarray, spin_offset) -> np.ndarray:
    """[N] time at which the main lidar swept over each box centre [N, 3] (world, at frame_t): frame_t plus
    `spin_offset(share)` (seconds) of the firing share of its azimuth in the vehicle frame of `pose`."""
    rel = (np.asarray(centres_world, np.float64).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]
    return frame_t + spin_offset(firing_share(np.arctan2(rel[:, 1], rel[:, 0])))


def label_box(road: sim.Road, agent, frame_t: float, pose: np.ndarray, spin_offset, margin_m: float,
              motion_distortion: bool = True) -> tuple[np.ndarray, float, np.ndarray]:
    """(centre [3] world, heading, size [3]) of the box an annotator draws for `agent` in the frame at `frame_t`
    (ego pose `pose`): the agent at its annotation time (`annotation_times`; the frame time without motion
    distortion), grown by `margin_m` on each side and on top (its bottom stays on the object's)."""
    centre, heading = agent.pose(road, frame_t)
    if motion_distortion:
        tau = float(annotation_times(frame_t, pose, centre[None], spin_offset)[0])
        centre, heading = agent.pose(road, tau)
    grown = np.asarray(agent.size, np.float64) + np.array([2 * margin_m, 2 * margin_m, margin_m])
    return centre + np.array([0.0, 0.0, margin_m / 2]), heading, grown


def points_in_box(points_world: np.ndarray, centre: np.ndarray, heading: float, size: np.ndarray,
                  tolerance_m: float = 1e-4, enlarge_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """[N] bool: world points [N, 3] inside a yaw box (a point within `tolerance_m` outside a face is inside;
    `enlarge_m` is added to (length, width, height) first, as Argoverse's labels do)."""
    c, s = np.cos(heading), np.sin(heading)
    rel = np.asarray(points_world, np.float64) - centre
    half = (np.asarray(size, np.float64) + np.asarray(enlarge_m, np.float64)) / 2 + tolerance_m
    return ((np.abs(c * rel[:, 0] + s * rel[:, 1]) <= half[0]) & (np.abs(-s * rel[:, 0] + c * rel[:, 1]) <= half[1])
            & (np.abs(rel[:, 2]) <= half[2]))


class PointsByX:
    """World points sorted by x once, for `inside` queries of many boxes."""

    def __init__(self, points_world: np.ndarray):
        self.points = np.asarray(points_world, np.float64)
        self.order = np.argsort(self.points[:, 0], kind="stable")
        self.x_sorted = self.points[self.order, 0]

    def inside(self, centre, heading, size, tolerance_m: float = 1e-4, enlarge_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Indices (ascending) of the points `points_in_box` holds in the box."""
        reach = float(np.hypot(size[0] + enlarge_m[0], size[1] + enlarge_m[1])) / 2 + tolerance_m + 1e-6
        lo, hi = np.searchsorted(self.x_sorted, [centre[0] - reach, centre[0] + reach])
        cand = np.sort(self.order[lo:hi])
        return cand[points_in_box(self.points[cand], centre, heading, size, tolerance_m, enlarge_m)]


def _ground(road: sim.Road, origins, dirs, max_range) -> np.ndarray:
    if road.ground is not None:
        return road.ground.intersect(origins, dirs, max_range)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(dirs[:, 2] < -1e-9, -origins[:, 2] / dirs[:, 2], np.inf)


def cast(origins: np.ndarray, dirs: np.ndarray, ray_times: np.ndarray, max_range: float, near: list,
         road: sim.Road, rng: np.random.Generator, t_ref: float,
         centres_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest surface along unit rays [K, 3] (world) fired at `ray_times` [K]: the ground, the solid boxes of the
    agents `near` posed at each ray's time, and porous boxes (agents with `extinction_per_m`), which a ray crossing a
    chord L returns from with probability 1 - exp(-extinction L), at an exponentially distributed depth.
    `centres_ref` [N, 3]: the agents' centres at time `t_ref` (to find the rays that may meet them).
    Returns range [K] (inf: no surface) and hit [K] (-1 ground, -2 none, else the index into `near`)."""
    k = dirs.shape[0]
    ranges = np.full(k, np.inf)
    hit = np.full(k, -2, np.int32)
    t_ground = _ground(road, origins, dirs, max_range)
    on_ground = t_ground < max_range
    ranges[on_ground], hit[on_ground] = t_ground[on_ground], -1
    by_azimuth = sim.RaysByAzimuth(dirs)
    origin_xy = origins.mean(axis=0)[:2]
    spread = float(np.ptp(origins[:, :2], axis=0).max()) + 0.1
    reach_s = float(np.max(np.abs(ray_times - t_ref)))
    porous = []
    for j, agent in enumerate(near):
        half = agent.size / 2
        moving = agent.moves()
        radius = float(np.hypot(half[0], half[1])) + spread + 0.1
        if moving:
            radius += agent.max_speed_mps(road) * reach_s
        cand = by_azimuth.candidates(centres_ref[j][:2] - origin_xy, radius)
        if cand.size == 0:
            continue
        if moving:
            times, inverse = np.unique(ray_times[cand], return_inverse=True)
            centres, headings = agent.poses(road, times)
            centre, heading = centres[inverse], headings[inverse]
        else:
            c, h = agent.pose(road, t_ref)
            centre, heading = np.broadcast_to(c, (cand.size, 3)), np.full(cand.size, h)
        t_near, t_far = _slab_world(origins[cand], dirs[cand], centre, heading, half)
        if agent.extinction_per_m > 0:
            porous.append((j, agent.extinction_per_m, cand, t_near, t_far))
            continue
        ok = (t_far >= t_near) & (t_near > 0) & (t_near < ranges[cand]) & (t_near < max_range)
        ranges[cand[ok]], hit[cand[ok]] = t_near[ok], j
    for j, extinction, cand, t_near, t_far in porous:
        entry, leave = np.maximum(t_near, 0.0), np.minimum(t_far, max_range)
        chord = np.maximum(leave - entry, 0.0)
        u = rng.uniform(size=cand.size)
        returned = u < 1.0 - np.exp(-extinction * chord)
        depth = entry - np.log1p(-np.where(returned, u, 0.0)) / extinction
        ok = returned & (depth < ranges[cand])
        ranges[cand[ok]], hit[cand[ok]] = depth[ok], j
    return ranges, hit


def _slab_world(origins, dirs, centres, headings, half) -> tuple[np.ndarray, np.ndarray]:
    """`scene.slab_interval` of rays [M, 3] against yaw boxes posed per ray (centres [M, 3], headings [M])."""
    c, s = np.cos(headings), np.sin(headings)
    rel = origins - centres
    o_box = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], -1)
    d_box = np.stack([c * dirs[:, 0] + s * dirs[:, 1], -s * dirs[:, 0] + c * dirs[:, 1], dirs[:, 2]], -1)
    return sim.slab_interval(o_box, d_box, half)


def scan(lidar: sim.LidarSpec, column_times: np.ndarray, column_poses: np.ndarray, scene: sim.FrameScene,
         road: sim.Road, rng: np.random.Generator, motion_distortion: bool = True):
    """Rays of one lidar, column w fired at `column_times[w]` from the vehicle -> world pose `column_poses[w]`, and
    their nearest surfaces among the ground and the agents of `scene.near` (`cast`; with `motion_distortion` False
    every ray sees the agents at the frame's time). Returns [H, W] range (inf: none), hit id (index into scene.near,
    -1 ground, -2 none), and [H, W, 3] world origins and unit directions."""
    h, w = lidar.height, lidar.width
    az = wod_format.column_azimuths(w, lidar.extrinsic)
    incl = wod_format.row_inclinations(h, lidar.beam_inclinations, lidar.inclination_min, lidar.inclination_max)
    d_sensor = np.stack([np.cos(az)[None, :] * np.cos(incl)[:, None], np.sin(az)[None, :] * np.cos(incl)[:, None],
                         np.broadcast_to(np.sin(incl)[:, None], (h, w))], -1)  # [H, W, 3]
    d_vehicle = d_sensor @ lidar.extrinsic[:3, :3].T
    rot, trans = column_poses[:, :3, :3], column_poses[:, :3, 3]
    dirs = np.einsum("wij,hwj->hwi", rot, d_vehicle)
    origins = np.broadcast_to((np.einsum("wij,j->wi", rot, lidar.extrinsic[:3, 3]) + trans)[None], (h, w, 3))
    in_fov = np.broadcast_to((np.abs(np.arctan2(np.sin(az), np.cos(az))) <= lidar.half_fov_rad)[None, :], (h, w))
    times = np.broadcast_to(np.asarray(column_times, np.float64)[None, :], (h, w))
    if not motion_distortion:
        times = np.full((h, w), scene.t)
    sel = np.flatnonzero(in_fov.reshape(-1))
    flat_o, flat_d, flat_t = origins.reshape(-1, 3)[sel], dirs.reshape(-1, 3)[sel], times.reshape(-1)[sel]
    sensor_xy = flat_o.mean(axis=0)[:2] if len(sel) else np.zeros(2)
    centres = np.array([scene.poses_t[a.track_id][0] for a in scene.near]).reshape(-1, 3)
    reach = lidar.max_range_m + 30.0 + np.linalg.norm([a.size for a in scene.near], axis=1) if scene.near else 0.0
    close = np.flatnonzero(np.linalg.norm(centres[:, :2] - sensor_xy, axis=1) < reach)
    ranges = np.full(h * w, np.inf)
    hits = np.full(h * w, -2, np.int32)
    if len(sel):
        r, hit = cast(flat_o, flat_d, flat_t, lidar.max_range_m, [scene.near[j] for j in close], road, rng, scene.t,
                      centres[close])
        mapped = np.concatenate([close, [-2, -1]]).astype(np.int32)
        ranges[sel], hits[sel] = r, mapped[hit]  # hit -1 / -2 index the last two entries
    return ranges.reshape(h, w), hits.reshape(h, w), origins, dirs


def reflectivity_of(hits: np.ndarray, near: list) -> np.ndarray:
    """Mean reflectivity (`scene.MATERIAL_INTENSITY`) of the surface each ray hit (ground for -1 and -2)."""
    table = np.array([sim.MATERIAL_INTENSITY[a.material][0] for a in near] + [sim.MATERIAL_INTENSITY["ground"][0]] * 2)
    return table[hits]


def measure_scan(rng: np.random.Generator, ranges: np.ndarray, hits: np.ndarray, near: list,
                 realism: realism_lib.Realism) -> tuple[np.ndarray, np.ndarray]:
    """(measured range, returned) of a scan's true ranges: `realism.measure` with each surface's reflectivity."""
    return realism_lib.measure(rng, ranges, reflectivity_of(hits, near), realism)
