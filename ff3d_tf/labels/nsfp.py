"""Scene-flow pseudo-labels for one pair of sweeps by Neural Scene Flow Prior: the options, the MLPs, the objective, the
per-pair fit (`nsfp_flow`) and the points it uses (`keep_mask`). The Chamfer term and the distance transform it reads
are in `ff3d_tf.labels.distance_grid`; the check against Argoverse 2's own flow in `ff3d_tf.labels.nsfp_av2_check`.

Neural Scene Flow Prior (NSFP; Li, Kaesemodel Pontes and Lucey, NeurIPS 2021): the flow of a pair is the output of a
coordinate MLP (8 hidden layers of 128 units, ReLU), fitted to that pair alone with Adam on a Chamfer objective, plus a
second MLP for the backward flow (its cycle term) and early stopping (NSFP's defaults: learning rate 0.008, L2 weight
decay 1e-4 on both MLPs, patience 100 steps, minimum improvement 1e-4, at most 5000 steps; its Chamfer terms are
mean SQUARED distances, truncated: a point whose squared distance is 2 m^2 or more counts 0; here the truncation is
an option, `truncate_m=NSFP_TRUNCATE_M`, off by default: on the Argoverse 2 sample pair with it the one-sided fit
stalled within 25 steps at zero motion, without it the loss kept falling). As Fast Neural Scene Flow (FastNSF), the
Chamfer term reads a precomputed distance transform of the fixed cloud (`options.exact_chamfer`: exact nearest
neighbours instead, for checking). Ground removal and the range crop (ZeroFlow's NSFP: z in [-3, 3] m) are options.

Convention (the project's labels, `ff3d_tf.labels.box_flow`): the forward MLP gives `motion_m`, the displacement of
each t0 point from t-1 to t0 in metres in the t0 vehicle frame; `points_xyz_t0 - motion_m` is where the point was at
t-1 and is pulled onto the ego-compensated t-1 cloud `points_xyz_tm1_in_t0`; `flow_mps_t0 = motion_m / dt_s`. The
cycle term moves that moved-back cloud forward again with the backward MLP and pulls it onto the t0 cloud. Each term's
moved-to-fixed side reads the fixed cloud's distance transform (mean squared distance of each moved point to its
nearest fixed point, m^2). NSFP's Chamfer is two-sided: also each fixed point to its nearest moved point, which
forbids many moved points collapsing onto a few fixed ones. The moved cloud changes every step, so that side has no
precomputed transform: with `reverse_every` = k > 0 its correspondences (each fixed point's nearest moved point) are
found exactly (`reverse_correspondences`, O(N*M)) at every k-th step and held in between, the distance to the named
point differentiable (`distance_grid.reverse_chamfer_loss`). `fit_every` = k > 1 fits the MLPs to every k-th kept
point of each cloud and evaluates the best step's forward MLP (the prior is a continuous function of xyz) at every
kept t0 point: k times fewer points a step and k^2 times less nearest-neighbour search.

Why squared (NSFP's choice, the default; `squared_chamfer=False` gives mean distances in m): at the start both MLPs
output ~0, where the cycle term is exactly 0 and holds the forward motion back until the backward MLP has learnt to
undo it. With plain distances every point's gradient has unit length wherever it is, so that restoring pull is as
strong for a 1 cm motion as for a 1 m one, while the forward term's pulls, each towards the point's current (often
wrong) nearest neighbour, largely cancel: a moving object then stays at zero motion with exact neighbours, or creeps
(the distance transform's smoothing) until early stopping ends the fit with its rotation unfitted. Squared distances
pull in proportion to the distance: the cycle's pull vanishes at zero motion and the forward term wins
(tests/labels/test_nsfp.py, the rigid-motion test, with both Chamfer forms).

XLA: one compiled fit program per (point bucket, grid-size bucket) (`ff3d_tf.data.pairs.bucket_size`; the two clouds
share a point bucket), run in segments of `segment_iterations` steps so that a caller sees progress; with the range
crop set, x and y of the grid come from the crop box, so only the z extent varies between pairs (fewer compiled grid
programs). Same seed, same inputs, same device: same labels.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, NamedTuple

import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig, nsfp_option_problem
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.labels.distance_grid import (DistanceGrid, build_distance_grid, chamfer_loss, fitted_grid_geometry,
                                          nearest_index, reverse_chamfer_loss)
from ff3d_tf.model.step import adam_apply

ADAM_BETA_1, ADAM_BETA_2, ADAM_EPSILON = 0.9, 0.999, 1e-8  # PyTorch's Adam defaults (NSFP's optimiser)
NSFP_TRUNCATE_M = math.sqrt(2.0)  # NSFP's truncated Chamfer: squared nearest distances of 2 m^2 or more count 0


@dataclasses.dataclass(frozen=True)
class NsfpOptions:
    """Options of `nsfp_flow`, by default NSFP's (but one-sided and untruncated; `MEASURED_FIT_OPTIONS`, the defaults
    of the config's `nsfp` section, is the pseudo-label job's fit; `options_from_config` builds them from a config).
    The objective and `min_delta` are in m^2 (mean squared Chamfer distances; m with `squared_chamfer=False`). Checked
    by the rules of the config's section (`ff3d_tf.config.nsfp_option_problem`)."""
    hidden_layers: int = 8  # NSFP: 8 hidden layers of 128, ReLU
    hidden_units: int = 128
    learning_rate: float = 8e-3  # Adam (NSFP and ZeroFlow: 0.008)
    warmup_iterations: int = 0  # learning rate ramped linearly from learning_rate / n to it over the first n steps
    weight_decay: float = 1e-4  # L2 added to the gradients (NSFP's per-group weight_decay on both MLPs)
    max_iterations: int = 5000
    patience: int = 100  # stop after this many steps without the loss improving by more than min_delta
    min_delta: float = 1e-4  # in the objective's units (m^2; m with squared_chamfer=False)
    backward_cycle: bool = True  # NSFP's backward-flow term
    reverse_every: int = 0  # two-sided Chamfer (NSFP): each fixed point's nearest moved point, exact, found again every
    # this many steps (O(N*M) each time) and held in between; 0: one-sided (moved points to the fixed cloud only)
    fit_every: int = 1  # fit on every k-th kept point of both clouds, then evaluate the fitted MLP at every kept point
    exact_chamfer: bool = False  # exact nearest neighbours (O(N*M) a step; for checking) instead of the grid
    squared_chamfer: bool = True  # mean squared distance (NSFP's Chamfer; see the module docstring), else mean distance
    truncate_m: float | None = None  # points this far or farther from the target count 0 (NSFP: NSFP_TRUNCATE_M)
    grid_cell_m: float = 0.1  # finest level of the distance transform (FastNSF: 0.1 m), coarsened by 1.25x steps
    # where the fitted region would need more than max_grid_cells nodes
    grid_margin_m: float = 0.5  # grid bounds: the kept clouds' bounding box (or crop box) grown by this much
    band_cells: int = 4  # finest level exact wherever the nearest point is within this many cells
    coarse_band_cells: int = 3  # the same on the coarser levels
    max_grid_cells: int = 1 << 26  # largest grid (memory: 4 bytes a node, two grids a pair); see grid_cell_m
    remove_ground_below_z_m: float | None = None  # drop points with z below this (vehicle frame), None: keep all
    crop_xy_half_extent_m: float | None = None  # keep points with |x| and |y| at most this, None: no crop
    crop_z_range_m: tuple[float, float] | None = None  # keep points with z in [lo, hi] (ZeroFlow: (-3, 3))
    point_bucket_base: int = 1024
    segment_iterations: int = 100  # Adam steps per compiled call (progress is reported between calls)
    seed: int = 0

    def __post_init__(self):
        for field in dataclasses.fields(self):  # the rules of the config's nsfp section, one statement of them
            problem = nsfp_option_problem(field.name, getattr(self, field.name))
            if problem:
                raise ValueError(f"NsfpOptions.{field.name}: {problem}, got {getattr(self, field.name)!r}")


