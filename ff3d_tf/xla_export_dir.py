"""The model's portable export directory, shared by its two kinds of programs: the forward
(`ff3d_tf.inference.xla_export` writes it, `xla_artifact` runs it) and the training step
(`ff3d_tf.training.xla_step_export` adds it, `xla_step_runner` runs it).

Layout of an export directory:

  manifest.json                      format, grid, input/output names, the weights' order, one entry per artifact
                                     ("artifacts": forward, "train_artifacts": training step)
  weights.npz                        the model's weights as plain float32 arrays (w000, w001, ...), saved once
  forward_<P>_<precision>.jaxexport  `jax.export` serialisation of the forward for P padded points, lowered for the
                                     manifest's platforms (CPU and CUDA)
  train_step_<B>x<P>_<precision>.jaxexport
                                     the training step (forward, loss, backward, Adam) for a batch of B pairs of P
                                     padded points (optional)
  reference.npz                      optional: inputs and TensorFlow's results of the first float32 artifacts, which
                                     the runner compares with what the programs compute on its device

An artifact's arguments are the weights in manifest order, then the six model inputs of `manifest["input_keys"]`
(batch B, padded points P: points_xyz_t0 [B,P,3], point_features_t0 [B,P,2], point_mask_t0 [B,P] bool, the same for
t-1 in the t0 frame); a forward returns flow_mps [B,P,3] (m/s) and point_valid [B,P] bool.

Precisions: `float32` (every convolution and matmul at HIGHEST precision: float32-exact on GPUs with TF32), `tf32`
(DEFAULT precision: XLA may use TF32 on Ampere and later), `bfloat16` (the model's mixed_bfloat16 compute, float32
weights and point coordinates).

Here: the format (reading, checking, the benchmark inputs), the run that times every artifact kind of a directory on
the default JAX device (`run_export`, each kind an `ArtifactTiming` of its pipeline) and, for the exporters, the
model's flat arguments and the directory's weights, manifest and reference. Like `ff3d_tf.xla_program`, importing
it imports neither TensorFlow nor JAX (each function imports what it needs): the TensorFlow-free runners use it.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Protocol, Sequence

import numpy as np

from ff3d_tf import bench, xla_program
from ff3d_tf.xla_program import ExportFormatError  # noqa: F401  (this module's callers catch it from here)

FORMAT = "ff3d_tf.xla_forward/1"
MANIFEST_NAME = "manifest.json"
WEIGHTS_NAME = "weights.npz"
REFERENCE_NAME = "reference.npz"
PRECISIONS = ("float32", "tf32", "bfloat16")
OUTPUT_KEYS = ("flow_mps", "point_valid")


# -- reading (JAX side) ---------------------------------------------------------------------------------------------
def read_manifest(export_dir: str) -> dict:
    return xla_program.read_manifest(export_dir, MANIFEST_NAME, FORMAT, ("weights", "input_keys", "output_keys",
                                                                         "artifacts", "grid"), "tools/export_xla.py")


def load_weights(export_dir: str, manifest: dict) -> list[np.ndarray]:
    """The weights in argument order, each checked against the manifest's shape and dtype."""
    path = os.path.join(export_dir, WEIGHTS_NAME)
    with np.load(path, allow_pickle=False) as stored:
        weights = []
        for i, spec in enumerate(manifest["weights"]):
            key = f"w{i:03d}"
            if key not in stored:
                raise ExportFormatError(f"{path}: array {key} ({spec['path']}) missing")
            w = stored[key]
            if list(w.shape) != spec["shape"] or str(w.dtype) != spec["dtype"]:
                raise ExportFormatError(f"{path}: array {key} ({spec['path']}) is {w.dtype}{list(w.shape)}, manifest "
                                        f"says {spec['dtype']}{spec['shape']}")
            weights.append(w)
    return weights


def load_artifact(export_dir: str, entry: dict, num_in: int, num_out: int, expected: str):
    """The `jax.export.Exported` of one manifest entry, its argument and result counts checked (`expected` says
    what they should be, for the message)."""
    return xla_program.load_program(os.path.join(export_dir, entry["file"]), num_in, num_out, expected)


def random_inputs(manifest: dict, entry: dict, rng: np.random.Generator) -> list[np.ndarray]:
    """`bench.random_clouds` of `entry["points"]` points over the manifest's grid, padded to the artifact's size, in
    argument order (`manifest["input_keys"]`)."""
    g = manifest["grid"]
    clouds = bench.random_clouds(rng, entry["points"], entry["padded_points"],
                                 (g["x_range_m"], g["y_range_m"], g["z_range_m"]), entry["batch_size"])
    return [clouds[k] for k in manifest["input_keys"]]


