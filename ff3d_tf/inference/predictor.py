"""One way to run a trained model, whatever it was saved as.

`load_predictor(cfg, path)` is the one place where what a path holds chooses the runtime (`predictor_kind`); every
kind follows the contract of `ff3d_tf.predictor.Predictor`: `predict(batch, example) -> (flow_mps [N0,3],
point_valid [N0])` for one padded pair of `ff3d_tf.data.pairs.padded_singletons`, as NumPy arrays trimmed to the
pair's real t0 points.

  onnx         an .onnx file (tools/export_onnx.py): `onnx_export.OnnxFlowPredictor`, onnxruntime on the CPU
  saved_model  a directory with saved_model.pb (tools/export.py): `saved_model.SavedModelPredictor`
  xla          a directory with a portable export's manifest.json (tools/export_xla.py, batch 1):
               `xla_artifact.XlaPredictor`, JAX
  checkpoint   anything else, a model_dir or a checkpoint prefix: `ff3d_tf.model.forward.ModelPredictor` of the model
               restored with the config given
"""
from __future__ import annotations

import os

import tensorflow as tf

from ff3d_tf import xla_export_dir
from ff3d_tf.checkpoints import restore_model
from ff3d_tf.config import ConfigError, ExperimentConfig
from ff3d_tf.model.forward import ModelPredictor
from ff3d_tf.predictor import Predictor

KINDS = ("onnx", "saved_model", "xla", "checkpoint")


def is_saved_model(path: str) -> bool:
    return tf.io.gfile.exists(os.path.join(path, "saved_model.pb"))


def predictor_kind(path: str) -> str:
    """Which of `KINDS` `path` holds (see the module docstring)."""
    if path.endswith(".onnx"):
        return "onnx"
    if is_saved_model(path):
        return "saved_model"
    if os.path.isfile(os.path.join(path, xla_export_dir.MANIFEST_NAME)):
        return "xla"
    return "checkpoint"


def load_predictor(cfg: ExperimentConfig, path: str) -> Predictor:
    """The model at `path` (an ONNX file, a SavedModel or portable XLA export directory, a model_dir or a checkpoint
    prefix) as a `Predictor`; `cfg` builds the model of a checkpoint (the exports carry their own). An export that
    reads another number of sweeps than `cfg.data.num_frames` (the examples the caller will make) is a ConfigError."""
    kind = predictor_kind(path)
    if kind == "onnx":
        from ff3d_tf.inference.onnx_export import OnnxFlowPredictor
        predictor = OnnxFlowPredictor(path)
    elif kind == "saved_model":
        from ff3d_tf.inference.saved_model import SavedModelPredictor
        predictor = SavedModelPredictor(path)
    elif kind == "xla":
        from ff3d_tf.inference.xla_artifact import XlaPredictor
        predictor = XlaPredictor(path)
    else:
        return ModelPredictor(restore_model(cfg, path), cfg.model.jit_compile)
    if predictor.num_frames != cfg.data.num_frames:
        raise ConfigError(f"{path}: the model reads {predictor.num_frames} sweeps per example; the config has "
                          f"data.num_frames={cfg.data.num_frames}: set data.num_frames={predictor.num_frames} (and "
                          "the model.temporal it was trained with)")
    return predictor
