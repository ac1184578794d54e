"""Scene-flow pseudo-labels for one pair of sweeps by Neural Scene Flow Prior, with a distance-transform Chamfer term.

Neural Scene Flow Prior (NSFP; Li, Kaesemodel Pontes and Lucey, NeurIPS 2021): the flow of a pair is the output of a
coordinate MLP (8 hidden layers of 128 units, ReLU), fitted to that pair alone with Adam on a Chamfer objective, plus a
second MLP for the backward flow (its cycle term) and early stopping (NSFP's defaults: learning rate 0.008, L2 weight
decay 1e-4 on both MLPs, patience 100 steps, minimum improvement 1e-4, at most 5000 steps). Fast Neural Scene Flow
(FastNSF; Li, Zheng, Ferroni, Pontes and Lucey, ICCV 2023): the Chamfer term reads a precomputed distance transform of
the fixed cloud (a voxel grid of distances to its nearest point, trilinearly interpolated), so a step costs O(N)
instead of O(N*M). Ground removal and the range crop (ZeroFlow's NSFP: z in [-3, 3] m) are options.

Convention (the project's labels, `ff3d_tf.labels.box_flow`): the forward MLP gives `motion_m`, the displacement of
each t0 point from t-1 to t0 in metres in the t0 vehicle frame; `points_xyz_t0 - motion_m` is where the point was at
t-1 and is pulled onto the ego-compensated t-1 cloud `points_xyz_tm1_in_t0`; `flow_mps_t0 = motion_m / dt_s`. The
cycle term moves that moved-back cloud forward again with the backward MLP and pulls it onto the t0 cloud. Both terms
are one-sided Chamfer distances (mean distance of each moved point to its nearest point of the fixed cloud, in metres):
only a fixed cloud has a distance transform.

The distance transform (`build_distance_grid`) is a pyramid of grids, each `PYRAMID_FACTOR` times coarser than the one
below, the finest `grid_cell_m` apart. On each level a node's value is the exact Euclidean distance to its nearest
point wherever that distance is at most `band_cells` cells of that level (found by scattering each point's distance to
the nodes around it: every point within that distance of a node is among the scattered ones, so the minimum is exact);
farther, the trilinear interpolation of the level above; the top level (at most `TOP_LEVEL_MAX_NODES` nodes) is
brute force everywhere. Cost O(points x stencil + nodes), no O(nodes x points) term.

XLA: one compiled fit program per (point bucket, grid-size bucket) (`ff3d_tf.data.pairs.bucket_size`; the two clouds
share a point bucket), run in segments of `segment_iterations` steps so that a caller sees progress; one compiled grid
program per (grid shape, point bucket); with the range crop set, x and y of the grid come from the crop box, so only
the z extent varies between pairs. Same seed, same inputs, same device: same labels.
"""
from __future__ import annotations

import dataclasses
import glob
import json
import math
import os
import time
from typing import Callable, NamedTuple

import numpy as np
import tensorflow as tf

from ff3d_tf import geometry
from ff3d_tf.data import argoverse2
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.model.step import adam_apply

PYRAMID_FACTORS = (2, 4)  # level l+1 of the distance pyramid is PYRAMID_FACTORS[min(l, 1)] times coarser than l
TOP_LEVEL_MAX_NODES = 4096  # the pyramid's top level, brute force everywhere, has at most this many nodes
ADAM_BETA_1, ADAM_BETA_2, ADAM_EPSILON = 0.9, 0.999, 1e-8  # PyTorch's Adam defaults (NSFP's optimiser)
_DIMS_MULTIPLE = 8  # each grid axis is rounded up to a multiple of this many nodes (fewer compiled grid programs)
_GRID_BUCKET_BASE = 1 << 16  # the flat grid handed to the fit is padded to bucket_size(nodes, this)
_TOP_NODE_CHUNK = 256  # top-level nodes per brute-force step ([chunk, points] distances)
_EXACT_QUERY_CHUNK = 512  # query points per step of the exact nearest neighbours ([chunk, points] distances)
_SQRT_FLOOR = 1e-12  # distance = sqrt(max(d^2, floor)): a finite gradient where a point sits on its neighbour


