"""Argoverse 2 sweeps under a realism profile (`synthetic.realism`), the parts `synthetic.av2` adds for them.

A sweep (`scan_sweep`): both stacked lidars turn once from the sweep timestamp on, each column at its offset
`offset_ns` (the share of the turn, shifted by the lidar's phase; the down lidar, mounted upside down, turns the
other way in the ego frame), fired from the ego pose at timestamp + offset against the world at that time
(`synthetic.lidar`), measured with noise and dropped returns. The points are then written as Argoverse 2 writes them:
"egomotion-compensated to the egovehicle reference timestamp" (av2-api, `av2.structures.sweep.Sweep`): each world
point in the ego frame at the sweep timestamp. So a static surface is where it is, and a moving object is where it
was when each ray reached it: its points are spread by its motion over the time the lidars take across it.

The cuboids (`cuboid_box`) are the boxes an annotator fits to the up lidar's points (`lidar.label_box`): each object
where it was when the up lidar swept over its centre, grown by the profile's margin, in the ego frame of the sweep
timestamp; their `num_interior_pts` count the stored points inside. The flow labels of sweep 0 (`argoverse_flow`)
follow Argoverse's rule on those cuboids: a point inside a cuboid enlarged by `argoverse2.CUBOID_MARGIN_M` (the last
such cuboid of the file) moves with it to its track's cuboid at sweep 1, every other point with the ego motion only.
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import geometry
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.synthetic import lidar as lidar_lib
from ff3d_tf.data.synthetic import scene as sim


def scan_sweep(lidars, beam_inclinations, width: int, scene: sim.FrameScene, world_from_ego_at, road: sim.Road,
               rng: np.random.Generator, realism, period_ns: int, max_range_m: float, min_range_m: float):
    """Every return of the stacked lidars in the sweep at `scene.t`: world points [N, 3] (where each ray met its
    surface, at its firing time), hit ids [N] (index into `scene.near`, -1 ground), laser numbers [N] and offset_ns
    [N] (int64)."""
    out = []
    height = len(beam_inclinations)
    for lidar in lidars:
        spec = sim.LidarSpec(name=2, height=height, width=width, extrinsic=lidar.extrinsic(), max_range_m=max_range_m,
                             beam_inclinations=beam_inclinations)
        turn = ((np.arange(width) + 0.5) / width + lidar.spin_phase) % 1.0
        offset_ns = np.round(turn * period_ns).astype(np.int64)
        column_times = scene.t + offset_ns * 1e-9
        ranges, hits, origins, dirs = lidar_lib.scan(spec, column_times, world_from_ego_at(column_times), scene, road,
                                                     rng, realism.motion_distortion)
        measured, returned = lidar_lib.measure_scan(rng, ranges, hits, scene.near, realism)
        valid = returned & (measured > min_range_m)
        rows, cols = np.nonzero(valid)
        points = origins[rows, cols] + dirs[rows, cols] * measured[rows, cols][:, None]
        # Row 0 is the highest beam (wod_format.row_inclinations); laser numbers go up with inclination.
        out.append((points, hits[rows, cols], lidar.first_laser + (height - 1 - rows), offset_ns[cols]))
    return [np.concatenate(parts) for parts in zip(*out)]


def up_lidar_offset_s(spin_phase: float, period_ns: int):
    """The up lidar's firing offset (s after the sweep timestamp) as a function of the share of its turn."""
    return lambda share: ((np.asarray(share) + spin_phase) % 1.0) * period_ns * 1e-9


def cuboid_box(road: sim.Road, agent, t_sweep: float, world_from_ego: np.ndarray, spin_offset, realism):
    """(centre [3], yaw, size [3]) of an agent's cuboid in the ego frame at the sweep timestamp (module docstring)."""
    centre_w, heading_w, size = lidar_lib.label_box(road, agent, t_sweep, world_from_ego, spin_offset,
                                                    realism.box_margin_m, realism.motion_distortion)
    ego_from_world = np.linalg.inv(world_from_ego)
    centre = ego_from_world[:3, :3] @ centre_w + ego_from_world[:3, 3]
    ego_yaw = np.arctan2(world_from_ego[1, 0], world_from_ego[0, 0])
    return centre, float(np.arctan2(np.sin(heading_w - ego_yaw), np.cos(heading_w - ego_yaw))), size


def _row_box(row: dict) -> tuple[np.ndarray, float, np.ndarray]:
    yaw = float(geometry.yaw_from_quaternion_np(row["qw"], row["qx"], row["qy"], row["qz"]))
    return (np.array([row["tx_m"], row["ty_m"], row["tz_m"]]), yaw,
            np.array([row["length_m"], row["width_m"], row["height_m"]]))


def argoverse_flow(points_ego0: np.ndarray, rows0: list, rows1: list, city_from_ego0: np.ndarray,
                   city_from_ego1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(flow [N, 3] metres, Argoverse's convention: the point at sweep 1 in the sweep-1 ego frame minus the point;
    owner [N]: index into `rows0` of the cuboid the point moved with, -1 none) of sweep-0 points by Argoverse's
    cuboid rule (module docstring). `rows0`, `rows1`: the annotation rows of the two sweeps, in file order."""
    p0 = np.asarray(points_ego0, np.float64)
    owner = np.full(len(p0), -1, np.int64)
    by_x = lidar_lib.PointsByX(p0)
    for i in range(len(rows0) - 1, -1, -1):  # the last cuboid of the file first: it keeps the points it holds
        centre, yaw, size = _row_box(rows0[i])
        inside = by_x.inside(centre, yaw, size, enlarge_m=argoverse2.CUBOID_MARGIN_M)
        owner[inside[owner[inside] < 0]] = i
    ego1_from_city = np.linalg.inv(city_from_ego1)
    moved = geometry.transform_points_np(p0, ego1_from_city @ city_from_ego0)  # ego motion only
    next_box = {r["track_uuid"]: r for r in rows1}
    for i in np.unique(owner[owner >= 0]):
        nxt = next_box.get(rows0[i]["track_uuid"])
        if nxt is None:
            continue
        sel = owner == i
        b0 = city_from_ego0 @ geometry.box_matrices_np(*_row_box(rows0[i])[:2])[0]
        b1 = city_from_ego1 @ geometry.box_matrices_np(*_row_box(nxt)[:2])[0]
        moved[sel] = geometry.transform_points_np(p0[sel], ego1_from_city @ b1 @ np.linalg.inv(b0) @ city_from_ego0)
    return moved - p0, owner
