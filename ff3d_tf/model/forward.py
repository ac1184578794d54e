"""Running a model forward, for whoever runs it: the trainer's periodic evaluation, evaluation and serving.

`Predictor` is the contract of "flow for one padded pair" (`ff3d_tf.data.pairs.padded_singletons`) that evaluation
takes; `ModelPredictor` is the in-memory Keras model behind it. Other predictors (a SavedModel) live with what they
run, in `ff3d_tf.inference`.
"""
from __future__ import annotations

import abc

import numpy as np
import tensorflow as tf

from ff3d_tf.schema import MODEL_INPUT_KEYS


def model_inputs(batch: dict) -> dict:
    """The model's input keys of a batched example (labels and poses dropped)."""
    return {k: batch[k] for k in MODEL_INPUT_KEYS}


def compiled_forward(model, jit_compile: bool | None = None):
    """`inputs -> model(inputs, training=False)` as one tf.function, retraced per bucket. The model's compile mode
    (`model.compile`) says what XLA compiles; `jit_compile=True` makes it one XLA program in any mode (the model
    traces its stages inline)."""
    inline = jit_compile is True
    return tf.function(lambda inputs: model(inputs, training=False, inline_stages=inline), jit_compile=jit_compile,
                       reduce_retracing=True)


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
