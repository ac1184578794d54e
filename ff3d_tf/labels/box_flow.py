"""Scene-flow labels bootstrapped from tracked 3D boxes (paper Sec. 3.2 and appendix "Bootstrapping Ground Truth").

Rigid boxes, secant approximation, ego motion compensated: for a t0 box B_t0 (box -> vehicle frame at t0) whose track
has a box B_tm1 at t-1, B*_tm1 = inv(pose_t0) @ pose_tm1 @ B_tm1 and T_delta = B*_tm1 @ inv(B_t0); a point p0 inside
the t0 box gets flow (p0 - T_delta p0) / dt_s and the box's class. A point inside a box without a t-1 match gets class -1
(flow 0); every other point is background (class 0, flow 0).
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import geometry, schema

BOX_KEYS = ("center", "size", "heading", "track_id", "class_id")
_MAX_TABLE_CELLS = 1 << 22  # bound on the cell -> box table of points_in_boxes (cells per layer)


def empty_boxes() -> dict:
    return {"center": np.zeros((0, 3)), "size": np.zeros((0, 3)), "heading": np.zeros(0),
            "track_id": np.zeros(0, dtype=str), "class_id": np.zeros(0, np.int32)}


def points_in_boxes(points_xyz: np.ndarray, boxes: dict, tolerance_m: float = 1e-4,
                    enlarge_m=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Index of the (lowest-numbered) box containing each point, -1 for none. A point on a face (within
    `tolerance_m`) is inside.

    No Python loop over points or boxes: every box paints the 1 m x-y cells (coarser when the boxes spread over more
    than 2 km) under its axis-aligned footprint into a layered cell -> box table (layer l holds the l-th lowest box
    index covering the cell), each point looks up its cell, and each layer tests all its candidate points against
    their box at once. The number of layers is the largest number of boxes over one cell (a few where boxes touch).
    """
    points_xyz = np.asarray(points_xyz).reshape(-1, 3)
    n = len(points_xyz)
    k = len(boxes["heading"])
    owner = np.full(n, -1, np.int32)
    if n == 0 or k == 0:
        return owner
    half = (np.asarray(boxes["size"], np.float64) + np.asarray(enlarge_m, np.float64)) / 2.0 + tolerance_m  # [K,3]
    centers = np.asarray(boxes["center"], np.float64)
    heading = np.asarray(boxes["heading"], np.float64)
    if not (np.isfinite(half).all() and np.isfinite(centers).all() and np.isfinite(heading).all()):
        raise ValueError("points_in_boxes: boxes have non-finite center, size or heading")
    cos_h, sin_h = np.cos(heading), np.sin(heading)
    # Axis-aligned half extent of each rotated footprint, then its cell range.
    ext = np.stack([np.abs(cos_h) * half[:, 0] + np.abs(sin_h) * half[:, 1],
                    np.abs(sin_h) * half[:, 0] + np.abs(cos_h) * half[:, 1]], 1) + 1e-3  # margin: float32 points
    span = np.ptp(np.concatenate([centers[:, :2] - ext, centers[:, :2] + ext]), axis=0)
    cell_m = max(1.0, float(np.sqrt(np.prod(span + 1.0) / _MAX_TABLE_CELLS)))  # far-apart boxes: coarser cells
    lo_cell = np.floor((centers[:, :2] - ext) / cell_m).astype(np.int64)  # [K,2]
    hi_cell = np.floor((centers[:, :2] + ext) / cell_m).astype(np.int64)
    origin = lo_cell.min(axis=0)
    grid_shape = hi_cell.max(axis=0) - origin + 1
    # (box, cell) pairs of every box's cell rectangle, without a loop: repeat each box over its cells.
    counts_xy = hi_cell - lo_cell + 1
    per_box = counts_xy[:, 0] * counts_xy[:, 1]
    box_of_pair = np.repeat(np.arange(k), per_box)
    rank = np.arange(len(box_of_pair)) - np.repeat(np.cumsum(per_box) - per_box, per_box)
    cx = lo_cell[box_of_pair, 0] - origin[0] + rank // counts_xy[box_of_pair, 1]
    cy = lo_cell[box_of_pair, 1] - origin[1] + rank % counts_xy[box_of_pair, 1]
    flat_cell = cx * grid_shape[1] + cy
    order = np.lexsort((box_of_pair, flat_cell))  # by cell, then by box index
    flat_cell, box_of_pair = flat_cell[order], box_of_pair[order]
    layer = np.arange(len(flat_cell)) - np.searchsorted(flat_cell, flat_cell, "left")
    num_cells = int(grid_shape[0] * grid_shape[1])
    table = np.full((layer.max() + 1, num_cells + 1), -1, np.int32)  # last column: points outside the grid
    table[layer, flat_cell] = box_of_pair
    # Each point's cell, in int32 (at most _MAX_TABLE_CELLS cells). A float32 floor is exact enough for a candidate
    # lookup: the inside test below runs in float64.
    xy = points_xyz[:, :2] if cell_m == 1.0 else points_xyz[:, :2] / cell_m
    ix = np.floor(xy[:, 0]).astype(np.int32) - np.int32(origin[0])
    iy = np.floor(xy[:, 1]).astype(np.int32) - np.int32(origin[1])
    outside = (ix.view(np.uint32) >= grid_shape[0]) | (iy.view(np.uint32) >= grid_shape[1])  # negatives wrap
    cell = ix * np.int32(grid_shape[1]) + iy
    cell[outside] = num_cells
    box = table[0][cell]
    cand = np.flatnonzero(box >= 0)
    box, cell = box[cand], cell[cand]
    for layer_index in range(len(table)):
        if layer_index:
            box = table[layer_index][cell]
            keep = box >= 0
            cand, cell, box = cand[keep], cell[keep], box[keep]
        if len(cand) == 0:
            break
        rel = points_xyz[cand].astype(np.float64) - centers[box]
        cb, sb, hb = cos_h[box], sin_h[box], half[box]
        inside = ((np.abs(cb * rel[:, 0] + sb * rel[:, 1]) <= hb[:, 0]) &
                  (np.abs(cb * rel[:, 1] - sb * rel[:, 0]) <= hb[:, 1]) & (np.abs(rel[:, 2]) <= hb[:, 2]))
        owner[cand[inside]] = box[inside]
        cand, cell = cand[~inside], cell[~inside]
    return owner