def load_reference(export_dir: str):
    """`REFERENCE_NAME`'s arrays (TensorFlow's inputs and results), or None when the export has none."""
    path = os.path.join(export_dir, REFERENCE_NAME)
    return dict(np.load(path)) if os.path.exists(path) else None


# -- the timing run -------------------------------------------------------------------------------------------------
@dataclasses.dataclass
class ExportRun:
    """What every artifact timing of one run reads: the directory, its manifest, weights and reference (None when it
    has none), and the run's random generator (the benchmark inputs, drawn in manifest order)."""
    export_dir: str
    manifest: dict
    weights: list
    reference: dict | None
    rng: np.random.Generator


class ArtifactTiming(Protocol):
    """One kind of artifact as `run_export` times it (the forward: `ff3d_tf.inference.xla_timing.ForwardTiming`; the
    training step: `ff3d_tf.training.xla_step_runner.TrainStepTiming`)."""
    kind: str  # a skipped row's "kind"
    manifest_key: str  # the manifest's list of this kind's entries
    result_key: str  # the result's list of this kind's rows

    def time(self, run: ExportRun, entry: dict) -> dict:
        """The row of one entry: its timing and "reference" (the check against TensorFlow's results, or None)."""

    def describe(self, row: dict) -> str:
        """The log line of a row."""

    def table(self, result: dict) -> list[str]:
        """The Markdown lines of this kind's rows (none when the run has none)."""

    def check_name(self, row: dict) -> str:
        """What a row's reference check is called in the table."""


def run_export(export_dir: str, timings: Sequence[ArtifactTiming], precisions=None, points=None,
               budget_s: float | None = None, seed: int = 0, log=print, on_row=None) -> dict:
    """Times the artifacts of an export directory, kind by kind in the order of `timings` (optionally only some
    precisions / point counts), each with its reference check.

    Artifacts still untimed when `budget_s` seconds have passed are listed as skipped (a GPU check must end in time).
    `on_row(result)` is called after each timed artifact with the result so far (e.g. to save partial results).
    """
    import jax
    start = time.perf_counter()
    manifest = read_manifest(export_dir)
    weights = load_weights(export_dir, manifest)
    device = jax.devices()[0]
    result = {"export_dir": export_dir, "jax": jax.__version__, "platform": device.platform,
              "device": getattr(device, "device_kind", str(device)), "num_weights": len(weights),
              "exported_with": manifest.get("exported_with", {}), **{t.result_key: [] for t in timings},
              "skipped": []}
    run = ExportRun(export_dir, manifest, weights, load_reference(export_dir), np.random.default_rng(seed))

    def wanted(entry, kind):
        if (precisions and entry["precision"] not in precisions) or (points and entry["points"] not in points):
            return False
        if budget_s is not None and time.perf_counter() - start > budget_s:
            result["skipped"].append({"kind": kind, "points": entry["points"], "precision": entry["precision"],
                                      "batch_size": entry["batch_size"],
                                      "reason": f"time budget of {budget_s:.0f} s spent"})
            return False
        return True

    for timing in timings:
        for entry in manifest.get(timing.manifest_key, []):
            if not wanted(entry, timing.kind):
                continue
            row = timing.time(run, entry)
            result[timing.result_key].append(row)
            if on_row is not None:
                on_row(result)
            log(timing.describe(row))
    result["total_s"] = time.perf_counter() - start
    return result


def describe_check(check: dict | None) -> str:
    """"; vs TensorFlow: " and a reference check's differences, or "" without one."""
    return "" if check is None else "; vs TensorFlow: " + ", ".join(f"{k} {v:.3g}" for k, v in check.items())


def results_table(result: dict, timings: Sequence[ArtifactTiming]) -> str:
    """Markdown tables of a `run_export` result, one per kind of `timings`, then the reference checks of every row."""
    lines, checks = [], []
    for timing in timings:
        lines += timing.table(result)
        checks += [(timing.check_name(row), row.get("reference")) for row in result.get(timing.result_key, [])]
    checks = [(name, check) for name, check in checks if check]
    if checks:
        lines += ["", "Against TensorFlow's results on the reference inputs (export machine, CPU, float32):", ""]
        lines += [f"- {name}:{describe_check(check).split(':', 1)[1]}" for name, check in checks]
    return "\n".join(lines)


