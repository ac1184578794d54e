"""The model as portable XLA programs: its forward (one `jax.export` artifact per point bucket and precision) and,
optionally, its training step (forward, loss, backward, Adam), weights saved once.

TensorFlow compiles the forward with XLA (`jit_compile=True`); this module takes that program before any
optimisation, with the weights as plain arguments, and serialises it so that a process without TensorFlow (JAX/XLA
only, e.g. on a GPU machine) compiles and runs it: `ff3d_tf.inference.xla_artifact` reads it back.

  1. `tf.function(jit_compile=True)` over `model.stateless_call` with flat arguments (weights, then the six inputs of
     one padded bucket): `experimental_get_compiler_ir(...)(stage="hlo_serialized")` is the pre-optimisation HLO,
     in which nothing depends on the device.
  2. jaxlib converts the HLO to StableHLO; a JAX primitive whose lowering inlines that module makes it a JAX
     function, and `jax.export` lowers it for the platforms asked (CPU and CUDA, on a machine without a GPU) and
     serialises it with StableHLO's versioned portable format (both steps: `ff3d_tf.xla_program`, which NSFP's export
     shares).

The training step is stateless: it takes the weights, the BatchNorm statistics, Adam's slots and iteration count and
a labelled batch, and returns their new values with the loss and the gradients' global norm (`train_step_fn`): a
JAX process keeps that state on its device and times steps with TensorFlow absent (`xla_artifact.CompiledTrainStep`).

TF32: TensorFlow writes its TF32 setting into the program (convolution/matmul precision HIGHEST when disabled,
DEFAULT when enabled), so each precision is traced with the setting it names (see `xla_artifact.PRECISIONS`).
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf import xla_program
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.inference import xla_artifact
from ff3d_tf.model import build_model
from ff3d_tf.model import step as step_lib
from ff3d_tf.schema import MODEL_INPUT_KEYS

OUTPUT_KEYS = ("flow_mps", "point_valid")
TRAIN_LABEL_KEYS = xla_artifact.TRAIN_LABEL_KEYS
PLATFORMS = xla_program.PLATFORMS


def input_specs(batch_size: int, padded_points: int) -> list[tf.TensorSpec]:
    """The six model inputs of one bucket, in `MODEL_INPUT_KEYS` order (`ff3d_tf.schema`)."""
    b, p = batch_size, padded_points
    shapes = {"points_xyz_t0": ([b, p, 3], tf.float32), "point_features_t0": ([b, p, 2], tf.float32),
              "point_mask_t0": ([b, p], tf.bool), "points_xyz_tm1_in_t0": ([b, p, 3], tf.float32),
              "point_features_tm1": ([b, p, 2], tf.float32), "point_mask_tm1": ([b, p], tf.bool)}
    return [tf.TensorSpec(*shapes[k], name=k) for k in MODEL_INPUT_KEYS]


def label_specs(batch_size: int, padded_points: int) -> list[tf.TensorSpec]:
    """The training step's labels, in `TRAIN_LABEL_KEYS` order: flow_mps_t0 [B,P,3], class_id_t0 [B,P] int32."""
    return [tf.TensorSpec([batch_size, padded_points, 3], tf.float32, name="flow_mps_t0"),
            tf.TensorSpec([batch_size, padded_points], tf.int32, name="class_id_t0")]


def model_weights(model) -> list:
    """The forward's weight arguments: trainable, then non-trainable variables (BatchNorm statistics)."""
    return list(model.trainable_variables) + list(model.non_trainable_variables)


def forward_hlo(model, batch_size: int, padded_points: int, tf32: bool = False) -> bytes:
    """Serialized pre-optimisation HLO of `model`'s inference forward for one bucket, weights as arguments.

    Arguments: `model_weights(model)` in order, then the inputs of `input_specs`; results: flow_mps [B,P,3],
    point_valid [B,P].
    """
    num_trainable = len(model.trainable_variables)
    num_weights = len(model_weights(model))

    def forward(*flat):
        outputs, _ = model.stateless_call(list(flat[:num_trainable]), list(flat[num_trainable:num_weights]),
                                          dict(zip(MODEL_INPUT_KEYS, flat[num_weights:])), training=False,
                                          inline_stages=True)
        return tuple(outputs[k] for k in OUTPUT_KEYS)

    specs = [tf.TensorSpec(v.shape, v.dtype) for v in model_weights(model)] + input_specs(batch_size, padded_points)
    return xla_program.traced_hlo(forward, specs, tf32)