def bootstrap_flow(points_xyz_t0, boxes_t0: dict, boxes_tm1: dict, pose_t0, pose_tm1, dt_s: float, *,
                   tolerance_m: float = 1e-4, enlarge_m=(0.0, 0.0, 0.0), with_instances: bool = False):
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
      with_instances: also return each point's box (`instance_id_t0` of the pair records).
    Returns:
      flow_mps float32 [N,3], class_id int32 [N]; with `with_instances`, instance_id int32 [N]: the index of the t0
      box the point is in (the lowest where boxes overlap, as for its flow and class), -1 for none.
    """
    if dt_s == 0:
        raise ValueError("bootstrap_flow: dt_s must be non-zero")
    pts = np.asarray(points_xyz_t0).reshape(-1, 3)
    n = len(pts)
    flow = np.zeros((n, 3), np.float32)
    cls = np.full(n, schema.CLASS_BACKGROUND, np.int32)
    owner = points_in_boxes(pts, boxes_t0, tolerance_m, enlarge_m)
    if len(boxes_t0["heading"]) == 0:
        return (flow, cls, owner) if with_instances else (flow, cls)
    k = len(boxes_t0["heading"])
    b_t0 = geometry.box_matrices_np(np.asarray(boxes_t0["center"], np.float64), np.asarray(boxes_t0["heading"], np.float64))
    tm1_index = {str(t): i for i, t in enumerate(boxes_tm1["track_id"])}
    match = np.array([tm1_index.get(str(t), -1) for t in boxes_t0["track_id"]], np.int64)  # [K]
    # T_delta per t0 box (identity where unmatched): t0 point -> its position at t-1, in the t0 frame.
    t_delta = np.tile(np.eye(4), (k, 1, 1))
    if np.any(match >= 0):
        b_tm1 = geometry.box_matrices_np(np.asarray(boxes_tm1["center"], np.float64),
                             np.asarray(boxes_tm1["heading"], np.float64))
        t0_from_tm1 = geometry.t0_from_tm1_np(pose_t0, pose_tm1)
        m = match >= 0
        t_delta[m] = t0_from_tm1 @ b_tm1[match[m]] @ np.linalg.inv(b_t0[m])
    inside = np.flatnonzero(owner >= 0)
    box = owner[inside]
    # flow = (p0 - T_delta p0) / dt = A p0 + c with A = (I - R_delta) / dt, c = -t_delta / dt (zero if unmatched).
    a = (np.eye(3) - t_delta[:, :3, :3]) / dt_s  # [K,3,3]
    c = -t_delta[:, :3, 3] / dt_s
    p0 = pts[inside]
    flow[inside] = (a[box, :, 0] * p0[:, :1] + a[box, :, 1] * p0[:, 1:2] + a[box, :, 2] * p0[:, 2:3] + c[box])
    cls[inside] = np.where(match >= 0, np.asarray(boxes_t0["class_id"], np.int32), schema.CLASS_NO_LABEL)[box]
    return (flow, cls, owner) if with_instances else (flow, cls)


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
