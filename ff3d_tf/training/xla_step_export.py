"""The training step (forward, loss, backward, Adam) as portable XLA programs, added to an export directory of the
forward (`ff3d_tf.inference.xla_export.export_forward`; the layout: `ff3d_tf.xla_export_dir`).

The step is stateless: it takes the weights, the BatchNorm statistics, Adam's slots and iteration count and a
labelled batch, and returns their new values with the loss and the gradients' global norm (`train_step_fn`, the
Trainer's own step of `ff3d_tf.model.step`): a JAX process keeps that state on its device and times steps with
TensorFlow absent (`xla_step_runner.CompiledTrainStep`). Traced and written as the forward is (`ff3d_tf.xla_program`);
each precision with the TF32 setting it names.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf import xla_export_dir, xla_program
from ff3d_tf.config import LOSS_SPECS, ExperimentConfig
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.model import step as step_lib
from ff3d_tf.schema import model_input_keys
from ff3d_tf.training.xla_step_runner import TRAIN_LABEL_KEYS, initial_train_state, random_labels, train_artifact_name
from ff3d_tf.xla_export_dir import input_specs, model_weights, tracing_model

PLATFORMS = xla_program.PLATFORMS


def step_label_keys(cfg: ExperimentConfig, num_frames: int) -> tuple[str, ...]:
    """The labels a training step of `cfg` takes, in argument order: `TRAIN_LABEL_KEYS`, then the fields its loss
    needs (`config.LOSS_SPECS`: a self-supervised loss's per-cloud fields; its batch holds them as records do)."""
    return TRAIN_LABEL_KEYS + LOSS_SPECS[cfg.train.loss].fields("needs", num_frames)


def label_specs(batch_size: int, padded_points: int, keys: Sequence[str] = TRAIN_LABEL_KEYS) -> list[tf.TensorSpec]:
    """The training step's labels, in `keys` order: flow_mps_t0 [B,P,3] float32, every other [B,P] int32 (class ids,
    self-supervision fields)."""
    return [tf.TensorSpec([batch_size, padded_points, 3] if k == "flow_mps_t0" else [batch_size, padded_points],
                          tf.float32 if k == "flow_mps_t0" else tf.int32, name=k) for k in keys]


def train_step_fn(cfg: ExperimentConfig, model, batch_size: int):
    """The training step (`ff3d_tf.model.step`, the Trainer's) as a function of flat tensors, for one device's batch
    that is the whole global batch, to be compiled whole with XLA:

      (weights..., bn_statistics..., adam_m..., adam_v..., iterations (int32: JAX without x64), the model's inputs,
       the labels of `step_label_keys`)
        -> (new weights..., new bn_statistics..., new adam_m..., new adam_v..., new iterations, loss, grad_norm)

    weights = `model.trainable_variables` order, bn_statistics = `model.non_trainable_variables`; adam_m / adam_v one
    per weight (the order of `ff3d_tf.model.step.TrainState`). Loss, optional global-norm clipping, Keras' Adam and
    the non-finite skip (nothing changes, iterations included) are the Trainer's; grad_norm is taken before clipping.
    """
    num_weights, num_stats = len(model.trainable_variables), len(model.non_trainable_variables)
    layout = step_lib.TrainState([0] * num_weights, [0] * num_stats, [0] * num_weights, [0] * num_weights, 0)
    num_state = len(tf.nest.flatten(layout))
    train_step = step_lib.train_step_fn(cfg, step_lib.loss_and_grads_fn(cfg, model, batch_size, inline_stages=True))
    keys = model_input_keys(model.num_frames) + step_label_keys(cfg, model.num_frames)

    def flat_step(*flat):
        state = tf.nest.pack_sequence_as(layout, list(flat[:num_state]))
        batch = dict(zip(keys, flat[num_state:]))
        batch["point_mask_t0"] = tf.cast(batch["point_mask_t0"], tf.bool)
        result = train_step(state, batch)
        return (*tf.nest.flatten(result.state), result.loss, result.grad_norm)

    return flat_step


def train_step_specs(cfg: ExperimentConfig, model, batch_size: int, padded_points: int) -> list[tf.TensorSpec]:
    """Argument specs of `train_step_fn`'s step for one bucket."""
    weights = model.trainable_variables
    state = [tf.TensorSpec(v.shape, v.dtype) for v in weights + model.non_trainable_variables + weights + weights]
    return (state + [tf.TensorSpec([], tf.int32, name="iterations")]
            + input_specs(batch_size, padded_points, model.num_frames)
            + label_specs(batch_size, padded_points, step_label_keys(cfg, model.num_frames)))


def train_step_hlo(cfg: ExperimentConfig, model, batch_size: int, padded_points: int, tf32: bool = False) -> bytes:
    """Serialized pre-optimisation HLO of `train_step_fn` for one bucket (arguments and results as documented there)."""
    return xla_program.traced_hlo(train_step_fn(cfg, model, batch_size),
                                  train_step_specs(cfg, model, batch_size, padded_points), tf32)


def _reference(cfg: ExperimentConfig, model, manifest: dict, rng: np.random.Generator) -> dict:
    """A labelled batch and TensorFlow's loss and gradient norm (CPU, XLA) of the first step of the first float32
    training-step artifact, for the runner to compare with its device's (`xla_export_dir.REFERENCE_NAME`)."""
    train = next((e for e in manifest["train_artifacts"] if e["precision"] == "float32"), None)
    if train is None:
        return {}
    b, p = train["batch_size"], train["padded_points"]
    batch = xla_export_dir.random_inputs(manifest, train, rng) + random_labels(train, manifest, rng)
    state = initial_train_state([v.numpy() for v in model_weights(model)], manifest)
    with xla_program.tensor_float_32(False):
        results = tf.function(train_step_fn(cfg, model, b), jit_compile=True)(*state, *batch)
    return {**{f"train/{k}": a for k, a in zip((*manifest["input_keys"], *manifest["train_label_keys"]), batch)},
            "train/out/loss": results[-2].numpy(), "train/out/grad_norm": results[-1].numpy(),
            "train/batch_size": np.int64(b), "train/padded_points": np.int64(p)}


def export_train_steps(cfg: ExperimentConfig, model, out_dir: str, points: Sequence[int],
                       batch_sizes: Sequence[int] = (1,), precisions: Sequence[str] = ("float32",),
                       log=print, reference: bool = False) -> dict:
    """Adds one training-step artifact per (bucket, batch size, precision) to `out_dir`, an export of `model`'s
    forward (`export_forward`, the same weights), for the platforms of its manifest.

    `points` are cloud sizes, each padded to its bucket (`data.point_bucket_base`). `reference`: also add
    TensorFlow's results for the first float32 artifact (`xla_export_dir.REFERENCE_NAME`). Returns the manifest
    (also written as manifest.json).
    """
    xla_export_dir.check_precisions(precisions)
    if not points or min(points) < 1:
        raise ValueError(f"train points must be positive cloud sizes, got {list(points)}")
    if not batch_sizes or min(batch_sizes) < 1:
        raise ValueError(f"train batch sizes must be positive, got {list(batch_sizes)}")
    manifest = xla_export_dir.read_manifest(out_dir)
    xla_export_dir.check_same_weights(manifest, model, out_dir)
    platforms = manifest["exported_with"]["platforms"]
    manifest["train_label_keys"] = list(step_label_keys(cfg, model.num_frames))
    written = {e["file"]: e["bytes"] for e in manifest.setdefault("train_artifacts", [])}
    for precision in precisions:
        tracer = tracing_model(cfg, precision, model)
        for n in points:
            padded = bucket_size(n, cfg.data.point_bucket_base)
            for b in batch_sizes:
                name = train_artifact_name(b, padded, precision)
                if name not in written:
                    hlo = train_step_hlo(cfg, tracer, b, padded, tf32=precision == "tf32")
                    written[name] = xla_program.write_program(out_dir, name, hlo, platforms, log)
                manifest["train_artifacts"].append({"points": int(n), "padded_points": padded, "batch_size": int(b),
                                                    "precision": precision, "file": name, "bytes": written[name]})
    if reference:
        xla_export_dir.add_reference(out_dir, _reference(cfg, model, manifest, np.random.default_rng(0)))
    xla_export_dir.write_manifest(out_dir, manifest)
    return manifest