@dataclasses.dataclass(frozen=True)
class NsfpOptions:
    """Options of `nsfp_flow`. Loss and `min_delta_m` are in metres (mean one-sided Chamfer distance)."""
    hidden_layers: int = 8  # NSFP: 8 hidden layers of 128, ReLU
    hidden_units: int = 128
    learning_rate: float = 8e-3  # Adam (NSFP and ZeroFlow: 0.008)
    warmup_iterations: int = 0  # learning rate ramped linearly from learning_rate / n to it over the first n steps
    weight_decay: float = 1e-4  # L2 added to the gradients (NSFP's per-group weight_decay on both MLPs)
    max_iterations: int = 5000
    patience: int = 100  # stop after this many steps without the loss improving by more than min_delta_m
    min_delta_m: float = 1e-4
    backward_cycle: bool = True  # NSFP's backward-flow term
    exact_chamfer: bool = False  # exact nearest neighbours (O(N*M) a step; for checking) instead of the grid
    squared_chamfer: bool = False  # mean squared distance (NSFP's Chamfer) instead of mean distance
    truncate_m: float | None = None  # points this far or farther from the target count 0 (NSFP: sqrt(2) m)
    grid_cell_m: float = 0.1  # finest level of the distance transform (FastNSF: 0.1 m)
    grid_margin_m: float = 0.5  # grid bounds: the kept clouds' bounding box (or crop box) grown by this much
    band_cells: int = 4  # finest level exact wherever the nearest point is within this many cells
    coarse_band_cells: int = 3  # the same on the coarser levels
    max_grid_cells: int = 1 << 26  # refuse grids larger than this (memory: 4 bytes a node, two grids a pair)
    remove_ground_below_z_m: float | None = None  # drop points with z below this (vehicle frame), None: keep all
    crop_xy_half_extent_m: float | None = None  # keep points with |x| and |y| at most this, None: no crop
    crop_z_range_m: tuple[float, float] | None = None  # keep points with z in [lo, hi] (ZeroFlow: (-3, 3))
    point_bucket_base: int = 1024
    segment_iterations: int = 100  # Adam steps per compiled call (progress is reported between calls)
    seed: int = 0

    def __post_init__(self):
        for name in ("hidden_layers", "hidden_units", "max_iterations", "patience", "max_grid_cells",
                     "point_bucket_base", "band_cells", "coarse_band_cells", "segment_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"NsfpOptions.{name}: must be an integer >= 1, got {value!r}")
        if isinstance(self.warmup_iterations, bool) or not isinstance(self.warmup_iterations, int) \
                or self.warmup_iterations < 0:
            raise ValueError(f"NsfpOptions.warmup_iterations: must be an integer >= 0, got {self.warmup_iterations!r}")
        for name in ("learning_rate", "grid_cell_m"):
            if not _is_real(getattr(self, name)) or not getattr(self, name) > 0:
                raise ValueError(f"NsfpOptions.{name}: must be a finite number > 0, got {getattr(self, name)!r}")
        for name in ("min_delta_m", "grid_margin_m", "weight_decay"):
            if not _is_real(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"NsfpOptions.{name}: must be a finite number >= 0, got {getattr(self, name)!r}")
        if self.truncate_m is not None and not (_is_real(self.truncate_m) and self.truncate_m > 0):
            raise ValueError(f"NsfpOptions.truncate_m: must be a finite number > 0 or None, got {self.truncate_m!r}")
        if self.remove_ground_below_z_m is not None and not _is_real(self.remove_ground_below_z_m):
            raise ValueError(f"NsfpOptions.remove_ground_below_z_m: must be a finite number or None, "
                             f"got {self.remove_ground_below_z_m!r}")
        crop = self.crop_xy_half_extent_m
        if crop is not None and not (_is_real(crop) and crop > 0):
            raise ValueError(f"NsfpOptions.crop_xy_half_extent_m: must be a finite number > 0 or None, got {crop!r}")
        z_range = self.crop_z_range_m
        if z_range is not None and not (isinstance(z_range, (tuple, list)) and len(z_range) == 2
                                        and all(_is_real(z) for z in z_range) and z_range[0] < z_range[1]):
            raise ValueError(f"NsfpOptions.crop_z_range_m: must be (lo, hi) with lo < hi or None, got {z_range!r}")
        for name in ("backward_cycle", "exact_chamfer", "squared_chamfer"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"NsfpOptions.{name}: must be a bool, got {getattr(self, name)!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed < 2 ** 31:
            raise ValueError(f"NsfpOptions.seed: must be an integer in [0, 2**31), got {self.seed!r}")


def _is_real(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class DistanceGrid(NamedTuple):
    """Distance transform of a cloud: `distance_m[(i * dims[1] + j) * dims[2] + k]` is the value at the node
    `origin_m + (i, j, k) * cell_m` (see the module docstring for what it equals); entries past dims' product pad."""
    distance_m: tf.Tensor  # [C] float32, C a bucket size >= prod(dims)
    origin_m: tf.Tensor  # [3] float32
    dims: tf.Tensor  # [3] int32, each >= 2
    cell_m: tf.Tensor  # [] float32


@dataclasses.dataclass(frozen=True)
class NsfpResult:
    flow_mps_t0: np.ndarray  # [N,3] float32, t0 vehicle frame; 0 where not valid
    valid_t0: np.ndarray  # [N] bool: the point was kept (ground removal, crop) and optimised
    num_iterations: int  # Adam steps taken
    loss_m: float  # best objective (forward + cycle Chamfer, metres); its flow is the one returned
    grid_s: float  # seconds building the distance grids (0 with exact_chamfer)
    fit_s: float  # seconds in the fit


# --- nearest neighbours --------------------------------------------------------------------------------------------

def _nearest_index_chunk(query_xyz, target_xyz, target_mask):
    """Index of each query point's nearest valid target point (squared distances as |q|^2 - 2 q.t + |t|^2)."""
    d2 = (tf.reduce_sum(query_xyz ** 2, -1)[:, None] - 2.0 * tf.matmul(query_xyz, target_xyz, transpose_b=True)
          + tf.reduce_sum(target_xyz ** 2, -1)[None, :])
    return tf.argmin(tf.where(target_mask[None, :], d2, np.float32(np.inf)), axis=1, output_type=tf.int32)


def nearest_index(query_xyz, target_xyz, target_mask):
    """[Q] int32 index of each query point's nearest valid target point, `_EXACT_QUERY_CHUNK` queries at a time (a
    [chunk, targets] matrix, never [Q, targets]); not differentiable."""
    query_xyz = tf.stop_gradient(tf.convert_to_tensor(query_xyz, tf.float32))
    target_xyz = tf.stop_gradient(tf.convert_to_tensor(target_xyz, tf.float32))
    num_query = query_xyz.shape[0]
    chunk = min(_EXACT_QUERY_CHUNK, num_query)
    padded = -(-num_query // chunk) * chunk
    chunks = tf.reshape(tf.pad(query_xyz, [[0, padded - num_query], [0, 0]]), [-1, chunk, 3])
    index = tf.map_fn(lambda q: _nearest_index_chunk(q, target_xyz, target_mask), chunks,
                      fn_output_signature=tf.int32, parallel_iterations=1)
    return tf.reshape(index, [-1])[:num_query]


def exact_nearest_distance_m(query_xyz, target_xyz, target_mask):
    """[Q] distance (m) of each query point to its nearest valid target point, by brute force. The neighbour is chosen
    on the matmul form and its distance recomputed from the coordinate difference (no cancellation error);
    differentiable in the query (the neighbour held fixed)."""
    nearest = tf.gather(target_xyz, nearest_index(query_xyz, target_xyz, target_mask))
    return tf.sqrt(tf.maximum(tf.reduce_sum((query_xyz - nearest) ** 2, -1), _SQRT_FLOOR))


# --- the distance transform ----------------------------------------------------------------------------------------

def band_offsets(band_cells: int) -> np.ndarray:
    """[S,3] int32 node offsets o (from a point's own node) at which some point of that node's cell (a cube of one
    cell around the node) can lie within `band_cells` cells: sum over axes of max(|o| - 1/2, 0)^2 <= band_cells^2."""
    r = np.arange(-band_cells, band_cells + 1)
    offsets = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    gap = np.maximum(np.abs(offsets) - 0.5, 0.0)
    return offsets[(gap ** 2).sum(1) <= band_cells ** 2].astype(np.int32)


def level_factor(level: int, factors: tuple = PYRAMID_FACTORS) -> int:
    """How many times coarser level `level` + 1 is than level `level`."""
    return factors[min(level, len(factors) - 1)]


def level_scale(level: int, factors: tuple = PYRAMID_FACTORS) -> int:
    """Cell size of level `level` in finest cells."""
    return int(np.prod([level_factor(k, factors) for k in range(level)]))


def pyramid_dims(dims, factors: tuple = PYRAMID_FACTORS) -> list[tuple[int, int, int]]:
    """Node counts of each level, finest first: node I of level l + 1 is node level_factor(l) * I of level l, so a
    level covers the one below; up to the first level with at most TOP_LEVEL_MAX_NODES nodes."""
    levels = [tuple(int(d) for d in dims)]
    while np.prod(levels[-1]) > TOP_LEVEL_MAX_NODES:
        f = level_factor(len(levels) - 1, factors)
        levels.append(tuple(int(-(-(d - 1) // f) + 1) for d in levels[-1]))
    return levels


def _band_squared_m2(points_xyz, point_mask, origin_m, dims, cell_m, offsets: np.ndarray):
    """[X,Y,Z] squared distance of each node to the nearest valid point whose own node (nearest node) is at one of
    `offsets` from it; inf where none. One scatter-min per x offset (a [points, offsets] block at a time)."""
    nx, ny, nz = dims
    num_nodes = nx * ny * nz
    snap = tf.cast(tf.floor((points_xyz - origin_m) / cell_m + 0.5), tf.int32)
    out = tf.fill([num_nodes + 1], np.float32(np.inf))  # the last entry takes what falls off the grid
    for ox in np.unique(offsets[:, 0]):
        node = snap[:, None, :] + tf.constant(offsets[offsets[:, 0] == ox])[None]
        inside = tf.reduce_all((node >= 0) & (node < tf.constant(dims, tf.int32)), -1) & point_mask[:, None]
        flat = tf.where(inside, (node[..., 0] * ny + node[..., 1]) * nz + node[..., 2], num_nodes)
        d2 = tf.reduce_sum(tf.square(origin_m + tf.cast(node, tf.float32) * cell_m - points_xyz[:, None]), -1)
        out = tf.tensor_scatter_nd_min(out, tf.reshape(flat, [-1, 1]), tf.reshape(d2, [-1]))
    return tf.reshape(out[:num_nodes], dims)


def _node_xyz(dims, origin_m, cell_m):
    ijk = tf.stack(tf.meshgrid(*[tf.range(d) for d in dims], indexing="ij"), -1)
    return tf.reshape(origin_m + tf.cast(ijk, tf.float32) * cell_m, [-1, 3])


def _brute_squared_m2(points_xyz, point_mask, origin_m, dims, cell_m):
    """[X,Y,Z] squared distance of every node to its nearest valid point, `_TOP_NODE_CHUNK` nodes at a time."""
    nodes = _node_xyz(dims, origin_m, cell_m)
    num_nodes = int(np.prod(dims))
    padded = -(-num_nodes // _TOP_NODE_CHUNK) * _TOP_NODE_CHUNK
    chunks = tf.reshape(tf.pad(nodes, [[0, padded - num_nodes], [0, 0]]), [-1, _TOP_NODE_CHUNK, 3])
    norms = tf.where(point_mask, tf.reduce_sum(points_xyz ** 2, -1), np.float32(np.inf))

    def chunk(q):
        d2 = tf.reduce_sum(q ** 2, -1)[:, None] - 2.0 * tf.matmul(q, points_xyz, transpose_b=True) + norms[None]
        return tf.maximum(tf.reduce_min(d2, 1), 0.0)
    d2 = tf.map_fn(chunk, chunks, fn_output_signature=tf.float32, parallel_iterations=1)
    return tf.reshape(tf.reshape(d2, [-1])[:num_nodes], dims)


def _upsample(values, dims_out, f: int):
    """Trilinear interpolation of a level at the nodes of the level below (node I above = node f*I below), as one
    linear interpolation per axis, cropped to `dims_out`."""
    for axis in range(3):
        v = tf.experimental.numpy.moveaxis(values, axis, 0)
        low, high = v[:-1], v[1:]
        between = tf.stack([low + (high - low) * (r / f) for r in range(f)], 1)
        v = tf.concat([tf.reshape(between, [-1] + v.shape[1:].as_list()), v[-1:]], 0)[: dims_out[axis]]
        values = tf.experimental.numpy.moveaxis(v, 0, axis)
    return values


_GRID_PROGRAMS: dict = {}


def _grid_program(dims: tuple, band_cells: int, coarse_band_cells: int, factors: tuple = PYRAMID_FACTORS):
    """The compiled pyramid for one grid shape (retraced per point bucket)."""
    key = (dims, band_cells, coarse_band_cells, factors)
    if key not in _GRID_PROGRAMS:
        levels = pyramid_dims(dims, factors)
        fine, coarse = band_offsets(band_cells), band_offsets(coarse_band_cells)

        @tf.function(jit_compile=True)
        def build(points_xyz, point_mask, origin_m, cell_m):
            top = len(levels) - 1
            values = tf.sqrt(_brute_squared_m2(points_xyz, point_mask, origin_m, levels[top],
                                               cell_m * level_scale(top, factors)))
            for level in range(top - 1, -1, -1):
                h = cell_m * level_scale(level, factors)
                band, offsets = (band_cells, fine) if level == 0 else (coarse_band_cells, coarse)
                d2 = _band_squared_m2(points_xyz, point_mask, origin_m, levels[level], h, offsets)
                values = tf.where(d2 <= tf.square(band * h), tf.sqrt(d2), _upsample(values, levels[level], level_factor(level, factors)))
            return tf.reshape(values, [-1])
        _GRID_PROGRAMS[key] = build
    return _GRID_PROGRAMS[key]


def grid_geometry(clouds_xyz: list[np.ndarray], cell_m: float, margin_m: float, max_cells: int,
                  box_m: tuple | None = None):
    """(origin_m [3] float32, dims [3] int32) of a grid of nodes `cell_m` apart covering the clouds' bounding box
    (or, per axis where `box_m` = ((lo, hi) or None per axis) gives one, that box) grown by `margin_m`; each axis
    rounded up to a multiple of 8 nodes."""
    stacked = np.concatenate([np.asarray(c, np.float64).reshape(-1, 3) for c in clouds_xyz])
    lo, hi = stacked.min(0), stacked.max(0)
    for axis, bounds in enumerate(box_m or (None, None, None)):
        if bounds is not None:
            lo[axis], hi[axis] = bounds
    lo, hi = lo - margin_m, hi + margin_m
    dims = np.floor((hi - lo) / cell_m).astype(np.int64) + 1
    dims = np.maximum(-(-dims // _DIMS_MULTIPLE) * _DIMS_MULTIPLE, _DIMS_MULTIPLE)
    if int(np.prod(dims)) > max_cells:
        raise ValueError(f"NsfpOptions.grid_cell_m: a {cell_m} m grid over {np.round(hi - lo, 1).tolist()} m has "
                         f"{int(np.prod(dims))} cells, above NsfpOptions.max_grid_cells={max_cells}")
    return lo.astype(np.float32), dims.astype(np.int32)


def build_distance_grid(points_xyz, point_mask, origin_m, dims, cell_m: float, band_cells: int = 4,
                        coarse_band_cells: int = 3, factors: tuple = PYRAMID_FACTORS) -> DistanceGrid:
    """The distance transform of the valid points of `points_xyz` [P,3] on the given grid (module docstring): at a
    node whose nearest point is within `band_cells` * `cell_m`, the exact distance to it."""
    points_xyz = np.asarray(points_xyz, np.float32)
    point_mask = np.asarray(point_mask, bool)
    if not point_mask.any():
        raise ValueError("build_distance_grid: no valid point")
    # Points in node order: neighbouring points scatter into neighbouring memory (the result does not depend on it).
    u = np.floor((points_xyz - origin_m) / np.float32(cell_m) + 0.5).astype(np.int64)
    order = np.argsort((u[:, 0] * int(dims[1]) + u[:, 1]) * int(dims[2]) + u[:, 2], kind="stable")
    program = _grid_program(tuple(int(d) for d in dims), band_cells, coarse_band_cells, tuple(factors))
    values = program(tf.constant(points_xyz[order]), tf.constant(point_mask[order]), tf.constant(origin_m, tf.float32),
                     tf.constant(cell_m, tf.float32))
    size = bucket_size(int(np.prod(dims)), _GRID_BUCKET_BASE)
    values = tf.pad(values, [[0, size - int(np.prod(dims))]])
    return DistanceGrid(values, tf.constant(origin_m, tf.float32), tf.constant(dims, tf.int32),
                        tf.constant(cell_m, tf.float32))


def read_distance_grid(grid: DistanceGrid, query_xyz):
    """[Q] trilinear interpolation of the grid at the query points (m). Off the grid: the value at the nearest grid
    point plus the distance to it. Where the 8 corners hold exact distances, the error against the exact nearest
    distance is at most half a cell diagonal (the distance is 1-Lipschitz; see tests/labels/test_nsfp.py)."""
    u = (query_xyz - grid.origin_m) / grid.cell_m
    top = tf.cast(grid.dims - 1, tf.float32)
    u_in = tf.clip_by_value(u, 0.0, top)
    off_grid = tf.reduce_any(u != u_in, -1)
    outside_m = tf.where(off_grid, tf.sqrt(tf.maximum(tf.reduce_sum((u - u_in) ** 2, -1), _SQRT_FLOOR)), 0.0)
    outside_m *= grid.cell_m
    base = tf.minimum(tf.floor(u_in), top - 1.0)
    frac, base = u_in - base, tf.cast(base, tf.int32)
    value = tf.zeros_like(query_xyz[:, 0])
    for corner in range(8):
        offset = tf.constant([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], tf.int32)
        ijk = base + offset
        flat = (ijk[:, 0] * grid.dims[1] + ijk[:, 1]) * grid.dims[2] + ijk[:, 2]
        weight = tf.reduce_prod(tf.where(offset == 1, frac, 1.0 - frac), -1)
        value += weight * tf.gather(grid.distance_m, flat)
    return value + outside_m


def chamfer_m(query_xyz, query_mask, target_xyz, target_mask, grid: DistanceGrid | None, exact: bool,
              squared: bool = False, truncate_m=None):
    """One-sided Chamfer distance: mean over valid query points of the distance (m; `squared`: its square, m^2) to the
    nearest valid target point, exact (brute force) or read from `grid`, the target's distance transform. Truncated
    (NSFP): a point whose distance is `truncate_m` or more counts 0 (still in the mean's denominator)."""
    if exact:
        distance_m = exact_nearest_distance_m(query_xyz, target_xyz, target_mask)
    else:
        distance_m = read_distance_grid(grid, query_xyz)
    if truncate_m is not None:
        distance_m = tf.where(distance_m < truncate_m, distance_m, 0.0)
    if squared:
        distance_m = tf.square(distance_m)
    weight = tf.cast(query_mask, tf.float32)
    return tf.reduce_sum(distance_m * weight) / tf.maximum(tf.reduce_sum(weight), 1.0)


# --- the prior and its per-pair fit ----------------------------------------------------------------------------------

def init_mlp(seed: int, stream: int, hidden_layers: int, hidden_units: int) -> list[tf.Tensor]:
    """[w0, b0, w1, b1, ...] of an MLP 3 -> hidden_units x hidden_layers -> 3, each entry uniform in
    +-1/sqrt(fan_in) (PyTorch's nn.Linear default, as NSFP's MLP), from a stateless seed."""
    widths = [3] + [hidden_units] * hidden_layers + [3]
    params = []
    for layer, (fan_in, fan_out) in enumerate(zip(widths[:-1], widths[1:])):
        bound = 1.0 / math.sqrt(fan_in)
        for part, shape in enumerate(([fan_in, fan_out], [fan_out])):
            params.append(tf.random.stateless_uniform(shape, seed=[seed, (stream * 1000 + layer) * 2 + part],
                                                      minval=-bound, maxval=bound))
    return params


def mlp(params, xyz):
    """The coordinate MLP: ReLU after every hidden layer, linear output (m)."""
    h = xyz
    for w, b in zip(params[0:-2:2], params[1:-2:2]):
        h = tf.nn.relu(tf.matmul(h, w) + b)
    return tf.matmul(h, params[-2]) + params[-1]


def nsfp_objective_m(forward, backward, points_xyz_t0, mask_t0, points_xyz_tm1, mask_tm1, grid_tm1, grid_t0,
                     exact: bool, squared: bool = False, truncate_m=None):
    """(objective in m, motion_m [B,3]): Chamfer of the moved-back t0 cloud to the t-1 cloud, plus (when `backward`
    is not None) Chamfer of that cloud moved forward by the backward MLP to the t0 cloud."""
    motion_m = mlp(forward, points_xyz_t0)
    moved_back_xyz = points_xyz_t0 - motion_m  # where each t0 point was at t-1
    loss = chamfer_m(moved_back_xyz, mask_t0, points_xyz_tm1, mask_tm1, grid_tm1, exact, squared, truncate_m)
    if backward is not None:
        moved_forward_xyz = moved_back_xyz + mlp(backward, moved_back_xyz)
        loss += chamfer_m(moved_forward_xyz, mask_t0, points_xyz_t0, mask_t0, grid_t0, exact, squared, truncate_m)
    return loss, motion_m


class _FitState(NamedTuple):
    step: tf.Tensor  # Adam steps taken
    params: list  # forward MLP's tensors, then the backward MLP's
    adam_m: list
    adam_v: list
    best_loss: tf.Tensor  # lowest objective seen; best_motion is its motion
    best_motion: tf.Tensor
    reference_loss: tf.Tensor  # early stopping: the loss at the last improvement by more than min_delta_m
    stale: tf.Tensor  # steps since then


@tf.function(jit_compile=True)
def _fit_segment(state: _FitState, clouds, grids, hyper, num_forward: int, exact: bool, squared: bool,
                 segment: int):
    """Up to `segment` Adam steps on the NSFP objective in one in-graph loop, stopping early (patience) or at
    max_iterations; the loss of a step is that of the parameters before its update."""
    learning_rate, warmup, weight_decay, min_delta_m, patience, max_iterations, truncate_m = hyper
    end = tf.minimum(state.step + segment, max_iterations)

    def objective(p):
        return nsfp_objective_m(p[:num_forward], p[num_forward:] or None, *clouds, *grids, exact, squared, truncate_m)

    def body(s: _FitState):
        with tf.GradientTape() as tape:
            tape.watch(s.params)
            loss, motion_m = objective(s.params)
        grads = tape.gradient(loss, s.params, unconnected_gradients=tf.UnconnectedGradients.ZERO)
        grads = [g + weight_decay * p for g, p in zip(grads, s.params)]
        best = loss < s.best_loss
        improved = loss < s.reference_loss - min_delta_m
        rate = learning_rate * tf.minimum(1.0, tf.cast(s.step + 1, tf.float32) / tf.cast(tf.maximum(warmup, 1),
                                                                                           tf.float32))
        params, adam_m, adam_v = adam_apply(s.params, grads, s.adam_m, s.adam_v, s.step, rate,
                                            ADAM_BETA_1, ADAM_BETA_2, ADAM_EPSILON)
        return _FitState(s.step + 1, params, adam_m, adam_v, tf.where(best, loss, s.best_loss),
                         tf.where(best, motion_m, s.best_motion), tf.where(improved, loss, s.reference_loss),
                         tf.where(improved, 0, s.stale + 1))

    def running(s: _FitState):
        return (s.step < end) & (s.stale < patience)

    return tf.while_loop(running, lambda s: [body(s)], [state])[0]


# --- a pair in, flow out ---------------------------------------------------------------------------------------------

def keep_mask(points_xyz: np.ndarray, options: NsfpOptions) -> np.ndarray:
    """[P] bool: points that survive ground removal and the range crop (vehicle frame)."""
    keep = np.ones(len(points_xyz), bool)
    if options.remove_ground_below_z_m is not None:
        keep &= points_xyz[:, 2] >= options.remove_ground_below_z_m
    if options.crop_xy_half_extent_m is not None:
        keep &= np.all(np.abs(points_xyz[:, :2]) <= options.crop_xy_half_extent_m, axis=1)
    if options.crop_z_range_m is not None:
        keep &= (points_xyz[:, 2] >= options.crop_z_range_m[0]) & (points_xyz[:, 2] <= options.crop_z_range_m[1])
    return keep


def _padded(points_xyz: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    out = np.zeros((size, 3), np.float32)
    out[: len(points_xyz)] = points_xyz
    return out, np.arange(size) < len(points_xyz)


def _checked_cloud(points_xyz, name: str) -> np.ndarray:
    points_xyz = np.asarray(points_xyz, np.float32)
    if points_xyz.ndim != 2 or points_xyz.shape[1] != 3:
        raise ValueError(f"nsfp_flow: {name} must be [N,3], got shape {points_xyz.shape}")
    if not np.isfinite(points_xyz).all():
        raise ValueError(f"nsfp_flow: {name} has non-finite coordinates")
    return points_xyz


def _checked_keep(keep, size: int, name: str) -> np.ndarray:
    if keep is None:
        return np.ones(size, bool)
    keep = np.asarray(keep)
    if keep.dtype != bool or keep.shape != (size,):
        raise ValueError(f"nsfp_flow: {name} must be a bool array of shape ({size},), got {keep.dtype} {keep.shape}")
    return keep


def _crop_box(options: NsfpOptions):
    """Per axis (lo, hi) of the grid box in the vehicle frame: x and y from the crop when set (the same grid extent
    for every pair), None (the clouds' bounding box) otherwise and for z (a z crop is much taller than what the kept
    points fill: ground removed, few points above 3 m)."""
    xy = options.crop_xy_half_extent_m
    xy_box = None if xy is None else (-float(xy), float(xy))
    return xy_box, xy_box, None


def nsfp_flow(points_xyz_t0, points_xyz_tm1_in_t0, dt_s: float, options: NsfpOptions = NsfpOptions(),
              keep_t0=None, keep_tm1=None, progress: Callable[[int, float], None] | None = None) -> NsfpResult:
    """NSFP flow (m/s, t0 vehicle frame, the project's convention) of every t0 point, from the t0 cloud [N,3] and the
    ego-compensated t-1 cloud [M,3] (t0 vehicle frame). `keep_t0` / `keep_tm1` ([N] / [M] bool, optional): points to
    use besides the options' ground removal and crop (e.g. a map's ground labels). Points not used get flow 0 and
    `valid_t0` False, as do all points when either kept cloud is empty. `progress(steps, best_loss_m)` is called
    after every `segment_iterations` steps."""
    xyz_t0 = _checked_cloud(points_xyz_t0, "points_xyz_t0")
    xyz_tm1 = _checked_cloud(points_xyz_tm1_in_t0, "points_xyz_tm1_in_t0")
    if not (_is_real(dt_s) and dt_s > 0):
        raise ValueError(f"nsfp_flow: dt_s must be a finite number > 0, got {dt_s!r}")
    keep_t0 = keep_mask(xyz_t0, options) & _checked_keep(keep_t0, len(xyz_t0), "keep_t0")
    keep_tm1 = keep_mask(xyz_tm1, options) & _checked_keep(keep_tm1, len(xyz_tm1), "keep_tm1")
    flow_mps = np.zeros_like(xyz_t0)
    if not keep_t0.any() or not keep_tm1.any():
        return NsfpResult(flow_mps, np.zeros(len(xyz_t0), bool), 0, float("nan"), 0.0, 0.0)
    kept_t0, kept_tm1 = xyz_t0[keep_t0], xyz_tm1[keep_tm1]
    box = _crop_box(options)
    origin_m, dims = grid_geometry([kept_t0, kept_tm1], options.grid_cell_m, options.grid_margin_m,
                                   options.max_grid_cells, box)
    # Centred coordinates: the MLP sees the scene around 0, and the nearest-neighbour matmul keeps its precision.
    centre_m = (origin_m + (dims - 1) * np.float32(options.grid_cell_m) / 2).astype(np.float32)
    kept_t0, kept_tm1, origin_m = kept_t0 - centre_m, kept_tm1 - centre_m, origin_m - centre_m
    size = bucket_size(max(len(kept_t0), len(kept_tm1)), options.point_bucket_base)
    padded_t0, padded_tm1 = _padded(kept_t0, size), _padded(kept_tm1, size)
    start = time.perf_counter()
    if options.exact_chamfer:
        placeholder = DistanceGrid(tf.zeros([8]), tf.zeros([3]), tf.constant([2, 2, 2]), tf.constant(1.0))
        grids = (placeholder, placeholder)
    else:
        def grid(padded):
            return build_distance_grid(*padded, origin_m, dims, options.grid_cell_m, options.band_cells,
                                       options.coarse_band_cells)
        grid_tm1 = grid(padded_tm1)
        grids = (grid_tm1, grid(padded_t0) if options.backward_cycle else grid_tm1)
    grid_s = time.perf_counter() - start if not options.exact_chamfer else 0.0
    (t0, mask_t0), (tm1, mask_tm1) = [tuple(map(tf.constant, padded)) for padded in (padded_t0, padded_tm1)]
    start = time.perf_counter()
    state = initial_fit_state(options, size)
    hyper = (tf.constant(options.learning_rate, tf.float32), tf.constant(options.warmup_iterations),
             tf.constant(options.weight_decay, tf.float32),
             tf.constant(options.min_delta_m, tf.float32), tf.constant(options.patience),
             tf.constant(options.max_iterations),
             tf.constant(np.inf if options.truncate_m is None else options.truncate_m, tf.float32))
    num_forward = 2 * (options.hidden_layers + 1)
    while True:
        state = _fit_segment(state, (t0, mask_t0, tm1, mask_tm1), grids, hyper, num_forward, options.exact_chamfer,
                             options.squared_chamfer, options.segment_iterations)
        steps = int(state.step)
        if progress is not None:
            progress(steps, float(state.best_loss))
        if steps >= options.max_iterations or int(state.stale) >= options.patience:
            break
    motion_m = state.best_motion.numpy()[: len(kept_t0)]
    flow_mps[keep_t0] = motion_m / np.float32(dt_s)
    return NsfpResult(flow_mps, keep_t0, steps, float(state.best_loss), grid_s, time.perf_counter() - start)


def initial_fit_state(options: NsfpOptions, num_points: int) -> _FitState:
    """The fit's state before its first step: the MLPs initialised from `options.seed`, Adam's slots at 0."""
    params = init_mlp(options.seed, 0, options.hidden_layers, options.hidden_units)
    if options.backward_cycle:
        params += init_mlp(options.seed, 1, options.hidden_layers, options.hidden_units)
    zeros = [tf.zeros_like(p) for p in params]
    return _FitState(tf.constant(0), params, zeros, list(zeros), tf.constant(np.inf, tf.float32),
                     tf.zeros([num_points, 3]), tf.constant(np.inf, tf.float32), tf.constant(0))


# --- the check against Argoverse 2's own flow ------------------------------------------------------------------------

AV2_GROUND_HEIGHT_THRESHOLD_M = 0.3  # av2-api: a point within 0.3 m of the map's ground height, or below it, is ground
AV2_EVAL_HALF_EXTENT_M = 35.0  # the points evaluated: max(|x|, |y|) <= 35 m in the sweep-0 ego frame
AV2_NSFP_OPTIONS = NsfpOptions(crop_xy_half_extent_m=AV2_EVAL_HALF_EXTENT_M, crop_z_range_m=(-3.0, 3.0))


def av2_map_ground_mask(log_dir: str, points_xyz_ego: np.ndarray, ego_to_city: np.ndarray) -> np.ndarray:
    """[N] bool: ground points by the log's ground-height raster, the rule of Argoverse's `is_ground` labels (av2-api
    `GroundHeightLayer`: the raster pixel of p is int(s * (R p_xy + t)) of `*img_Sim2_city.json`; ground where
    |z - height| <= 0.3 m or z < height, city frame). Points off the raster are not ground."""
    map_dir = os.path.join(log_dir, "map")
    rasters = sorted(glob.glob(os.path.join(map_dir, "*_ground_height_surface____*.npy")))
    sims = sorted(glob.glob(os.path.join(map_dir, "*img_Sim2_city.json")))
    if len(rasters) != 1 or len(sims) != 1:
        raise argoverse2.Argoverse2FormatError(map_dir, "file", f"needs one *_ground_height_surface____*.npy and one "
                                               f"*img_Sim2_city.json, found {len(rasters)} and {len(sims)}")
    height = np.load(rasters[0], allow_pickle=False)
    if height.ndim != 2:
        raise argoverse2.Argoverse2FormatError(rasters[0], "file", f"ground height raster of shape {height.shape}")
    with open(sims[0]) as f:
        sim = json.load(f)
    try:
        rotation = np.asarray(sim["R"], np.float64).reshape(2, 2)
        translation = np.asarray(sim["t"], np.float64).reshape(2)
        scale = float(sim["s"])
    except (KeyError, TypeError, ValueError) as err:
        raise argoverse2.Argoverse2FormatError(sims[0], "R/t/s", f"not a Sim(2) ({type(err).__name__})") from None
    city = geometry.transform_points_np(points_xyz_ego, ego_to_city)
    pixel = ((city[:, :2] @ rotation.T + translation) * scale).astype(np.int64)
    on_raster = (pixel[:, 0] >= 0) & (pixel[:, 0] < height.shape[1]) & (pixel[:, 1] >= 0) & (pixel[:, 1] < height.shape[0])
    ground_z = np.full(len(city), np.nan)
    ground_z[on_raster] = height[pixel[on_raster, 1], pixel[on_raster, 0]]
    with np.errstate(invalid="ignore"):
        return (np.abs(city[:, 2] - ground_z) <= AV2_GROUND_HEIGHT_THRESHOLD_M) | (city[:, 2] < ground_z)


def _av2_label_columns(log_dir: str, num_points: int) -> dict[str, np.ndarray]:
    """`classes`, `dynamic`, `is_ground_0` of flow_labels.feather, one row per sweep-0 point."""
    import pyarrow.feather as feather
    path = os.path.join(log_dir, "flow_labels.feather")
    table = feather.read_table(path)
    out = {}
    for name in ("classes", "dynamic", "is_ground_0"):
        if name not in table.schema.names:
            raise argoverse2.Argoverse2FormatError(path, name, f"missing; the file has {table.schema.names}")
        column = table.column(name)
        if column.null_count:
            raise argoverse2.Argoverse2FormatError(path, name, f"{column.null_count} null values")
        out[name] = column.to_numpy(zero_copy_only=False)
        if len(out[name]) != num_points:
            raise argoverse2.Argoverse2FormatError(path, name, f"{len(out[name])} rows for a sweep of {num_points} "
                                                   "points")
    return out


def av2_sample_check(log_dir: str, options: NsfpOptions = AV2_NSFP_OPTIONS, point_stride: int = 1,
                     progress: Callable[[int, float], None] | None = None) -> dict:
    """NSFP pseudo-labels of an Argoverse 2 log's sweep 0 against Argoverse's own flow labels of it.

    Argoverse's flow goes forward, sweep 0 -> sweep 1; the project's labels give each t0 point's motion from t-1.
    So t0 := sweep 0 and "t-1" := sweep 1 moved into sweep 0's frame; Argoverse's forward displacement (ego motion
    removed, `argoverse2.argoverse_flow_in_paper_convention`) is then -motion_m. Ground: `is_ground_0` for sweep 0,
    the map raster for sweep 1 (its agreement with `is_ground_0` on sweep 0 is reported). Evaluated: non-ground points
    with max(|x|, |y|) <= 35 m; EPE in metres per frame (the sweep interval, ~0.1 s); foreground = classes > 0.
    `point_stride` > 1: every point_stride-th point of each sweep only (a cheaper check), evaluated on those."""
    if isinstance(point_stride, bool) or not isinstance(point_stride, int) or point_stride < 1:
        raise ValueError(f"av2_sample_check: point_stride must be an integer >= 1, got {point_stride!r}")
    stamps = argoverse2.sweep_timestamps(log_dir)
    if len(stamps) < 2:
        raise argoverse2.Argoverse2FormatError(os.path.join(log_dir, "sensors", "lidar"), "file",
                                               f"needs two sweeps, found {len(stamps)}")
    sweep0, sweep1 = (argoverse2.read_sweep(log_dir, s) for s in stamps[:2])
    true_m, points0 = argoverse2.argoverse_flow_in_paper_convention(log_dir)
    labels = _av2_label_columns(log_dir, len(points0))
    ground0 = labels["is_ground_0"].astype(bool)
    map_ground0 = av2_map_ground_mask(log_dir, sweep0["points_xyz"], sweep0["pose"])
    ground1 = av2_map_ground_mask(log_dir, sweep1["points_xyz"], sweep1["pose"])
    sweep1_in_0 = geometry.transform_points_np(sweep1["points_xyz"],
                                               geometry.t0_from_tm1_np(sweep0["pose"], sweep1["pose"]))
    dt_s = (stamps[1] - stamps[0]) * 1e-9
    every0, every1 = slice(None, None, point_stride), slice(None, None, point_stride)
    points0, true_m, ground0, map_ground0 = points0[every0], true_m[every0], ground0[every0], map_ground0[every0]
    labels = {k: v[every0] for k, v in labels.items()}
    sweep0_xyz, sweep1_in_0, ground1 = sweep0["points_xyz"][every0], sweep1_in_0[every1], ground1[every1]
    result = nsfp_flow(sweep0_xyz, sweep1_in_0, dt_s, options, keep_t0=~ground0, keep_tm1=~ground1,
                       progress=progress)
    predicted_m = -result.flow_mps_t0.astype(np.float64) * dt_s  # forward displacement, sweep 0 -> sweep 1
    evaluated = ~ground0 & (np.abs(points0[:, :2]).max(1) <= AV2_EVAL_HALF_EXTENT_M)
    epe_m = np.linalg.norm(predicted_m - true_m, axis=1)
    zero_m = np.linalg.norm(true_m, axis=1)
    dynamic, foreground = labels["dynamic"].astype(bool), labels["classes"] > 0
    subsets = {"dynamic": dynamic, "static": ~dynamic, "fg_dynamic": foreground & dynamic,
               "fg_static": foreground & ~dynamic, "bg_static": ~foreground}

    def mean_over(values, subset):
        chosen = evaluated & subset
        return float(values[chosen].mean()) if chosen.any() else float("nan")
    three_way = [mean_over(epe_m, subsets[k]) for k in ("fg_dynamic", "fg_static", "bg_static")]
    return {
        "epe_m_per_frame": {k: mean_over(epe_m, s) for k, s in subsets.items()},
        "three_way_mean_epe_m": float(np.nanmean(three_way)),
        "zero_flow_epe_m_per_frame": {k: mean_over(zero_m, s) for k, s in subsets.items()},
        "counts": {k: int((evaluated & s).sum()) for k, s in subsets.items()},
        "evaluated_points": int(evaluated.sum()),
        "evaluated_points_outside_crop_flow_0": int((evaluated & ~result.valid_t0).sum()),
        "optimised_points_t0": int(result.valid_t0.sum()),
        "optimised_points_tm1": int((keep_mask(sweep1_in_0.astype(np.float32), options) & ~ground1).sum()),
        "map_ground_agreement_with_is_ground_0": float((map_ground0 == ground0).mean()),
        "sweep_interval_s": dt_s,
        "point_stride": point_stride,
        "iterations": result.num_iterations,
        "loss_m": result.loss_m,
        "grid_s": result.grid_s,
        "fit_s": result.fit_s,
    }
