"""Scene-flow labels bootstrapped from tracked 3D boxes (paper Sec. 3.2 and appendix "Bootstrapping Ground Truth").

Rigid boxes, secant approximation, ego motion compensated: for a t0 box B_t0 (box -> vehicle frame at t0) whose track
has a box B_tm1 at t-1, B*_tm1 = inv(pose_t0) @ pose_tm1 @ B_tm1 and T_delta = B*_tm1 @ inv(B_t0); a point p0 inside
the t0 box gets flow (p0 - T_delta p0) / dt_s and the box's class. A point inside a box without a t-1 match gets class -1
(flow 0); every other point is background (class 0, flow 0).
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import schema

BOX_KEYS = ("center", "size", "heading", "track_id", "class_id")


def box_matrices(center: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """[K,4,4] box -> vehicle transforms (yaw-only boxes, as in WOD and AV2 cuboids up to a negligible tilt)."""
    k = len(heading)
    m = np.tile(np.eye(4), (k, 1, 1))
    c, s = np.cos(heading), np.sin(heading)
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = c, -s, s, c
    m[:, :3, 3] = center
    return m


def empty_boxes() -> dict:
    return {"center": np.zeros((0, 3)), "size": np.zeros((0, 3)), "heading": np.zeros(0),
            "track_id": np.zeros(0, dtype=str), "class_id": np.zeros(0, np.int32)}


def points_in_boxes(points_xyz: np.ndarray, boxes: dict, tolerance_m: float = 1e-4,
                    enlarge_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Index of the (first) box containing each point, -1 for none. A point on a face (within `tolerance_m`) is in.

    Vectorised per box over a candidate set: points are bucketed once into 1 m x-y cells (sorted cell keys), and
    each box tests only the points of the cells under its bounding circle (no Python loop over points).
    """
    n = len(points_xyz)
    owner = np.full(n, -1, np.int64)
    k = len(boxes["heading"])
    if n == 0 or k == 0:
        return owner
    half = (np.asarray(boxes["size"], np.float64) + np.asarray(enlarge_m, np.float64)) / 2.0 + tolerance_m
    centers = np.asarray(boxes["center"], np.float64)
    heading = np.asarray(boxes["heading"], np.float64)
    pts = np.asarray(points_xyz, np.float64)
    cell = 1.0
    radius = np.linalg.norm(half[:, :2], axis=1)
    # Mark the 1 m cells under any box's bounding circle; only points in marked cells are sorted and tested.
    lo_cell = np.floor((centers[:, :2] - radius[:, None]) / cell).astype(np.int64)  # [K,2]
    hi_cell = np.floor((centers[:, :2] + radius[:, None]) / cell).astype(np.int64)
    origin = lo_cell.min(axis=0)
    extent = hi_cell.max(axis=0) - origin + 1
    marked = np.zeros(extent, bool)
    for (ax, ay), (bx, by) in zip(lo_cell - origin, hi_cell - origin):
        marked[ax:bx + 1, ay:by + 1] = True
    ij = np.floor(pts[:, :2] / cell).astype(np.int64) - origin
    in_area = np.all((ij >= 0) & (ij < extent), axis=1)
    near = np.nonzero(in_area)[0]
    near = near[marked[ij[near, 0], ij[near, 1]]]
    span = 1 << 20  # keys ix * span + iy (cells relative to the marked area's corner)
    keys = ij[near, 0] * span + ij[near, 1]
    order = near[np.argsort(keys, kind="stable")]
    sorted_keys = np.sort(keys, kind="stable")
    for j in range(k):
        cols = np.arange(lo_cell[j, 0], hi_cell[j, 0] + 1, dtype=np.int64) - origin[0]
        lo = np.searchsorted(sorted_keys, cols * span + (lo_cell[j, 1] - origin[1]), "left")
        hi = np.searchsorted(sorted_keys, cols * span + (hi_cell[j, 1] - origin[1]), "right")
        if not np.any(hi > lo):
            continue
        cand = order[np.concatenate([np.arange(a_, b_) for a_, b_ in zip(lo, hi) if b_ > a_])]
        rel = pts[cand] - centers[j]
        c, s = np.cos(heading[j]), np.sin(heading[j])
        local_x = c * rel[:, 0] + s * rel[:, 1]
        local_y = -s * rel[:, 0] + c * rel[:, 1]
        inside = (np.abs(local_x) <= half[j, 0]) & (np.abs(local_y) <= half[j, 1]) & (np.abs(rel[:, 2]) <= half[j, 2])
        hits = cand[inside]
        hits = hits[owner[hits] < 0]  # first box wins where boxes overlap
        owner[hits] = j
    return owner


