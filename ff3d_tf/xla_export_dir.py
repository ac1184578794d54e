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

Here: the format (reading, checking), the made-up inputs of the reference (`random_clouds`, `random_labels`: two
clouds of N points uniform over the grid, so every point falls in a pillar, features uniform in [0, 1], padded with
zeros to P points and masked; flow labels uniform in [-10, 10] m/s and classes uniform in -1..4 on the real points,
zero flow and class -1 (no label) on the padding) and, for the exporters, the model's flat arguments and the
directory's weights, manifest and reference. Like `ff3d_tf.xla_program`, importing it imports neither TensorFlow nor
JAX (each function imports what it needs): the TensorFlow-free runners use it. The runs that time a directory's
artifacts are the lab's (`lab.xla_export_timing`).
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Sequence

import numpy as np

from ff3d_tf import xla_program
from ff3d_tf.schema import (CLASS_NAMES, CLASS_NO_LABEL, DYNAMIC_CLUSTER_GROUND, DYNAMIC_CLUSTER_KEY_FORMAT, MAX_NUM_FRAMES,
                            model_input_keys, sweep_clouds)
from ff3d_tf.xla_program import ExportFormatError  # noqa: F401  (this module's callers catch it from here)

DYNAMIC_CLUSTER_KEYS = frozenset(DYNAMIC_CLUSTER_KEY_FORMAT.format(cloud=c) for c in sweep_clouds(MAX_NUM_FRAMES))

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
    """`random_clouds` of `entry["points"]` points over the manifest's grid, padded to the artifact's size, in
    argument order (`manifest["input_keys"]`)."""
    g = manifest["grid"]
    clouds = random_clouds(rng, entry["points"], entry["padded_points"],
                           (g["x_range_m"], g["y_range_m"], g["z_range_m"]), entry["batch_size"],
                           len(manifest["input_keys"]) // 3)
    return [clouds[k] for k in manifest["input_keys"]]


def load_reference(export_dir: str):
    """`REFERENCE_NAME`'s arrays (TensorFlow's inputs and results), or None when the export has none."""
    path = os.path.join(export_dir, REFERENCE_NAME)
    return dict(np.load(path)) if os.path.exists(path) else None


# -- made-up input: the reference's clouds and labels (also the lab's benchmark cloud) ---------------------------------
def random_clouds(rng: np.random.Generator, points: int, padded_points: int, bounds: Sequence[Sequence[float]],
                  batch_size: int = 1, num_frames: int = 2) -> dict[str, np.ndarray]:
    """The model's inputs for `batch_size` examples of `num_frames` made-up clouds (t0, then t-1 and any older ones
    in the t0 frame) of `points` points, padded to `padded_points`: `schema.model_input_keys` in order, xyz float32
    [B,P,3], features float32 [B,P,2], mask bool [B,P]. `bounds`: the grid's ((x_min, x_max), (y_min, y_max),
    (z_min, z_max)), metres."""
    if not 0 < points <= padded_points:
        raise ValueError(f"points={points}: need 0 < points <= padded_points={padded_points}")
    b, n, p = batch_size, points, padded_points
    arrays = []
    for _ in range(num_frames):
        xyz = np.zeros((b, p, 3), np.float32)
        xyz[:, :n] = np.stack([rng.uniform(lo, hi, (b, n)) for lo, hi in bounds], -1)
        features = np.zeros((b, p, 2), np.float32)
        features[:, :n] = rng.uniform(0.0, 1.0, (b, n, 2))
        mask = np.zeros((b, p), bool)
        mask[:, :n] = True
        arrays += [xyz, features, mask]
    return dict(zip(model_input_keys(num_frames), arrays))


def random_labels(rng: np.random.Generator, points: int, padded_points: int, batch_size: int = 1,
                  keys: Sequence[str] = ("flow_mps_t0", "class_id_t0")) -> dict:
    """Labels of `random_clouds`' clouds, one array per key of `keys`: flow_mps_t0 float32 [B,P,3] uniform in
    [-10, 10] m/s and class_id_t0 int32 [B,P] uniform in -1..4 on the real points, zero flow and class -1 (no label) on
    the padding; a self-supervision field of any cloud (`schema.DYNAMIC_CLUSTER_KEY_FORMAT`) int32 [B,P] uniform from
    ground (-2) to cluster 4 on the real points, ground on the padding."""
    b, n, p = batch_size, points, padded_points
    out = {}
    for key in keys:
        if key == "flow_mps_t0":
            out[key] = np.zeros((b, p, 3), np.float32)
            out[key][:, :n] = rng.uniform(-10.0, 10.0, (b, n, 3))
        elif key == "class_id_t0":
            out[key] = np.full((b, p), CLASS_NO_LABEL, np.int32)
            out[key][:, :n] = rng.integers(CLASS_NO_LABEL, max(CLASS_NAMES) + 1, (b, n))
        elif key in DYNAMIC_CLUSTER_KEYS:
            out[key] = np.full((b, p), DYNAMIC_CLUSTER_GROUND, np.int32)
            out[key][:, :n] = rng.integers(DYNAMIC_CLUSTER_GROUND, 5, (b, n))
        else:
            raise ValueError(f"no made-up values for the label {key!r}")
    return out


# -- writing (TensorFlow side) --------------------------------------------------------------------------------------
def check_precisions(precisions: Sequence[str]) -> None:
    for p in precisions:
        if p not in PRECISIONS:
            raise ValueError(f"precision {p!r} unknown; one of {PRECISIONS}")


def model_weights(model) -> list:
    """A program's weight arguments: trainable, then non-trainable variables (BatchNorm statistics)."""
    return list(model.trainable_variables) + list(model.non_trainable_variables)


def input_specs(batch_size: int, padded_points: int, num_frames: int = 2) -> list:
    """The model inputs of one bucket (three per sweep: the pair's six) as `tf.TensorSpec`s, in
    `schema.model_input_keys` order."""
    import tensorflow as tf
    b, p = batch_size, padded_points
    specs = []
    for key in model_input_keys(num_frames):
        shape, dtype = (([b, p], tf.bool) if key.startswith("point_mask_") else
                        ([b, p, 2], tf.float32) if key.startswith("point_features_") else ([b, p, 3], tf.float32))
        specs.append(tf.TensorSpec(shape, dtype, name=key))
    return specs


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
        "input_keys": list(model_input_keys(model.num_frames)), "output_keys": list(OUTPUT_KEYS),
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