def train_step_fn(cfg: ExperimentConfig, model, batch_size: int):
    """The training step (`ff3d_tf.model.step`, the Trainer's) as a function of flat tensors, for one device's batch
    that is the whole global batch, to be compiled whole with XLA:

      (weights..., bn_statistics..., adam_m..., adam_v..., iterations (int32: JAX without x64), six inputs, flow_mps_t0, class_id_t0)
        -> (new weights..., new bn_statistics..., new adam_m..., new adam_v..., new iterations, loss, grad_norm)

    weights = `model.trainable_variables` order, bn_statistics = `model.non_trainable_variables`; adam_m / adam_v one
    per weight (the order of `ff3d_tf.model.step.TrainState`). Loss, optional global-norm clipping, Keras' Adam and
    the non-finite skip (nothing changes, iterations included) are the Trainer's; grad_norm is taken before clipping.
    """
    num_weights, num_stats = len(model.trainable_variables), len(model.non_trainable_variables)
    layout = step_lib.TrainState([0] * num_weights, [0] * num_stats, [0] * num_weights, [0] * num_weights, 0)
    num_state = len(tf.nest.flatten(layout))
    train_step = step_lib.train_step_fn(cfg, step_lib.loss_and_grads_fn(cfg, model, batch_size, inline_stages=True))

    def flat_step(*flat):
        state = tf.nest.pack_sequence_as(layout, list(flat[:num_state]))
        batch = dict(zip(MODEL_INPUT_KEYS + TRAIN_LABEL_KEYS, flat[num_state:]))
        batch["point_mask_t0"] = tf.cast(batch["point_mask_t0"], tf.bool)
        result = train_step(state, batch)
        return (*tf.nest.flatten(result.state), result.loss, result.grad_norm)

    return flat_step


def train_step_specs(model, batch_size: int, padded_points: int) -> list[tf.TensorSpec]:
    """Argument specs of `train_step_fn`'s step for one bucket."""
    weights = model.trainable_variables
    state = [tf.TensorSpec(v.shape, v.dtype) for v in weights + model.non_trainable_variables + weights + weights]
    return (state + [tf.TensorSpec([], tf.int32, name="iterations")] + input_specs(batch_size, padded_points)
            + label_specs(batch_size, padded_points))


def train_step_hlo(cfg: ExperimentConfig, model, batch_size: int, padded_points: int, tf32: bool = False) -> bytes:
    """Serialized pre-optimisation HLO of `train_step_fn` for one bucket (arguments and results as documented there)."""
    return xla_program.traced_hlo(train_step_fn(cfg, model, batch_size),
                                  train_step_specs(model, batch_size, padded_points), tf32)


def _tracing_model(cfg: ExperimentConfig, precision: str, model):
    """The model whose forward is traced for `precision` (weights are arguments, so a fresh one is fine)."""
    mixed = precision == "bfloat16"
    if mixed == cfg.model.mixed_precision:
        return model
    other = build_model(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, mixed_precision=mixed)))
    same = [(v.shape, v.dtype) for v in model_weights(other)] == [(v.shape, v.dtype) for v in model_weights(model)]
    if not same:
        raise ValueError(f"model.mixed_precision={mixed} changes the weights' shapes or dtypes; cannot export "
                         f"precision {precision} with the same weights")
    return other


def _reference(cfg, model, manifest: dict, rng: np.random.Generator) -> dict:
    """Inputs and TensorFlow's results for the first float32 forward and training-step artifacts (CPU, XLA), for the
    runner to compare against what the exported programs compute on its device (`xla_artifact.REFERENCE_NAME`)."""
    arrays = {}
    forward = next((e for e in manifest["artifacts"] if e["precision"] == "float32"), None)
    if forward is not None:
        inputs = xla_artifact.random_inputs(manifest, forward, rng)
        out = tf.function(lambda x: model(x, training=False, inline_stages=True), jit_compile=True)(
            dict(zip(MODEL_INPUT_KEYS, inputs)))
        arrays.update({f"forward/{k}": a for k, a in zip(MODEL_INPUT_KEYS, inputs)})
        arrays.update({f"forward/out/{k}": out[k].numpy() for k in OUTPUT_KEYS})
        arrays["forward/padded_points"] = np.int64(forward["padded_points"])
    train = next((e for e in manifest["train_artifacts"] if e["precision"] == "float32"), None)
    if train is not None:
        b, p = train["batch_size"], train["padded_points"]
        batch = xla_artifact.random_inputs(manifest, train, rng) + xla_artifact.random_labels(train, rng)
        state = xla_artifact.initial_train_state([v.numpy() for v in model_weights(model)], manifest)
        with xla_program.tensor_float_32(False):
            results = tf.function(train_step_fn(cfg, model, b), jit_compile=True)(*state, *batch)
        arrays.update({f"train/{k}": a for k, a in zip(MODEL_INPUT_KEYS + TRAIN_LABEL_KEYS, batch)})
        arrays["train/out/loss"], arrays["train/out/grad_norm"] = results[-2].numpy(), results[-1].numpy()
        arrays["train/batch_size"], arrays["train/padded_points"] = np.int64(b), np.int64(p)
    return arrays


