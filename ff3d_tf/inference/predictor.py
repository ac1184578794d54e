"""One way to run a trained model, whatever it was saved as.

`load_predictor(cfg, path)` takes a model_dir, a checkpoint prefix or a SavedModel directory (the one place where that
choice is made) and returns a `Predictor`: `predict(batch, example) -> (flow_mps [N0,3], point_valid [N0])` for one
padded pair of `ff3d_tf.data.pairs.padded_singletons`, as NumPy arrays trimmed to the pair's real t0 points.
"""
from __future__ import annotations

import os

import numpy as np
import tensorflow as tf

from ff3d_tf import geometry
from ff3d_tf.checkpoints import restore_model
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.model.forward import ModelPredictor, Predictor


def is_saved_model(path: str) -> bool:
    return tf.io.gfile.exists(os.path.join(path, "saved_model.pb"))


def raw_tm1_points(example: dict) -> np.ndarray:
    """The t-1 cloud back in its own vehicle frame ([N1,5] with features): the SavedModel's serving input."""
    tm1_from_t0 = np.linalg.inv(geometry.t0_from_tm1_np(example["pose_t0"], example["pose_tm1"]))
    xyz = geometry.transform_points_np(example["points_xyz_tm1_in_t0"], tm1_from_t0)
    return np.concatenate([xyz.astype(np.float32), example["point_features_tm1"]], -1)


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
