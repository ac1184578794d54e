"""Ground points of a LiDAR sweep without a map: a local height rule, the same for every cloud it is given.

The sweep's x-y plane (vehicle frame) is cut into `cell_m` x `cell_m` columns. A column's ground height is a low
percentile of the z of its points (`percentile`: robust to a few returns below the road surface, e.g. multipath); a
column with fewer than `min_points` points takes the lowest ground height among its 8 neighbours that have one (again,
up to `fill_passes` times), and one still without, the sweep's own low percentile. A point's ground height is the
bilinear interpolation of its four nearest column centres' heights, so a slope is followed across a column instead of
stepping at its edges (and carried on past the outermost centres); the point is ground when it lies less than `above_m` above that height. A column filled by an
object's roof alone (no ground under it seen) is the rule's known miss, made rarer by columns wider than a roof.
"""
from __future__ import annotations

import numpy as np

GROUND_CELL_M = 4.0
GROUND_ABOVE_M = 0.3
GROUND_PERCENTILE = 5.0
GROUND_MIN_POINTS = 8
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
    xyz = np.asarray(points_xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"height_ground_mask: points must be [N, 3], got {xyz.shape}")
    if len(xyz) == 0:
        return np.zeros(0, bool)
    if not np.isfinite(xyz).all():
        raise ValueError("height_ground_mask: points have non-finite coordinates")
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
    ground_z = ((1 - frac[:, 0]) * ((1 - frac[:, 1]) * h00 + frac[:, 1] * h01)
                + frac[:, 0] * ((1 - frac[:, 1]) * h10 + frac[:, 1] * h11))
    return xyz[:, 2] < ground_z + above_m