def export_forward(cfg: ExperimentConfig, model, points: Sequence[int], out_dir: str,
                   precisions: Sequence[str] = ("float32",), platforms: Sequence[str] = PLATFORMS,
                   batch_size: int = 1, weights_source: str = "random initialisation", log=print,
                   train_points: Sequence[int] = (), train_batch_sizes: Sequence[int] = (1,),
                   train_precisions: Sequence[str] | None = None, reference: bool = False) -> dict:
    """Writes `out_dir` (layout in `xla_artifact`): the weights of `model`, one forward artifact per (bucket,
    precision) and one training-step artifact per (train bucket, train batch size, train precision).

    `points` / `train_points` are cloud sizes; each is padded to its bucket (`data.point_bucket_base`), as the input
    pipeline does. `train_precisions` defaults to `precisions`. `reference`: also write TensorFlow's results for the
    first float32 artifacts of each kind (`xla_artifact.REFERENCE_NAME`). Returns the manifest (also written as
    manifest.json).
    """
    train_precisions = tuple(precisions if train_precisions is None else train_precisions)
    for p in (*precisions, *train_precisions):
        if p not in xla_artifact.PRECISIONS:
            raise ValueError(f"precision {p!r} unknown; one of {xla_artifact.PRECISIONS}")
    if not points or min(points) < 1 or (train_points and min(train_points) < 1):
        raise ValueError(f"points must be positive cloud sizes, got {list(points)} and {list(train_points)}")
    if train_points and (not train_batch_sizes or min(train_batch_sizes) < 1):
        raise ValueError(f"train batch sizes must be positive, got {list(train_batch_sizes)}")
    os.makedirs(out_dir, exist_ok=True)
    import jax
    weights = model_weights(model)
    np.savez(os.path.join(out_dir, xla_artifact.WEIGHTS_NAME),
             **{f"w{i:03d}": np.asarray(v.numpy()) for i, v in enumerate(weights)})
    g = cfg.grid
    manifest = {
        "format": xla_artifact.FORMAT,
        "exported_with": {"tensorflow": tf.__version__, "jax": jax.__version__, "platforms": list(platforms)},
        "weights_source": weights_source,
        "grid": {"num_pillars_x": g.num_pillars_x, "num_pillars_y": g.num_pillars_y, "x_range_m": list(g.x_range_m),
                 "y_range_m": list(g.y_range_m), "z_range_m": list(g.z_range_m)},
        "params": int(model.count_params()),
        "input_keys": list(MODEL_INPUT_KEYS), "output_keys": list(OUTPUT_KEYS), "train_label_keys": list(TRAIN_LABEL_KEYS),
        "weights": [{"path": v.path, "shape": list(v.shape), "dtype": str(v.dtype)} for v in weights],
        "num_trainable": len(model.trainable_variables),
        "artifacts": [], "train_artifacts": [],
    }
    written: dict[str, int] = {}
    for precision in precisions:
        tracer = _tracing_model(cfg, precision, model)
        for n in points:
            padded = bucket_size(n, cfg.data.point_bucket_base)
            name = xla_artifact.artifact_name(padded, precision)
            if name not in written:
                written[name] = xla_program.write_program(out_dir, name, forward_hlo(tracer, batch_size, padded,
                                                                           tf32=precision == "tf32"), platforms, log)
            manifest["artifacts"].append({"points": int(n), "padded_points": padded, "batch_size": batch_size,
                                          "precision": precision, "file": name, "bytes": written[name]})
    for precision in train_precisions if train_points else ():
        tracer = _tracing_model(cfg, precision, model)
        for n in train_points:
            padded = bucket_size(n, cfg.data.point_bucket_base)
            for b in train_batch_sizes:
                name = xla_artifact.train_artifact_name(b, padded, precision)
                if name not in written:
                    hlo = train_step_hlo(cfg, tracer, b, padded, tf32=precision == "tf32")
                    written[name] = xla_program.write_program(out_dir, name, hlo, platforms, log)
                manifest["train_artifacts"].append({"points": int(n), "padded_points": padded, "batch_size": int(b),
                                                    "precision": precision, "file": name, "bytes": written[name]})
    if reference:
        np.savez(os.path.join(out_dir, xla_artifact.REFERENCE_NAME),
                 **_reference(cfg, model, manifest, np.random.default_rng(0)))
    with open(os.path.join(out_dir, xla_artifact.MANIFEST_NAME), "w") as f:
        json.dump(manifest, f, indent=1)
    return manifest