def _is_real(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def options_from_config(cfg: ExperimentConfig) -> NsfpOptions:
    """The fit of the pseudo-label job that `cfg` (an ExperimentConfig) configures: every NsfpOptions field from the
    field of the same name in `cfg.nsfp`."""
    return NsfpOptions(**{f.name: getattr(cfg.nsfp, f.name) for f in dataclasses.fields(NsfpOptions)})


# The pseudo-label job's fit (`ff3d_tf.labels.pseudo_records`): the defaults of the config's `nsfp` section
# (`ff3d_tf.config.NsfpConfig`, which says how they were chosen). `NsfpOptions()` itself keeps NSFP's published fit.
MEASURED_FIT_OPTIONS = options_from_config(ExperimentConfig())


@dataclasses.dataclass(frozen=True)
class NsfpResult:
    flow_mps_t0: np.ndarray  # [N,3] float32, t0 vehicle frame; 0 where not valid
    valid_t0: np.ndarray  # [N] bool: the point was kept (ground removal, crop) and optimised
    num_iterations: int  # Adam steps taken
    loss: float  # best objective (forward + cycle Chamfer; m^2, or m with squared_chamfer=False); its flow is returned
    grid_s: float  # seconds building the distance grids (0 with exact_chamfer)
    fit_s: float  # seconds in the fit
    grid_cell_m: float = float("nan")  # the distance transform's finest cell (>= options.grid_cell_m), NaN if no fit


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


def nsfp_objective(forward, backward, points_xyz_t0, mask_t0, points_xyz_tm1, mask_tm1, grid_tm1, grid_t0,
                   exact: bool, squared: bool = False, truncate_m=None, reverse_index=None):
    """(objective in m, or m^2 when `squared`; motion_m [B,3]): Chamfer of the moved-back t0 cloud to the t-1 cloud,
    plus (when `backward` is not None) Chamfer of that cloud moved forward by the backward MLP to the t0 cloud.
    `reverse_index` ([2,B] int32, `reverse_correspondences`) makes both terms two-sided (NSFP): row 0 names each t-1
    point's nearest moved-back point, row 1 each t0 point's nearest moved-forward point."""
    motion_m = mlp(forward, points_xyz_t0)
    moved_back_xyz = points_xyz_t0 - motion_m  # where each t0 point was at t-1
    loss = chamfer_loss(moved_back_xyz, mask_t0, points_xyz_tm1, mask_tm1, grid_tm1, exact, squared, truncate_m)
    if reverse_index is not None:
        loss += reverse_chamfer_loss(points_xyz_tm1, mask_tm1, moved_back_xyz, reverse_index[0], squared, truncate_m)
    if backward is not None:
        moved_forward_xyz = moved_back_xyz + mlp(backward, moved_back_xyz)
        loss += chamfer_loss(moved_forward_xyz, mask_t0, points_xyz_t0, mask_t0, grid_t0, exact, squared, truncate_m)
        if reverse_index is not None:
            loss += reverse_chamfer_loss(points_xyz_t0, mask_t0, moved_forward_xyz, reverse_index[1], squared,
                                         truncate_m)
    return loss, motion_m


def reverse_correspondences(forward, backward, points_xyz_t0, mask_t0, points_xyz_tm1):
    """[2,B] int32 for `nsfp_objective`'s `reverse_index`, by brute force (`nearest_index`): each t-1 point's nearest
    valid moved-back t0 point and each t0 point's nearest valid moved-forward point (row 1 zeros without
    `backward`)."""
    moved_back_xyz = points_xyz_t0 - mlp(forward, points_xyz_t0)
    rows = [nearest_index(points_xyz_tm1, moved_back_xyz, mask_t0)]
    if backward is not None:
        rows.append(nearest_index(points_xyz_t0, moved_back_xyz + mlp(backward, moved_back_xyz), mask_t0))
    else:
        rows.append(tf.zeros_like(rows[0]))
    return tf.stack(rows)


class _FitState(NamedTuple):
    step: tf.Tensor  # Adam steps taken
    params: list  # forward MLP's tensors, then the backward MLP's
    adam_m: list
    adam_v: list
    best_loss: tf.Tensor  # lowest objective seen; best_motion is its motion
    best_motion: tf.Tensor
    reference_loss: tf.Tensor  # early stopping: the loss at the last improvement by more than min_delta
    stale: tf.Tensor  # steps since then
    reverse_index: tf.Tensor  # [2,B] int32: the two-sided terms' correspondences (reverse_every > 0), else unused
    best_params: list  # the parameters of best_loss


@tf.function(jit_compile=True)
def _fit_segment(state: _FitState, clouds, grids, hyper, num_forward: int, exact: bool, squared: bool,
                 segment: int, reverse_every: int = 0):
    """Up to `segment` Adam steps on the NSFP objective in one in-graph loop, stopping early (patience) or at
    max_iterations; the loss of a step is that of the parameters before its update. `reverse_every` > 0: two-sided
    Chamfer, its correspondences found again at every step that is a multiple of it."""
    learning_rate, warmup, weight_decay, min_delta, patience, max_iterations, truncate_m = hyper
    end = tf.minimum(state.step + segment, max_iterations)

    def objective(p, reverse_index):
        return nsfp_objective(p[:num_forward], p[num_forward:] or None, *clouds, *grids, exact, squared, truncate_m,
                              reverse_index)

    def correspondences(s: _FitState):
        if not reverse_every:
            return s.reverse_index
        return tf.cond(tf.equal(s.step % reverse_every, 0),
                       lambda: reverse_correspondences(s.params[:num_forward], s.params[num_forward:] or None,
                                                       clouds[0], clouds[1], clouds[2]),
                       lambda: s.reverse_index)

    def body(s: _FitState):
        reverse_index = correspondences(s)
        with tf.GradientTape() as tape:
            tape.watch(s.params)
            loss, motion_m = objective(s.params, reverse_index if reverse_every else None)
        grads = tape.gradient(loss, s.params, unconnected_gradients=tf.UnconnectedGradients.ZERO)
        grads = [g + weight_decay * p for g, p in zip(grads, s.params)]
        best = loss < s.best_loss
        improved = loss < s.reference_loss - min_delta
        rate = learning_rate * tf.minimum(1.0, tf.cast(s.step + 1, tf.float32) / tf.cast(tf.maximum(warmup, 1),
                                                                                           tf.float32))
        params, adam_m, adam_v = adam_apply(s.params, grads, s.adam_m, s.adam_v, s.step, rate,
                                            ADAM_BETA_1, ADAM_BETA_2, ADAM_EPSILON)
        return _FitState(s.step + 1, params, adam_m, adam_v, tf.where(best, loss, s.best_loss),
                         tf.where(best, motion_m, s.best_motion), tf.where(improved, loss, s.reference_loss),
                         tf.where(improved, 0, s.stale + 1), reverse_index,
                         [tf.where(best, p, b) for p, b in zip(s.params, s.best_params)])

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
    `valid_t0` False, as do all points when either kept cloud is empty. `progress(steps, best_loss)` is called
    after every `segment_iterations` steps. With `fit_every` = k > 1 the MLPs are fitted to every k-th kept point of
    each cloud and the forward MLP of the best step gives the flow of every kept t0 point."""
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
    origin_m, dims, cell_m = fitted_grid_geometry([kept_t0, kept_tm1], options.grid_cell_m, options.grid_margin_m,
                                                  options.max_grid_cells, box)
    # Centred coordinates: the MLP sees the scene around 0, and the nearest-neighbour matmul keeps its precision.
    centre_m = (origin_m + (dims - 1) * np.float32(cell_m) / 2).astype(np.float32)
    kept_t0, kept_tm1, origin_m = kept_t0 - centre_m, kept_tm1 - centre_m, origin_m - centre_m
    fit_t0, fit_tm1 = kept_t0[:: options.fit_every], kept_tm1[:: options.fit_every]
    size = bucket_size(max(len(fit_t0), len(fit_tm1)), options.point_bucket_base)
    padded_t0, padded_tm1 = _padded(fit_t0, size), _padded(fit_tm1, size)
    start = time.perf_counter()
    grids = _grids(padded_t0, padded_tm1, origin_m, dims, cell_m, options)
    grid_s = time.perf_counter() - start if not options.exact_chamfer else 0.0
    start = time.perf_counter()
    state = _fit(padded_t0, padded_tm1, grids, size, options, progress)
    if options.fit_every == 1:
        motion_m = state.best_motion.numpy()[: len(kept_t0)]
    else:
        motion_m = _evaluate_mlp(state.best_params[: 2 * (options.hidden_layers + 1)], kept_t0)
    flow_mps[keep_t0] = motion_m / np.float32(dt_s)
    return NsfpResult(flow_mps, keep_t0, int(state.step), float(state.best_loss), grid_s, time.perf_counter() - start,
                      float(cell_m))


def _grids(padded_t0, padded_tm1, origin_m, dims, cell_m: float, options: NsfpOptions) -> tuple[DistanceGrid,
                                                                                                DistanceGrid]:
    """(t-1 grid, t0 grid) of the fit: distance transforms of the padded clouds, or placeholders with exact_chamfer
    (the t-1 grid twice without the cycle term)."""
    if options.exact_chamfer:
        placeholder = DistanceGrid(tf.zeros([8]), tf.zeros([3]), tf.constant([2, 2, 2]), tf.constant(1.0))
        return placeholder, placeholder

    def grid(padded):
        return build_distance_grid(*padded, origin_m, dims, cell_m, options.band_cells, options.coarse_band_cells)
    grid_tm1 = grid(padded_tm1)
    return grid_tm1, grid(padded_t0) if options.backward_cycle else grid_tm1


def _fit(padded_t0, padded_tm1, grids, size: int, options: NsfpOptions, progress) -> _FitState:
    """The fit's final state: compiled segments of `segment_iterations` steps until early stopping or the cap."""
    (t0, mask_t0), (tm1, mask_tm1) = [tuple(map(tf.constant, padded)) for padded in (padded_t0, padded_tm1)]
    state = initial_fit_state(options, size)
    hyper = (tf.constant(options.learning_rate, tf.float32), tf.constant(options.warmup_iterations),
             tf.constant(options.weight_decay, tf.float32),
             tf.constant(options.min_delta, tf.float32), tf.constant(options.patience),
             tf.constant(options.max_iterations),
             tf.constant(np.inf if options.truncate_m is None else options.truncate_m, tf.float32))
    num_forward = 2 * (options.hidden_layers + 1)
    while True:
        state = _fit_segment(state, (t0, mask_t0, tm1, mask_tm1), grids, hyper, num_forward, options.exact_chamfer,
                             options.squared_chamfer, options.segment_iterations, options.reverse_every)
        steps = int(state.step)
        if progress is not None:
            progress(steps, float(state.best_loss))
        if steps >= options.max_iterations or int(state.stale) >= options.patience:
            return state


_EVALUATE_CHUNK = 1 << 16  # points per call of the fitted MLP in `_evaluate_mlp`


@tf.function(jit_compile=True, reduce_retracing=True)
def _mlp_compiled(params, xyz):
    return mlp(params, xyz)


def _evaluate_mlp(params, points_xyz: np.ndarray) -> np.ndarray:
    """[P,3] the MLP at every point, in bucket-padded chunks (few compiled shapes)."""
    out = []
    for begin in range(0, len(points_xyz), _EVALUATE_CHUNK):
        chunk = points_xyz[begin: begin + _EVALUATE_CHUNK]
        padded, _ = _padded(chunk, bucket_size(len(chunk), 1024))
        out.append(_mlp_compiled(params, tf.constant(padded)).numpy()[: len(chunk)])
    return np.concatenate(out) if out else np.zeros((0, 3), np.float32)


def initial_fit_state(options: NsfpOptions, num_points: int) -> _FitState:
    """The fit's state before its first step: the MLPs initialised from `options.seed`, Adam's slots at 0."""
    params = init_mlp(options.seed, 0, options.hidden_layers, options.hidden_units)
    if options.backward_cycle:
        params += init_mlp(options.seed, 1, options.hidden_layers, options.hidden_units)
    zeros = [tf.zeros_like(p) for p in params]
    return _FitState(tf.constant(0), params, zeros, list(zeros), tf.constant(np.inf, tf.float32),
                     tf.zeros([num_points, 3]), tf.constant(np.inf, tf.float32), tf.constant(0),
                     tf.zeros([2, num_points], tf.int32), list(params))
