"""The distance transform of a cloud and the Chamfer distance (its moved-to-fixed side read from the transform or found
exactly, its other side through given correspondences): what the NSFP pseudo-labels (`ff3d_tf.labels.nsfp`) pull the
moved clouds onto.

Fast Neural Scene Flow (FastNSF; Li, Zheng, Ferroni, Pontes and Lucey, ICCV 2023): the Chamfer term reads a
precomputed distance transform of the fixed cloud (a voxel grid of distances to its nearest point, trilinearly
interpolated), so a step costs O(N) instead of O(N*M). Here: exact nearest neighbours by brute force, chunked
(`nearest_index`, `exact_nearest_distance_m`; for checking), the grid's bounds (`grid_geometry`), its build
(`build_distance_grid`, its compiled `grid_program`) and read (`read_distance_grid`), `chamfer_loss` on either and
`reverse_chamfer_loss`.

The distance transform (`build_distance_grid`) is a pyramid of grids, each `PYRAMID_FACTORS` times coarser than the one
below, the finest `cell_m` apart. On each level a node's value is the exact Euclidean distance to its nearest point
wherever that distance is at most `band_cells` cells of that level (found by scattering each point's distance to the
nodes around it, `band_offsets`: every point within that distance of a node is among the scattered ones, so the minimum
is exact); farther, the trilinear interpolation of the level above; the top level (at most `TOP_LEVEL_MAX_NODES` nodes)
is brute force everywhere. Cost O(points x stencil + nodes), no O(nodes x points) term.

XLA: one compiled grid program per (grid shape, point bucket); each axis is rounded up to a multiple of 8 nodes and the
flat grid is padded to a bucket size (`ff3d_tf.data.pairs.bucket_size`), so few shapes reach the fit.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import tensorflow as tf

from ff3d_tf.data.pairs import bucket_size

PYRAMID_FACTORS = (2, 4)  # level l+1 of the distance pyramid is PYRAMID_FACTORS[min(l, 1)] times coarser than l
TOP_LEVEL_MAX_NODES = 4096  # the pyramid's top level, brute force everywhere, has at most this many nodes
_DIMS_MULTIPLE = 8  # each grid axis is rounded up to a multiple of this many nodes (fewer compiled grid programs)
_GRID_BUCKET_BASE = 1 << 16  # the flat grid handed to the fit is padded to bucket_size(nodes, this)
_TOP_NODE_CHUNK = 256  # top-level nodes per brute-force step ([chunk, points] distances)
_EXACT_QUERY_CHUNK = 512  # query points per step of the exact nearest neighbours ([chunk, points] distances)
_SQRT_FLOOR = 1e-12  # distance = sqrt(max(d^2, floor)): a finite gradient where a point sits on its neighbour


class DistanceGrid(NamedTuple):
    """Distance transform of a cloud: `distance_m[(i * dims[1] + j) * dims[2] + k]` is the value at the node
    `origin_m + (i, j, k) * cell_m` (see the module docstring for what it equals); entries past dims' product pad."""
    distance_m: tf.Tensor  # [C] float32, C a bucket size >= prod(dims)
    origin_m: tf.Tensor  # [3] float32
    dims: tf.Tensor  # [3] int32, each >= 2
    cell_m: tf.Tensor  # [] float32


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
    return _distance_m(query_xyz, tf.gather(target_xyz, nearest_index(query_xyz, target_xyz, target_mask)))


def _distance_m(a_xyz, b_xyz):
    """[N] distance (m) between paired points, from their coordinate difference; a finite gradient at 0."""
    return tf.sqrt(tf.maximum(tf.reduce_sum((a_xyz - b_xyz) ** 2, -1), _SQRT_FLOOR))


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


def padded_grid_cells(dims) -> int:
    """Length of a grid's flat distances as `grid_program` returns them: the node count, padded to a bucket size."""
    return bucket_size(int(np.prod(dims)), _GRID_BUCKET_BASE)


