"""NSFP's per-pair optimiser as portable XLA programs (written by `ff3d_tf.labels.nsfp_export`): the format, the
synthetic pairs they run on, loading, running and the check against TensorFlow, with JAX alone (the lab times them:
`lab.labels.nsfp_timing`).

Nothing here imports TensorFlow or a module that does: a machine with JAX/XLA only (a GPU box;
lab/tools/run_nsfp_xla.py, lab/tools/gpu_check.sh) builds the distance grids and runs the fit from an export directory.
Layout:

  manifest.json             format, the NSFP options, the fit's hyperparameters, one entry per point bucket
  initial_params.npz        the MLPs' initial parameters (p000, ...: forward MLP's [w0, b0, ...], then the backward
                            MLP's), as `nsfp.initial_fit_state` draws them from the options' seed
  initial_state.npz         start values of state leaves that are neither parameters, scalars nor zeros (if any)
  grid_<P>_<X>x<Y>x<Z>.jaxexport
                            the distance transform (`distance_grid.build_distance_grid`) of one padded cloud of P
                            points on an X x Y x Z node grid: (points_xyz [P,3] m, point_mask [P] bool, origin_m [3],
                            cell_m []) -> distance_m [C] (C = the grid's padded node count)
  fit_<P>_<S>steps_<precision>.jaxexport
                            S Adam steps of the NSFP objective (`nsfp._fit_segment`, no early stop within them unless
                            the hyperparameters say so): (state..., clouds (4), grid of t-1 (4), grid of t0 (4),
                            hyperparameters (7)) -> state...: `nsfp._FitState` flattened, its leaves (field, shape,
                            dtype, start value) listed in the entry's "state"
  reference.npz             optional: TensorFlow's grids (a strided sample) and fit result for the first entry

Clouds, frame and units (`ff3d_tf.labels.nsfp`): t0 cloud and ego-compensated t-1 cloud in the t0 vehicle frame, in
metres, shifted by the entry's `centre_m` (the fit's centred coordinates) and padded to P points (masks say which are
real); the fit's `best_motion` [P,3] is each t0 point's motion from t-1 to t0 in metres (flow = motion / dt_s).
The pairs are `synthetic_pair`: regenerated here from the entry's seed (numpy), checked against the digest the
export stored, so no cloud travels with the programs.
"""
from __future__ import annotations

import hashlib
import os

import numpy as np

from ff3d_tf import xla_program

FORMAT = "ff3d_tf.xla_nsfp/1"
MANIFEST_NAME = "manifest.json"
PARAMS_NAME = "initial_params.npz"
STATE_ARRAYS_NAME = "initial_state.npz"
REFERENCE_NAME = "reference.npz"
PRECISIONS = ("float32", "tf32")  # matmuls at HIGHEST precision / DEFAULT (XLA may use TF32 on Ampere and later)
HYPER_KEYS = ("learning_rate", "warmup_iterations", "weight_decay", "min_delta", "patience", "max_iterations",
              "truncate_m")  # `nsfp._fit_segment`'s `hyper`, in order
HYPER_INT_KEYS = ("warmup_iterations", "patience", "max_iterations")  # int32; the others float32
SYNTHETIC_OBJECT_MOTION_M = (0.6, 0.15, 0.0)  # motion of the synthetic moving box from t-1 to t0, m
SYNTHETIC_NOISE_M = 0.02  # per-coordinate noise of the t-1 cloud, m


def grid_artifact_name(padded_points: int, dims) -> str:
    return f"grid_{padded_points}_{'x'.join(str(int(d)) for d in dims)}.jaxexport"


def fit_artifact_name(padded_points: int, segment_steps: int, precision: str) -> str:
    return f"fit_{padded_points}_{segment_steps}steps_{precision}.jaxexport"


# --- the synthetic pairs ---------------------------------------------------------------------------------------------

def synthetic_pair(points: int, seed: int, half_extent_m: float, z_range_m) -> dict[str, np.ndarray]:
    """A pair with a known motion, t0 vehicle frame, metres: t0 points uniform in |x|, |y| <= half_extent_m and z in
    z_range_m; those in a 10 x 6 m box ahead moved by `SYNTHETIC_OBJECT_MOTION_M` since t-1, the rest static; the t-1
    cloud is each t0 point moved back, plus noise, clipped to the box. {"points_xyz_t0", "points_xyz_tm1_in_t0",
    "motion_m"}: [N,3] float32 each."""
    rng = np.random.default_rng(seed)
    h = float(half_extent_m)
    lo, hi = np.array([-h, -h, z_range_m[0]]), np.array([h, h, z_range_m[1]])
    xyz_t0 = rng.uniform(lo, hi, (points, 3)).astype(np.float32)
    moving = (np.abs(xyz_t0[:, 0] - 8.0) <= 5.0) & (np.abs(xyz_t0[:, 1]) <= 3.0)
    motion_m = np.where(moving[:, None], np.float32(SYNTHETIC_OBJECT_MOTION_M), np.float32(0)).astype(np.float32)
    noise = rng.normal(0.0, SYNTHETIC_NOISE_M, (points, 3)).astype(np.float32)
    xyz_tm1 = np.clip(xyz_t0 - motion_m + noise, lo.astype(np.float32), hi.astype(np.float32)).astype(np.float32)
    return {"points_xyz_t0": xyz_t0, "points_xyz_tm1_in_t0": xyz_tm1, "motion_m": motion_m}