# -- writing (TensorFlow side) --------------------------------------------------------------------------------------
def check_precisions(precisions: Sequence[str]) -> None:
    for p in precisions:
        if p not in PRECISIONS:
            raise ValueError(f"precision {p!r} unknown; one of {PRECISIONS}")


def model_weights(model) -> list:
    """A program's weight arguments: trainable, then non-trainable variables (BatchNorm statistics)."""
    return list(model.trainable_variables) + list(model.non_trainable_variables)


def input_specs(batch_size: int, padded_points: int) -> list:
    """The six model inputs of one bucket as `tf.TensorSpec`s, in `MODEL_INPUT_KEYS` order (`ff3d_tf.schema`)."""
    import tensorflow as tf
    from ff3d_tf.schema import MODEL_INPUT_KEYS
    b, p = batch_size, padded_points
    shapes = {"points_xyz_t0": ([b, p, 3], tf.float32), "point_features_t0": ([b, p, 2], tf.float32),
              "point_mask_t0": ([b, p], tf.bool), "points_xyz_tm1_in_t0": ([b, p, 3], tf.float32),
              "point_features_tm1": ([b, p, 2], tf.float32), "point_mask_tm1": ([b, p], tf.bool)}
    return [tf.TensorSpec(*shapes[k], name=k) for k in MODEL_INPUT_KEYS]


def tracing_model(cfg, precision: str, model):
    """The model whose program is traced for `precision` (weights are arguments, so a fresh one is fine)."""
    from ff3d_tf.model import build_model
    mixed = precision == "bfloat16"
    if mixed == cfg.model.mixed_precision:
        return model
    other = build_model(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, mixed_precision=mixed)))
    same = [(v.shape, v.dtype) for v in model_weights(other)] == [(v.shape, v.dtype) for v in model_weights(model)]
    if not same:
        raise ValueError(f"model.mixed_precision={mixed} changes the weights' shapes or dtypes; cannot export "
                         f"precision {precision} with the same weights")
    return other


def new_export(cfg, model, out_dir: str, platforms: Sequence[str], weights_source: str) -> dict:
    """Creates `out_dir` with `model`'s weights (`WEIGHTS_NAME`; an earlier export's reference there is removed);
    returns its manifest, no artifact in it yet (write it with `write_manifest` once they are added)."""
    import jax
    import tensorflow as tf
    from ff3d_tf.schema import MODEL_INPUT_KEYS
    os.makedirs(out_dir, exist_ok=True)
    if os.path.exists(os.path.join(out_dir, REFERENCE_NAME)):
        os.remove(os.path.join(out_dir, REFERENCE_NAME))
    weights = model_weights(model)
    np.savez_compressed(os.path.join(out_dir, WEIGHTS_NAME),
                        **{f"w{i:03d}": np.asarray(v.numpy()) for i, v in enumerate(weights)})
    g = cfg.grid
    return {
        "format": FORMAT,
        "exported_with": {"tensorflow": tf.__version__, "jax": jax.__version__, "platforms": list(platforms)},
        "weights_source": weights_source,
        "grid": {"num_pillars_x": g.num_pillars_x, "num_pillars_y": g.num_pillars_y, "x_range_m": list(g.x_range_m),
                 "y_range_m": list(g.y_range_m), "z_range_m": list(g.z_range_m)},
        "params": int(model.count_params()),
        "input_keys": list(MODEL_INPUT_KEYS), "output_keys": list(OUTPUT_KEYS),
        "weights": [{"path": v.path, "shape": list(v.shape), "dtype": str(v.dtype)} for v in weights],
        "num_trainable": len(model.trainable_variables),
        "artifacts": [], "train_artifacts": [],
    }


def check_same_weights(manifest: dict, model, export_dir: str) -> None:
    """Raises ValueError unless `model`'s weights are those the manifest lists (path, shape, dtype, in order)."""
    have = [{"path": v.path, "shape": list(v.shape), "dtype": str(v.dtype)} for v in model_weights(model)]
    if have != manifest["weights"]:
        raise ValueError(f"{export_dir}: the model's weights differ from the export's ({len(have)} against "
                         f"{len(manifest['weights'])} arrays, or their paths, shapes or dtypes): export the same model")


def write_manifest(out_dir: str, manifest: dict) -> None:
    with open(os.path.join(out_dir, MANIFEST_NAME), "w") as f:
        json.dump(manifest, f, indent=1)


def add_reference(out_dir: str, arrays: dict) -> None:
    """Adds `arrays` to the directory's `REFERENCE_NAME` (created when there is none)."""
    np.savez_compressed(os.path.join(out_dir, REFERENCE_NAME), **{**(load_reference(out_dir) or {}), **arrays})