def bootstrap_flow(points_xyz_t0, boxes_t0: dict, boxes_tm1: dict, pose_t0, pose_tm1, dt_s: float, *,
                   tolerance_m: float = 1e-4, enlarge_m=(0.0, 0.0, 0.0)):
    """Per-point flow (m/s, vehicle frame at t0) and class from tracked boxes.

    Args:
      points_xyz_t0: [N,3] vehicle frame at t0.
      boxes_t0, boxes_tm1: dicts of `center` [K,3], `size` [K,3] (length along heading, width, height), `heading` [K]
        (yaw, rad), `track_id` [K] str, `class_id` [K] (1 vehicle, 2 pedestrian, 3 sign, 4 cyclist), each in the
        vehicle frame of its own time.
      pose_t0, pose_tm1: [4,4] vehicle -> world.
      dt_s: t0 - t-1 in seconds (non-zero; negative when the other frame is later).
      tolerance_m: a point this close outside a face still counts as on it (float rounding of stored points).
      enlarge_m: added to (length, width, height) before the inside test (e.g. Argoverse's 0.2 m cuboid margin).
    Returns:
      flow_mps float32 [N,3], class_id int32 [N].
    """
    if dt_s == 0:
        raise ValueError("bootstrap_flow: dt_s must be non-zero")
    pts = np.asarray(points_xyz_t0, np.float64).reshape(-1, 3)
    n = len(pts)
    flow = np.zeros((n, 3), np.float32)
    cls = np.full(n, schema.CLASS_BACKGROUND, np.int32)
    if len(boxes_t0["heading"]) == 0:
        return flow, cls
    owner = points_in_boxes(pts, boxes_t0, tolerance_m, enlarge_m)
    k = len(boxes_t0["heading"])
    b_t0 = box_matrices(np.asarray(boxes_t0["center"], np.float64), np.asarray(boxes_t0["heading"], np.float64))
    tm1_index = {str(t): i for i, t in enumerate(boxes_tm1["track_id"])}
    match = np.array([tm1_index.get(str(t), -1) for t in boxes_t0["track_id"]], np.int64)  # [K]
    # T_delta per t0 box (identity where unmatched): t0 point -> its position at t-1, in the t0 frame.
    t_delta = np.tile(np.eye(4), (k, 1, 1))
    if np.any(match >= 0):
        b_tm1 = box_matrices(np.asarray(boxes_tm1["center"], np.float64),
                             np.asarray(boxes_tm1["heading"], np.float64))
        t0_from_tm1 = np.linalg.inv(np.asarray(pose_t0, np.float64)) @ np.asarray(pose_tm1, np.float64)
        m = match >= 0
        t_delta[m] = t0_from_tm1 @ b_tm1[match[m]] @ np.linalg.inv(b_t0[m])
    inside = np.nonzero(owner >= 0)[0]
    box = owner[inside]
    matched = match[box] >= 0
    p0 = pts[inside]
    p1 = np.einsum("nij,nj->ni", t_delta[box, :3, :3], p0) + t_delta[box, :3, 3]
    flow[inside] = np.where(matched[:, None], (p0 - p1) / dt_s, 0.0)
    cls[inside] = np.where(matched, np.asarray(boxes_t0["class_id"], np.int32)[box], schema.CLASS_NO_LABEL)
    return flow, cls


def boxes_from_wod_labels(laser_labels) -> dict:
    """Boxes dict from a WOD `Frame.laser_labels` (types 1..4 kept; label.proto Type numbers equal flow classes)."""
    labels = [lb for lb in laser_labels if lb.type in schema.OBJECT_CLASSES]
    if not labels:
        return empty_boxes()
    return {
        "center": np.array([[lb.box.center_x, lb.box.center_y, lb.box.center_z] for lb in labels]),
        "size": np.array([[lb.box.length, lb.box.width, lb.box.height] for lb in labels]),
        "heading": np.array([lb.box.heading for lb in labels]),
        "track_id": np.array([lb.id for lb in labels]),
        "class_id": np.array([lb.type for lb in labels], np.int32),
    }