def pair_digest(pair: dict[str, np.ndarray]) -> str:
    """sha256 of the pair's two clouds' bytes (the runner checks it regenerated the exporter's pair)."""
    digest = hashlib.sha256()
    for key in ("points_xyz_t0", "points_xyz_tm1_in_t0"):
        digest.update(np.ascontiguousarray(pair[key], np.float32).tobytes())
    return digest.hexdigest()


def entry_pair(entry: dict) -> dict[str, np.ndarray]:
    """The entry's synthetic pair, checked against its digest."""
    pair = synthetic_pair(entry["points"], entry["pair_seed"], entry["half_extent_m"], entry["z_range_m"])
    if pair_digest(pair) != entry["pair_digest"]:
        raise xla_program.ExportFormatError(
            f"the synthetic pair of {entry['points']} points (seed {entry['pair_seed']}) differs from the exporter's "
            f"(digest {entry['pair_digest'][:12]}): numpy's generator changed between the two machines")
    return pair


def padded_clouds(pair: dict, entry: dict) -> list[np.ndarray]:
    """The fit's four cloud arguments: t0 xyz [P,3], its mask [P], t-1 xyz [P,3], its mask [P]; centred (minus the
    entry's `centre_m`) and zero-padded."""
    out = []
    centre_m = np.asarray(entry["centre_m"], np.float32)
    for key in ("points_xyz_t0", "points_xyz_tm1_in_t0"):
        xyz = np.zeros((entry["padded_points"], 3), np.float32)
        xyz[: entry["points"]] = pair[key] - centre_m
        out += [xyz, np.arange(entry["padded_points"]) < entry["points"]]
    return out


# --- loading ---------------------------------------------------------------------------------------------------------

def read_manifest(export_dir: str) -> dict:
    return xla_program.read_manifest(export_dir, MANIFEST_NAME, FORMAT, ("options", "hyper", "num_params", "entries"),
                                     "tools/export_nsfp_xla.py")


def load_initial_params(export_dir: str, manifest: dict) -> list[np.ndarray]:
    path = os.path.join(export_dir, PARAMS_NAME)
    with np.load(path, allow_pickle=False) as stored:
        missing = [f"p{i:03d}" for i in range(manifest["num_params"]) if f"p{i:03d}" not in stored]
        if missing:
            raise xla_program.ExportFormatError(f"{path}: arrays {missing} missing")
        return [stored[f"p{i:03d}"] for i in range(manifest["num_params"])]


def hyper_arrays(hyper: dict) -> list[np.ndarray]:
    """The fit's hyperparameter arguments, `HYPER_KEYS` order (truncate_m None -> inf)."""
    out = []
    for key in HYPER_KEYS:
        value = np.inf if hyper[key] is None else hyper[key]
        out.append(np.asarray(value, np.int32 if key in HYPER_INT_KEYS else np.float32))
    return out


def initial_state(entry: dict, params: list[np.ndarray], stored: dict) -> list[np.ndarray]:
    """The fit's flat state before its first step (`nsfp.initial_fit_state`'s values), from the entry's layout:
    MLP parameters from `params`, other arrays from `stored` (`STATE_ARRAYS_NAME`)."""
    out = []
    for leaf in entry["state"]:
        init, dtype = leaf["init"], np.dtype(leaf["dtype"])
        if "param" in init:
            value = params[init["param"]]
        elif "value" in init:
            value = np.asarray(init["value"], dtype)
        elif "zeros" in init:
            value = np.zeros(leaf["shape"], dtype)
        else:
            value = stored[init["array"]]
        if list(value.shape) != leaf["shape"] or value.dtype != dtype:
            raise xla_program.ExportFormatError(f"state leaf {leaf['field']}: {value.dtype}{list(value.shape)}, the "
                                                f"manifest says {leaf['dtype']}{leaf['shape']}")
        out.append(value)
    return out


def state_index(entry: dict, field: str) -> int:
    """Position in the flat state of the (first) leaf of `_FitState` field `field` (step, best_loss, best_motion)."""
    return [leaf["field"] for leaf in entry["state"]].index(field)


