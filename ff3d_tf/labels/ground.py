"""Ground points of a LiDAR sweep without a map: a local height rule, the same for every cloud it is given; for a
pair of sweeps in one frame, `pair_ground_masks` (one surface for both, and raised ground that stayed put).

The sweep's x-y plane (vehicle frame) is cut into `cell_m` x `cell_m` columns. A column's ground height is a low
percentile of the z of its points (`percentile`: robust to a few returns below the road surface, e.g. multipath); a
column with fewer than `min_points` points takes the lowest ground height among its 8 neighbours that have one (again,
up to `fill_passes` times), and one still without, the sweep's own low percentile. A point's ground height is the
bilinear interpolation of its four nearest column centres' heights, so a slope is followed across a column instead of
stepping at its edges (and carried on past the outermost centres); the point is ground when it lies less than
`above_m` above that height. A column filled by an object's roof alone (no ground under it seen) is the rule's known
miss, made rarer by columns wider than a roof.
"""
from __future__ import annotations

import itertools

import numpy as np

GROUND_CELL_M = 4.0
GROUND_ABOVE_M = 0.3
GROUND_PERCENTILE = 5.0
GROUND_MIN_POINTS = 8
# `pair_ground_masks`: columns longer than a car (so a column rarely holds an object and no road; the default counts
# the lower parts of objects and kerbs as ground more often), and a point up to STATIC_BAND_M above the surface whose
# nearest point of the other sweep lies within STATIC_MATCH_M is ground too.
PAIR_GROUND_CELL_M = 8.0
STATIC_BAND_M = 0.4
STATIC_MATCH_M = 0.1
_MAX_COLUMNS_PER_AXIS = 1024  # a sweep wider than this many columns gets wider columns
_FILL_PASSES = 3


def _column_heights(cells: np.ndarray, z: np.ndarray, shape: tuple[int, int], percentile: float,
                    min_points: int) -> np.ndarray:
    """[X, Y] the `percentile` z of each column with at least `min_points` points, NaN elsewhere."""
    column = cells[:, 0] * shape[1] + cells[:, 1]
    order = np.lexsort((z, column))  # by column, then z
    starts = np.flatnonzero(np.r_[True, np.diff(column[order]) != 0])
    counts = np.diff(np.r_[starts, len(order)])
    picked = starts + np.floor((counts - 1) * percentile / 100.0).astype(np.int64)
    heights = np.full(shape[0] * shape[1], np.nan)
    dense = counts >= min_points
    heights[column[order][starts][dense]] = z[order][picked][dense]
    return heights.reshape(shape)