def grid_program(dims: tuple, band_cells: int, coarse_band_cells: int, factors: tuple = PYRAMID_FACTORS):
    """The compiled distance transform for one grid shape (retraced per point bucket): (points_xyz [P,3] m,
    point_mask [P] bool, origin_m [3], cell_m []) -> distance_m [padded_grid_cells(dims)], zero past the nodes. The
    points are sorted into node order first, so that neighbouring points scatter into neighbouring memory (the result
    does not depend on the order)."""
    dims = tuple(int(d) for d in dims)
    key = (dims, band_cells, coarse_band_cells, tuple(factors))
    if key not in _GRID_PROGRAMS:
        levels = pyramid_dims(dims, factors)
        fine, coarse = band_offsets(band_cells), band_offsets(coarse_band_cells)
        num_nodes = int(np.prod(dims))

        @tf.function(jit_compile=True)
        def build(points_xyz, point_mask, origin_m, cell_m):
            node = tf.cast(tf.floor((points_xyz - origin_m) / cell_m + 0.5), tf.int32)
            order = tf.argsort((node[:, 0] * dims[1] + node[:, 1]) * dims[2] + node[:, 2], stable=True)
            points_xyz, point_mask = tf.gather(points_xyz, order), tf.gather(point_mask, order)
            top = len(levels) - 1
            values = tf.sqrt(_brute_squared_m2(points_xyz, point_mask, origin_m, levels[top],
                                               cell_m * level_scale(top, factors)))
            for level in range(top - 1, -1, -1):
                h = cell_m * level_scale(level, factors)
                band, offsets = (band_cells, fine) if level == 0 else (coarse_band_cells, coarse)
                d2 = _band_squared_m2(points_xyz, point_mask, origin_m, levels[level], h, offsets)
                coarser = _upsample(values, levels[level], level_factor(level, factors))
                values = tf.where(d2 <= tf.square(band * h), tf.sqrt(d2), coarser)
            return tf.pad(tf.reshape(values, [-1]), [[0, padded_grid_cells(dims) - num_nodes]])
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


def fitted_grid_geometry(clouds_xyz: list[np.ndarray], cell_m: float, margin_m: float, max_cells: int,
                         box_m: tuple | None = None):
    """(origin_m, dims, cell) of `grid_geometry` at the finest cell of `cell_m` x 1.25^k (k = 0, 1, ...) whose grid has
    at most `max_cells` nodes: a region too large for the finest cell gets a coarser distance transform, never a
    refusal (the region itself is the caller's to bound)."""
    for _ in range(64):
        try:
            return (*grid_geometry(clouds_xyz, cell_m, margin_m, max_cells, box_m), cell_m)
        except ValueError:
            cell_m *= 1.25
    raise ValueError(f"fitted_grid_geometry: no cell fits {max_cells} nodes")


def build_distance_grid(points_xyz, point_mask, origin_m, dims, cell_m: float, band_cells: int = 4,
                        coarse_band_cells: int = 3, factors: tuple = PYRAMID_FACTORS) -> DistanceGrid:
    """The distance transform of the valid points of `points_xyz` [P,3] on the given grid (module docstring): at a
    node whose nearest point is within `band_cells` * `cell_m`, the exact distance to it."""
    points_xyz = np.asarray(points_xyz, np.float32)
    point_mask = np.asarray(point_mask, bool)
    if not point_mask.any():
        raise ValueError("build_distance_grid: no valid point")
    program = grid_program(dims, band_cells, coarse_band_cells, factors)
    values = program(tf.constant(points_xyz), tf.constant(point_mask), tf.constant(origin_m, tf.float32),
                     tf.constant(cell_m, tf.float32))
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


def chamfer_loss(query_xyz, query_mask, target_xyz, target_mask, grid: DistanceGrid | None, exact: bool,
                 squared: bool = False, truncate_m=None):
    """One-sided Chamfer distance: mean over valid query points of the distance (m; `squared`: its square, m^2) to the
    nearest valid target point, exact (brute force) or read from `grid`, the target's distance transform. Truncated
    (NSFP): a point whose distance is `truncate_m` or more counts 0 (still in the mean's denominator)."""
    if exact:
        distance_m = exact_nearest_distance_m(query_xyz, target_xyz, target_mask)
    else:
        distance_m = read_distance_grid(grid, query_xyz)
    return _mean_distance(distance_m, query_mask, squared, truncate_m)


def reverse_chamfer_loss(target_xyz, target_mask, moved_xyz, nearest_moved, squared: bool = False, truncate_m=None):
    """The other side of the Chamfer distance: mean over valid target points of the distance (m; `squared`: its
    square) to the moved point `nearest_moved` [M] int32 names (its nearest valid moved point, `nearest_index`, found
    by the caller, possibly some steps ago), truncated as `chamfer_loss`; differentiable in `moved_xyz`."""
    distance_m = _distance_m(target_xyz, tf.gather(moved_xyz, nearest_moved))
    return _mean_distance(distance_m, target_mask, squared, truncate_m)


def _mean_distance(distance_m, mask, squared: bool, truncate_m):
    if truncate_m is not None:
        distance_m = tf.where(distance_m < truncate_m, distance_m, 0.0)
    if squared:
        distance_m = tf.square(distance_m)
    weight = tf.cast(mask, tf.float32)
    return tf.reduce_sum(distance_m * weight) / tf.maximum(tf.reduce_sum(weight), 1.0)
