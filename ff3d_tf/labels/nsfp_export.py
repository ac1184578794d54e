"""NSFP's per-pair optimiser as portable XLA programs (TensorFlow side): per point bucket, the distance transform of
one cloud and a segment of S Adam steps of the fit, traced from `ff3d_tf.labels.nsfp` / `distance_grid` themselves
(so the export follows their objective) and written through `ff3d_tf.xla_program`; `ff3d_tf.labels.nsfp_program`
(format, loading; no TensorFlow) runs them where only JAX is installed (the lab times them: `lab.labels.nsfp_timing`).

Both programs are XLA programs in TensorFlow already (`jit_compile=True`), so both are exported: a GPU runs the whole
pair (grid build and fit) on the device. What stays on the host: the grid's bounds and the clouds' centring
(`distance_grid.grid_geometry`, numpy, once per pair), which fix the grid's node counts: a grid program is compiled per
(point bucket, node counts), as in TensorFlow. The grid program is `distance_grid.grid_program`
itself (it sorts the points into node order on the device).

The pairs are `nsfp_program.synthetic_pair` (uniform clouds in the crop box, a moving box with a known motion): the
runner regenerates them from a seed, so only programs and the MLPs' initial parameters travel.
The fit program's state is `nsfp._FitState` flattened (whatever fields it has); the manifest says, leaf by leaf, its
field, shape, dtype and how the runner makes its initial value (`_state_layout`). Not exported: `exact_chamfer`
(O(N*M), for checking) and `fit_every` (the entry's point count is the fitted count).
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf import xla_program
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.labels import distance_grid, nsfp, nsfp_program
from ff3d_tf.labels.distance_grid import DistanceGrid

TIMING_STEP_CAP = 2 ** 30  # patience and max_iterations of the exported hyperparameters: every call runs all its steps
REFERENCE_GRID_SAMPLES = 1 << 16  # about this many grid nodes (strided) of each reference grid are saved


def _num_forward(options: nsfp.NsfpOptions) -> int:
    return 2 * (options.hidden_layers + 1)


def fit_program_fn(options: nsfp.NsfpOptions, padded_points: int, segment_steps: int, grid_cells: int):
    """(flat function, argument specs) of `segment_steps` steps of `nsfp._fit_segment` for one bucket:
    (state leaves..., t0 xyz, t0 mask, t-1 xyz, t-1 mask, t-1 grid (distance_m [grid_cells], origin_m [3], dims [3]
    int32, cell_m []), t0 grid (the same), hyperparameters (`nsfp_program.HYPER_KEYS`)) -> state leaves."""
    if options.exact_chamfer:
        raise ValueError("NsfpOptions.exact_chamfer: the exported fit reads distance grids; export without it")
    template = nsfp.initial_fit_state(options, padded_points)
    leaves = tf.nest.flatten(template)
    num_state = len(leaves)

    def flat_fit(*flat):
        state = tf.nest.pack_sequence_as(template, list(flat[:num_state]))
        clouds = tuple(flat[num_state: num_state + 4])
        grid = flat[num_state + 4: num_state + 12]
        grids = (DistanceGrid(*grid[:4]), DistanceGrid(*grid[4:]))
        out = nsfp._fit_segment.python_function(state, clouds, grids, tuple(flat[num_state + 12:]),
                                                _num_forward(options), False, options.squared_chamfer,
                                                segment_steps, options.reverse_every)
        return tuple(tf.nest.flatten(out))

    p = padded_points
    grid_spec = [tf.TensorSpec([grid_cells], tf.float32), tf.TensorSpec([3], tf.float32),
                 tf.TensorSpec([3], tf.int32), tf.TensorSpec([], tf.float32)]
    specs = ([tf.TensorSpec(x.shape, x.dtype) for x in leaves]
             + [tf.TensorSpec([p, 3], tf.float32), tf.TensorSpec([p], tf.bool)] * 2 + grid_spec * 2
             + [tf.TensorSpec([], tf.int32 if k in nsfp_program.HYPER_INT_KEYS else tf.float32)
                for k in nsfp_program.HYPER_KEYS])
    return flat_fit, specs


def grid_program_fn(options: nsfp.NsfpOptions, dims, padded_points: int):
    """(function, argument specs, padded node count C) of `distance_grid.grid_program` for node counts `dims`:
    (points_xyz [P,3] m, point_mask [P] bool, origin_m [3], cell_m []) -> (distance_m [C],), as
    `build_distance_grid` computes it."""
    build = distance_grid.grid_program(dims, options.band_cells, options.coarse_band_cells)

    def grid(points_xyz, point_mask, origin_m, cell_m):
        return (build.python_function(points_xyz, point_mask, origin_m, cell_m),)

    specs = [tf.TensorSpec([padded_points, 3], tf.float32), tf.TensorSpec([padded_points], tf.bool),
             tf.TensorSpec([3], tf.float32), tf.TensorSpec([], tf.float32)]
    return grid, specs, distance_grid.padded_grid_cells(dims)


def state_layout(options: nsfp.NsfpOptions, padded_points: int) -> tuple[list[dict], dict]:
    """Per leaf of the flattened initial `_FitState` of one bucket: {"field", "shape", "dtype", "init"}, init one of
    {"param": i} (the i-th MLP parameter, `initial_params.npz`), {"value": x} (a scalar), {"zeros": true} or
    {"array": key} (any other start value, returned in the dict for the export's npz)."""
    template = nsfp.initial_fit_state(options, padded_points)
    params = template.params
    named = type(template)(*[tf.nest.map_structure(lambda _, f=f: f, getattr(template, f)) for f in template._fields])
    fields = tf.nest.flatten(named)
    param_index = {id(p): i for i, p in enumerate(params)}
    layout, arrays = [], {}
    for j, (field, leaf) in enumerate(zip(fields, tf.nest.flatten(template))):
        value = leaf.numpy()
        if id(leaf) in param_index:
            init = {"param": param_index[id(leaf)]}
        elif value.ndim == 0:
            init = {"value": value.item()}
        elif not value.any():
            init = {"zeros": True}
        else:
            init = {"array": f"p{padded_points}_s{j:03d}"}
            arrays[init["array"]] = value
        layout.append({"field": field, "shape": list(value.shape), "dtype": value.dtype.name, "init": init})
    return layout, arrays


def timing_hyper(options: nsfp.NsfpOptions) -> dict:
    """The fit's hyperparameters as exported (`nsfp_program.HYPER_KEYS`): the options' except patience and the step
    cap, `TIMING_STEP_CAP`, so that a timed segment never stops early."""
    return {"learning_rate": options.learning_rate, "warmup_iterations": options.warmup_iterations,
            "weight_decay": options.weight_decay, "min_delta": options.min_delta, "patience": TIMING_STEP_CAP,
            "max_iterations": TIMING_STEP_CAP, "truncate_m": options.truncate_m}


def pair_entry(options: nsfp.NsfpOptions, points: int, seed: int, z_range_m=(-0.5, 3.0)) -> dict:
    """A manifest entry's pair and grid: the synthetic pair of `points` points in the options' crop box (35 m when
    there is none), its grid bounds (`grid_geometry`, the crop box in x and y as `nsfp_flow`), the centre the fit's
    coordinates are taken from, the point bucket."""
    half_extent_m = float(options.crop_xy_half_extent_m or 35.0)
    pair = nsfp_program.synthetic_pair(points, seed, half_extent_m, z_range_m)
    for key in ("points_xyz_t0", "points_xyz_tm1_in_t0"):
        if not nsfp.keep_mask(pair[key], options).all():
            raise ValueError(f"the synthetic {key} leaves the options' crop: z range {z_range_m} m")
    origin_m, dims = distance_grid.grid_geometry([pair["points_xyz_t0"], pair["points_xyz_tm1_in_t0"]],
                                                 options.grid_cell_m, options.grid_margin_m, options.max_grid_cells,
                                                 nsfp._crop_box(options))
    centre_m = (origin_m + (dims - 1) * np.float32(options.grid_cell_m) / 2).astype(np.float32)
    return {"points": int(points), "padded_points": bucket_size(points, options.point_bucket_base),
            "pair_seed": int(seed), "half_extent_m": half_extent_m, "z_range_m": [float(z) for z in z_range_m],
            "pair_digest": nsfp_program.pair_digest(pair), "centre_m": centre_m.tolist(),
            "origin_m": (origin_m - centre_m).tolist(), "dims": [int(d) for d in dims],
            "cell_m": float(options.grid_cell_m)}


def _hyper_tensors(hyper: dict) -> tuple:
    return tuple(tf.constant(a) for a in nsfp_program.hyper_arrays(hyper))


def tf_grids(entry: dict, clouds: list[np.ndarray], options: nsfp.NsfpOptions) -> tuple[DistanceGrid, DistanceGrid]:
    """TensorFlow's (t-1, t0) distance grids of the entry's padded clouds (`build_distance_grid`)."""
    t0, mask_t0, tm1, mask_tm1 = clouds
    origin_m, dims = np.asarray(entry["origin_m"], np.float32), np.asarray(entry["dims"], np.int32)

    def grid(xyz, mask):
        return distance_grid.build_distance_grid(xyz, mask, origin_m, dims, options.grid_cell_m, options.band_cells,
                                                 options.coarse_band_cells)
    return grid(tm1, mask_tm1), grid(t0, mask_t0)


def tf_segment(options: nsfp.NsfpOptions, entry: dict, hyper: dict):
    """`segment(state, clouds, grids)`: TensorFlow's own `nsfp._fit_segment`, `entry["segment_steps"]` steps."""
    hyper_t = _hyper_tensors(hyper)

    def segment(state, clouds, grids):
        return nsfp._fit_segment(state, clouds, grids, hyper_t, _num_forward(options), False, options.squared_chamfer,
                                 entry["segment_steps"], options.reverse_every)
    return segment


def tf_reference(options: nsfp.NsfpOptions, entry: dict, hyper: dict, calls: int) -> dict:
    """TensorFlow's grids (a strided sample) and fit state after `calls` segments on the entry's pair, for
    `nsfp_program.check_reference`."""
    clouds = nsfp_program.padded_clouds(nsfp_program.entry_pair(entry), entry)
    grids = tf_grids(entry, clouds, options)
    state = nsfp.initial_fit_state(options, entry["padded_points"])
    segment = tf_segment(options, entry, hyper)
    tf_clouds = tuple(tf.constant(c) for c in clouds)
    for _ in range(calls):
        state = segment(state, tf_clouds, grids)
    stride = max(1, int(grids[0].distance_m.shape[0]) // REFERENCE_GRID_SAMPLES)
    return {"padded_points": np.int64(entry["padded_points"]), "calls": np.int64(calls), "steps": state.step.numpy(),
            "grid_stride": np.int64(stride), "grid_tm1_sample": grids[0].distance_m.numpy()[::stride],
            "grid_t0_sample": grids[1].distance_m.numpy()[::stride], "best_loss": state.best_loss.numpy(),
            "best_motion": state.best_motion.numpy()}


def _write_entry(options, entry: dict, out_dir: str, precisions, platforms, log) -> None:
    """Writes the entry's grid and fit programs (adds their file names and sizes to `entry`)."""
    p, dims = entry["padded_points"], entry["dims"]
    grid_fn, grid_specs, cells = grid_program_fn(options, dims, p)
    entry["grid_cells"] = cells
    entry["grid_file"] = nsfp_program.grid_artifact_name(p, dims)
    entry["bytes"] = {entry["grid_file"]: xla_program.write_program(
        out_dir, entry["grid_file"], xla_program.traced_hlo(grid_fn, grid_specs), platforms, log)}
    fit_fn, fit_specs = fit_program_fn(options, p, entry["segment_steps"], cells)
    entry["fit_files"] = {}
    for precision in precisions:
        name = nsfp_program.fit_artifact_name(p, entry["segment_steps"], precision)
        hlo = xla_program.traced_hlo(fit_fn, fit_specs, tf32=precision == "tf32")
        entry["bytes"][name] = xla_program.write_program(out_dir, name, hlo, platforms, log)
        entry["fit_files"][precision] = name


def export_nsfp(options: nsfp.NsfpOptions, points: Sequence[int], out_dir: str, segment_steps: int = 50,
                precisions: Sequence[str] = ("float32",), platforms: Sequence[str] = xla_program.PLATFORMS,
                reference_calls: int = 0, reference_points: int | None = None, seed: int = 0, log=print) -> dict:
    """Writes `out_dir` (layout in `nsfp_program`): per cloud size in `points`, the grid program and one fit program
    of `segment_steps` steps per precision; the MLPs' initial parameters; with `reference_calls` > 0, TensorFlow's
    grids and fit after that many segments on the pair of `reference_points` points (default: the first entry's).
    Returns the manifest (also manifest.json)."""
    for precision in precisions:
        if precision not in nsfp_program.PRECISIONS:
            raise ValueError(f"precision {precision!r} unknown; one of {nsfp_program.PRECISIONS}")
    if not points or min(points) < 1 or segment_steps < 1:
        raise ValueError(f"points must be positive cloud sizes and segment_steps >= 1, got {list(points)}, "
                         f"{segment_steps}")
    if reference_calls > 0 and reference_points is not None and reference_points not in points:
        raise ValueError(f"reference_points {reference_points} is not one of the exported sizes {list(points)}")
    import jax
    os.makedirs(out_dir, exist_ok=True)
    params = nsfp.initial_fit_state(options, options.point_bucket_base).params
    np.savez(os.path.join(out_dir, nsfp_program.PARAMS_NAME), **{f"p{i:03d}": p.numpy() for i, p in enumerate(params)})
    hyper = timing_hyper(options)
    manifest = {"format": nsfp_program.FORMAT,
                "exported_with": {"tensorflow": tf.__version__, "jax": jax.__version__, "platforms": list(platforms)},
                "options": dataclasses.asdict(options), "hyper": hyper, "num_params": len(params),
                # The pseudo-label job fits every k-th point of a pair (the entries' points are fitted points).
                "job_fit_every": nsfp.MEASURED_FIT_OPTIONS.fit_every, "entries": []}
    initial_arrays = {}
    for i, n in enumerate(points):
        entry = {**pair_entry(options, n, seed + i), "segment_steps": int(segment_steps)}
        entry["state"], arrays = state_layout(options, entry["padded_points"])
        initial_arrays.update(arrays)
        _write_entry(options, entry, out_dir, precisions, platforms, log)
        manifest["entries"].append(entry)
    np.savez(os.path.join(out_dir, nsfp_program.STATE_ARRAYS_NAME), **initial_arrays)
    if reference_calls > 0:
        entry = next(e for e in manifest["entries"] if reference_points in (None, e["points"]))
        log(f"reference: TensorFlow's fit, {reference_calls} x {segment_steps} steps at {entry['points']} points")
        np.savez(os.path.join(out_dir, nsfp_program.REFERENCE_NAME), **tf_reference(options, entry, hyper,
                                                                                    reference_calls))
    with open(os.path.join(out_dir, nsfp_program.MANIFEST_NAME), "w") as f:
        json.dump(manifest, f, indent=1)
    return manifest