def _filled(heights: np.ndarray, fallback: float) -> np.ndarray:
    """`heights` with each NaN column given the lowest height of its 8 neighbours (repeated), then `fallback`."""
    for _ in range(_FILL_PASSES):
        missing = np.isnan(heights)
        if not missing.any():
            break
        padded = np.pad(heights, 1, constant_values=np.nan)
        shifts = [padded[1 + dx: padded.shape[0] - 1 + dx, 1 + dy: padded.shape[1] - 1 + dy]
                  for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
        stacked = np.stack(shifts)
        has = ~np.isnan(stacked).all(0)
        lowest = np.min(np.where(np.isnan(stacked), np.inf, stacked), axis=0)
        heights = np.where(missing & has, lowest, heights)
    return np.where(np.isnan(heights), fallback, heights)


def height_ground_mask(points_xyz, cell_m: float = GROUND_CELL_M, above_m: float = GROUND_ABOVE_M,
                       percentile: float = GROUND_PERCENTILE, min_points: int = GROUND_MIN_POINTS) -> np.ndarray:
    """[N] bool: the points within `above_m` of their interpolated ground height (module docstring)."""
    xyz = _checked_points(points_xyz, "height_ground_mask")
    return xyz[:, 2] < _ground_height_m(xyz, cell_m, percentile, min_points) + above_m


def _checked_points(points_xyz, what: str) -> np.ndarray:
    xyz = np.asarray(points_xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"{what}: points must be [N, 3], got {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise ValueError(f"{what}: points have non-finite coordinates")
    return xyz


def _ground_height_m(xyz: np.ndarray, cell_m: float, percentile: float = GROUND_PERCENTILE,
                     min_points: int = GROUND_MIN_POINTS) -> np.ndarray:
    """[N] the interpolated ground height (m) under each point (module docstring) of points already checked
    (`_checked_points`)."""
    if len(xyz) == 0:
        return np.zeros(0)
    low = xyz[:, :2].min(0)
    extent = xyz[:, :2].max(0) - low
    cell_m = max(cell_m, float(extent.max()) / (_MAX_COLUMNS_PER_AXIS - 1))
    shape = tuple(int(s) for s in np.floor(extent / cell_m).astype(np.int64) + 1)
    u = (xyz[:, :2] - low) / cell_m  # column coordinates: column i spans [i, i + 1), its centre at i + 0.5
    cells = np.minimum(np.floor(u).astype(np.int64), np.array(shape) - 1)
    heights = _column_heights(cells, xyz[:, 2], shape, percentile, min_points)
    heights = _filled(heights, float(np.percentile(xyz[:, 2], percentile)))
    # bilinear interpolation between the four nearest column centres; beyond the outer centres, the slope of the last
    # two columns carried on (a slope does not flatten at the sweep's edge)
    heights = np.pad(heights, 1, mode="reflect", reflect_type="odd") if min(shape) > 1 else \
        np.pad(heights, 1, mode="edge")  # the centre of padded column j lies at j - 0.5 in u
    v = u + 0.5
    base = np.clip(np.floor(v).astype(np.int64), 0, np.array(heights.shape) - 2)
    frac = np.clip(v - base, 0.0, 1.0)
    h00, h10 = heights[base[:, 0], base[:, 1]], heights[base[:, 0] + 1, base[:, 1]]
    h01, h11 = heights[base[:, 0], base[:, 1] + 1], heights[base[:, 0] + 1, base[:, 1] + 1]
    return ((1 - frac[:, 0]) * ((1 - frac[:, 1]) * h00 + frac[:, 1] * h01)
            + frac[:, 0] * ((1 - frac[:, 1]) * h10 + frac[:, 1] * h11))


def pair_ground_masks(points_xyz_t0, points_xyz_tm1_in_t0, cell_m: float = PAIR_GROUND_CELL_M,
                      above_m: float = GROUND_ABOVE_M, static_band_m: float = STATIC_BAND_M,
                      static_match_m: float = STATIC_MATCH_M) -> tuple[np.ndarray, np.ndarray]:
    """(ground of the t0 cloud, ground of the t-1 cloud), both in the t0 frame, where their static ground coincides:
    one surface (`_ground_height_m`) from the union of the two clouds, so a ground point is ground in both alike; the
    points within `above_m` of it; and the points up to `static_band_m` above it whose nearest point of the other
    cloud lies within `static_match_m`. The last are raised ground the band misses (kerbs, verges, ramps): ground
    stays where it was between two sweeps, while the lower parts of a moving object (bumpers, wheels) have moved."""
    t0 = _checked_points(points_xyz_t0, "pair_ground_masks (t0)")
    tm1 = _checked_points(points_xyz_tm1_in_t0, "pair_ground_masks (t-1)")
    both = np.concatenate([t0, tm1])
    rise_m = both[:, 2] - _ground_height_m(both, cell_m)
    ground = rise_m < above_m
    band = ~ground & (rise_m < static_band_m)
    n0 = len(t0)
    for own, other, offset in ((t0, tm1, 0), (tm1, t0, n0)):
        candidates = np.flatnonzero(band[offset:offset + len(own)])
        ground[offset + candidates] = has_neighbour_within(own[candidates], other, static_match_m)
    return ground[:n0], ground[n0:]


def has_neighbour_within(query_xyz, target_xyz, radius_m: float) -> np.ndarray:
    """[Q] bool: whether a target point lies within `radius_m` of each query point. The targets are hashed into cubes
    of side `radius_m`, so a neighbour lies in one of the 27 cubes around the query's."""
    query, target = np.asarray(query_xyz, np.float64), np.asarray(target_xyz, np.float64)
    found = np.zeros(len(query), bool)
    if len(query) == 0 or len(target) == 0:
        return found
    low = np.minimum(query.min(0), target.min(0)) - radius_m  # every cube index >= 1, so an offset of -1 is >= 0

    def cubes(xyz):
        return np.floor((xyz - low) / radius_m).astype(np.int64)
    target_cubes, query_cubes = cubes(target), cubes(query)
    dims = np.maximum(target_cubes.max(0), query_cubes.max(0)) + 2

    def key(c):
        return (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
    order = np.argsort(key(target_cubes), kind="stable")
    target_keys, target = key(target_cubes)[order], target[order]
    for offset in itertools.product((-1, 0, 1), repeat=3):
        todo = np.flatnonzero(~found)
        keys = key(query_cubes[todo] + np.array(offset))
        start = np.searchsorted(target_keys, keys, "left")
        count = np.searchsorted(target_keys, keys, "right") - start
        pair_query = np.repeat(todo, count)
        pair_target = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start, count)
        close = ((query[pair_query] - target[pair_target]) ** 2).sum(1) <= radius_m ** 2
        found[pair_query[close]] = True
    return found