class CompiledNsfp:
    """One entry's grid program and fit program (one precision) compiled for the default JAX device; the fit's state
    stays there between segments (donated buffers)."""

    def __init__(self, export_dir: str, manifest: dict, entry: dict, precision: str, grid_cache: dict | None = None):
        """`grid_cache`: {grid file: compiled program}, shared by the precisions of an entry (one grid program)."""
        import jax
        self.device = jax.devices()[0]
        self.entry, self.num_state = entry, len(entry["state"])
        self.index = {f: state_index(entry, f) for f in ("step", "best_loss", "best_motion")}
        self.segment_steps = entry["segment_steps"]
        fit = xla_program.load_program(os.path.join(export_dir, entry["fit_files"][precision]),
                                       self.num_state + 4 + 8 + len(HYPER_KEYS), self.num_state,
                                       f"{self.num_state} state arrays + 4 clouds + 8 grid + {len(HYPER_KEYS)} "
                                       f"hyperparameters -> {self.num_state}")
        grid_cache = {} if grid_cache is None else grid_cache
        grid_s = 0.0  # compile time of the grid program, when compiled here
        if entry["grid_file"] not in grid_cache:
            grid = xla_program.load_program(os.path.join(export_dir, entry["grid_file"]), 4, 1,
                                            "points, mask, origin, cell -> distances")
            grid_cache[entry["grid_file"]], grid_s = xla_program.compile_program(grid)
        self.grid_program = grid_cache[entry["grid_file"]]
        self.fit_program, fit_s = xla_program.compile_program(fit, range(self.num_state))
        self.compile_s = grid_s + fit_s
        self.hyper = self.put(hyper_arrays(manifest["hyper"]))
        self.grid_frame = self.put([np.asarray(entry["origin_m"], np.float32), np.asarray(entry["dims"], np.int32),
                                    np.asarray(entry["cell_m"], np.float32)])

    def put(self, arrays):
        import jax
        return [jax.device_put(a, self.device) for a in arrays]

    def grids(self, device_clouds) -> list:
        """Distance grids of the t-1 and t0 clouds (device arrays [C], m)."""
        origin_m, _, cell_m = self.grid_frame
        t0, mask_t0, tm1, mask_tm1 = device_clouds
        return [self.grid_program(tm1, mask_tm1, origin_m, cell_m)[0],
                self.grid_program(t0, mask_t0, origin_m, cell_m)[0]]

    def segment(self, state, device_clouds, grids) -> list:
        """`segment_steps` more Adam steps: the new state (the old one's buffers are reused)."""
        return list(self.fit_program(*state, *device_clouds, grids[0], *self.grid_frame, grids[1], *self.grid_frame,
                                     *self.hyper))

    def fit(self, device_clouds, start_state, calls: int):
        """(grids, state) after building both grids and `calls` segments from `start_state` (`initial_state`)."""
        grids = self.grids(device_clouds)
        state = self.put(start_state)
        for _ in range(calls):
            state = self.segment(state, device_clouds, grids)
        return grids, state


def load_state_arrays(export_dir: str) -> dict:
    path = os.path.join(export_dir, STATE_ARRAYS_NAME)
    return dict(np.load(path, allow_pickle=False)) if os.path.exists(path) else {}


def load_reference(export_dir: str):
    path = os.path.join(export_dir, REFERENCE_NAME)
    return dict(np.load(path)) if os.path.exists(path) else None


def check_reference(nsfp: CompiledNsfp, start_state, reference: dict | None) -> dict | None:
    """The device's grids and fit on the reference pair against TensorFlow's: largest grid difference (m, on the
    stored sample of nodes), relative difference of the best loss, largest motion difference (m) and the steps taken;
    None unless the reference is of this entry's bucket."""
    if reference is None or int(reference["padded_points"]) != nsfp.entry["padded_points"]:
        return None
    clouds = nsfp.put(padded_clouds(entry_pair(nsfp.entry), nsfp.entry))
    grids, state = nsfp.fit(clouds, start_state, int(reference["calls"]))
    stride = int(reference["grid_stride"])
    grid_diff = max(float(np.abs(np.asarray(g)[::stride] - reference[f"grid_{k}_sample"]).max())
                    for g, k in zip(grids, ("tm1", "t0")))
    loss, motion = float(state[nsfp.index["best_loss"]]), np.asarray(state[nsfp.index["best_motion"]])
    want = float(reference["best_loss"])
    return {"steps": int(state[nsfp.index["step"]]), "max_abs_grid_diff_m": grid_diff,
            "best_loss_rel_diff": abs(loss - want) / abs(want),
            "max_abs_motion_diff_m": float(np.abs(motion - reference["best_motion"]).max())}
