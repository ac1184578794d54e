"""Running a model forward, for whoever runs it: the trainer's periodic evaluation, evaluation and serving.

`ModelPredictor` is the in-memory Keras model behind the contract of "flow for one padded pair" that evaluation takes
(`ff3d_tf.predictor.Predictor`). Other predictors (a SavedModel, an ONNX file, a portable XLA export) live with what
they run, in `ff3d_tf.inference`.
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf.predictor import Predictor
from ff3d_tf.schema import MAX_NUM_FRAMES, model_input_keys


def model_inputs(batch: dict) -> dict:
    """The model's input keys of a batched example, of every sweep it holds (labels and poses dropped)."""
    return {k: batch[k] for k in model_input_keys(MAX_NUM_FRAMES) if k in batch}


def compiled_forward(model, jit_compile: bool | None = None):
    """`inputs -> model(inputs, training=False)` as one tf.function, retraced per bucket. The model's compile mode
    (`model.compile`) says what XLA compiles; `jit_compile=True` makes it one XLA program in any mode (the model
    traces its stages inline)."""
    inline = jit_compile is True
    return tf.function(lambda inputs: model(inputs, training=False, inline_stages=inline), jit_compile=jit_compile,
                       reduce_retracing=True)


class ModelPredictor(Predictor):
    """A Keras model (restored from a checkpoint, or in memory) through its compiled forward."""

    def __init__(self, model, jit_compile: bool | None = None):
        self.model = model
        self.forward = compiled_forward(model, jit_compile)

    def predict(self, batch, example):
        n = int(example["num_points_t0"])
        out = self.forward(model_inputs(batch))
        return out["flow_mps"][0, :n].numpy(), out["point_valid"][0, :n].numpy()
