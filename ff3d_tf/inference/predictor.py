"""One way to run a trained model, whatever it was saved as.

`load_predictor(cfg, path)` takes a model_dir, a checkpoint prefix or a SavedModel directory (the one place where that
choice is made) and returns a `Predictor`: `predict(batch, example) -> (flow_mps [N0,3], point_valid [N0])` for one
padded pair of `ff3d_tf.data.pairs.padded_singletons`, as NumPy arrays trimmed to the pair's real t0 points.
"""
from __future__ import annotations

import abc
import os

import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.model import build_model
from ff3d_tf.training.checkpoints import CheckpointError, list_checkpoints, newest_intact, verify_checkpoint
from ff3d_tf.model.fastflow3d import INPUT_KEYS


def model_inputs(batch: dict) -> dict:
    """The model's input keys of a batched example (labels and poses dropped)."""
    return {k: batch[k] for k in INPUT_KEYS}


def compiled_forward(model, jit_compile: bool | None = None):
    """`inputs -> model(inputs, training=False)` as one tf.function, retraced per bucket. The model's compile mode
    (`model.compile`) says what XLA compiles; `jit_compile=True` makes it one XLA program in any mode."""
    return tf.function(lambda inputs: model(inputs, training=False), jit_compile=jit_compile, reduce_retracing=True)


def resolve_checkpoint(path: str) -> str:
    """A checkpoint prefix from a checkpoint prefix or a model_dir (its newest checkpoint, found from the files)."""
    if tf.io.gfile.exists(path + ".index"):
        return path  # a prefix (checked first: ram:// calls any prefix of a file a directory)
    if tf.io.gfile.isdir(path):
        found = list_checkpoints(os.path.join(path, "checkpoints")) or list_checkpoints(path)
        if not found:
            raise FileNotFoundError(f"no checkpoint under {path} (expected {path}/checkpoints/ckpt-N.index)")
        return found[0]
    return path


def restore_model(cfg: ExperimentConfig, checkpoint_path: str):
    """The model of `cfg` with the weights of a checkpoint prefix or a model_dir's newest checkpoint.

    The checkpoint is verified first (`ff3d_tf.training.checkpoints.verify_checkpoint`): a damaged one, or one of
    another config, raises `CheckpointError` naming it, the reason and, for a model_dir, the newest intact one.
    Nothing is moved: choosing another checkpoint is the caller's decision.
    """
    model = build_model(cfg)
    root = tf.train.Checkpoint(model=model)
    prefix = resolve_checkpoint(checkpoint_path)
    try:
        verify_checkpoint(root, prefix)
    except CheckpointError as e:
        if prefix != checkpoint_path:  # a model_dir was given: say which of its checkpoints would work
            try:
                intact = newest_intact(root, os.path.dirname(prefix), log_fn=lambda _: None, move_damaged=False)
            except CheckpointError:
                intact = None
            if intact is not None:
                raise CheckpointError(prefix, f"{e.reason}; the newest intact checkpoint is {intact} (pass it as "
                                              f"the checkpoint, or rerun training to resume from it)") from e
        raise
    root.restore(prefix).expect_partial()
    return model


def is_saved_model(path: str) -> bool:
    return tf.io.gfile.exists(os.path.join(path, "saved_model.pb"))


def raw_tm1_points(example: dict) -> np.ndarray:
    """The t-1 cloud back in its own vehicle frame ([N1,5] with features): the SavedModel's serving input."""
    t = np.linalg.inv(np.linalg.inv(example["pose_t0"]) @ example["pose_tm1"])
    xyz = example["points_xyz_tm1_in_t0"].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
    return np.concatenate([xyz.astype(np.float32), example["point_features_tm1"]], -1)


class Predictor(abc.ABC):
    """Flow for one padded pair; subclasses differ only in what they run."""

    @abc.abstractmethod
    def predict(self, batch: dict, example: dict) -> tuple[np.ndarray, np.ndarray]:
        """(flow_mps [N0,3], point_valid [N0]) for the pair's real t0 points, as NumPy arrays."""


class ModelPredictor(Predictor):
    """A Keras model (restored from a checkpoint, or in memory) through its compiled forward."""

    def __init__(self, model, jit_compile: bool | None = None):
        self.model = model
        self.forward = compiled_forward(model, jit_compile)

    def predict(self, batch, example):
        n = int(example["num_points_t0"])
        out = self.forward(model_inputs(batch))
        return out["flow_mps"][0, :n].numpy(), out["point_valid"][0, :n].numpy()


class SavedModelPairPredictor(Predictor):
    """A SavedModel's `serving_default`, fed the raw clouds and poses of the pair (as a client would)."""

    def __init__(self, path: str):
        from ff3d_tf.inference.saved_model import SavedModelPredictor
        self.saved = SavedModelPredictor(path)

    def predict(self, batch, example):
        ex = {k: np.asarray(v) for k, v in example.items()}
        points_t0 = np.concatenate([ex["points_xyz_t0"], ex["point_features_t0"]], -1)
        out = self.saved(raw_tm1_points(ex), points_t0, ex["pose_tm1"], ex["pose_t0"])
        return out["flow_mps"].numpy(), out["point_valid"].numpy()


def load_predictor(cfg: ExperimentConfig, path: str) -> Predictor:
    """A SavedModel directory, a model_dir or a checkpoint prefix, as a `Predictor`."""
    if is_saved_model(path):
        return SavedModelPairPredictor(path)
    return ModelPredictor(restore_model(cfg, path), cfg.model.jit_compile)
