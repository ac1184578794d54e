"""One test battery for every layer of `ff3d_tf.model.layers` (in the manner of keras-hub's `run_layer_test`).

`run_layer_test` checks, for one layer class and one set of inputs:
  config      `get_config` returns exactly the constructor arguments; `from_config` and Keras serialisation give an
              equal config, and a clone with the same weights gives the same outputs;
  compiled    eager == tf.function graph == XLA (`jit_compile=True`), outputs and, when the layer has trainable
              weights, their gradients (of a fixed random projection of the outputs);
  precision   built under "mixed_bfloat16": float32 variables, bfloat16 float outputs, close to float32 outputs;
  masking     inputs changed only where they are masked (`masking=(perturb, select)`) leave the selected outputs
              unchanged.
"""
from __future__ import annotations

import inspect

import keras
import numpy as np
import tensorflow as tf


def _numpy(structure):
    return tf.nest.map_structure(lambda t: None if t is None else np.asarray(t), structure)


def _assert_close(actual, expected, atol, what):
    flat_a, flat_e = tf.nest.flatten(actual), tf.nest.flatten(expected)
    assert len(flat_a) == len(flat_e), what
    for i, (a, e) in enumerate(zip(flat_a, flat_e)):
        if e is None:
            assert a is None, f"{what}: output {i}"
            continue
        a, e = np.asarray(a), np.asarray(e)
        assert a.shape == e.shape and a.dtype == e.dtype, f"{what}: output {i} {a.shape}{a.dtype} vs {e.shape}{e.dtype}"
        if a.dtype.kind in "biu":
            np.testing.assert_array_equal(a, e, err_msg=f"{what}: output {i}")
        else:
            np.testing.assert_allclose(a.astype(np.float64), e.astype(np.float64), atol=atol,
                                       err_msg=f"{what}: output {i}")


def _float_outputs(outputs):
    return [t for t in tf.nest.flatten(outputs) if t is not None and t.dtype.is_floating]


def _projected_loss(outputs):
    """A fixed random projection of every float output: a scalar whose gradient reaches each output element."""
    total = 0.0
    for i, t in enumerate(_float_outputs(outputs)):
        # Deterministic weights in [-1, 1] (stateless random ops differ between XLA and the TF kernels).
        weights = tf.reshape(tf.sin(0.7 * tf.range(tf.size(t), dtype=tf.float32) + i), tf.shape(t))
        total += tf.reduce_sum(tf.cast(t, tf.float32) * weights)
    return total


def _build(layer_cls, init_kwargs, call_args, call_kwargs, policy="float32"):
    """The layer built from the inputs, its sublayers too constructed under `policy` (as `build_model` does)."""
    previous = keras.config.dtype_policy()
    keras.config.set_dtype_policy(policy)
    try:
        layer = layer_cls(**init_kwargs)
    finally:
        keras.config.set_dtype_policy(previous)
    layer(*call_args, **call_kwargs)
    return layer


def run_layer_test(layer_cls, init_kwargs: dict, call_args: tuple, call_kwargs: dict | None = None, *,
                   expected_output_shapes=None, atol: float = 1e-5, grad_atol: float = 1e-4,
                   mixed_precision: bool = True, mixed_rtol: float = 0.05, float32_under_mixed: tuple = (),
                   masking=None):
    """Runs the whole battery; returns the layer (built, eager float32) and its eager outputs for further checks.

    float32_under_mixed: positions (in the flattened floating outputs) that stay float32 under mixed precision by
    design; every other floating output must be bfloat16 there."""
    call_kwargs = dict(call_kwargs or {})
    layer = _build(layer_cls, init_kwargs, call_args, call_kwargs)
    eager = _numpy(layer(*call_args, **call_kwargs))
    if expected_output_shapes is not None:
        shapes = tf.nest.map_structure(lambda t: None if t is None else tuple(t.shape), eager)
        assert shapes == expected_output_shapes, (shapes, expected_output_shapes)

    # Config: exactly the constructor arguments, and a faithful round trip.
    config = layer.get_config()
    own = {k: v for k, v in config.items() if k in inspect.signature(layer_cls.__init__).parameters}
    assert set(own) == set(inspect.signature(layer_cls.__init__).parameters) - {"self", "kwargs"}, own
    for key, value in init_kwargs.items():
        assert own[key] == (tuple(value) if isinstance(value, list) else value), (key, own[key], value)
    clone = layer_cls.from_config(config)
    assert clone.get_config() == config
    restored = keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(layer))
    assert type(restored) is layer_cls and restored.get_config() == config
    clone(*call_args, **call_kwargs)
    clone.set_weights(layer.get_weights())
    _assert_close(_numpy(clone(*call_args, **call_kwargs)), eager, atol, "clone with the same weights")

    # Eager == graph == XLA, outputs and gradients.
    def forward(*args):
        return layer(*args, **call_kwargs)

    for name, jit in (("graph", False), ("xla", True)):
        compiled = _numpy(tf.function(forward, jit_compile=jit)(*call_args))
        _assert_close(compiled, eager, atol, f"{name} vs eager")
    if layer.trainable_variables:
        def grads(*args):
            with tf.GradientTape() as tape:
                loss = _projected_loss(layer(*args, **call_kwargs))
            return tape.gradient(loss, layer.trainable_variables)

        eager_grads = _numpy(grads(*call_args))
        assert all(g is not None and np.isfinite(g).all() for g in eager_grads), "eager gradients"
        assert any(np.abs(g).max() > 0 for g in eager_grads), "all gradients are zero"
        for name, jit in (("graph", False), ("xla", True)):
            _assert_close(_numpy(tf.function(grads, jit_compile=jit)(*call_args)), eager_grads, grad_atol,
                          f"{name} gradients vs eager")

    # Mixed precision: float32 variables, bfloat16 compute, outputs close to float32.
    if mixed_precision:
        mixed = _build(layer_cls, init_kwargs, call_args, call_kwargs, "mixed_bfloat16")
        assert all(v.dtype == "float32" for v in mixed.weights)
        mixed.set_weights(layer.get_weights())
        out16 = mixed(*call_args, **call_kwargs)
        dtypes = [t.dtype for t in _float_outputs(out16)]
        assert dtypes == [tf.float32 if i in float32_under_mixed else tf.bfloat16 for i in range(len(dtypes))], dtypes
        for a, e in zip(_float_outputs(out16), _float_outputs(layer(*call_args, **call_kwargs))):
            a, e = np.asarray(tf.cast(a, tf.float32)), np.asarray(e)
            assert np.linalg.norm(a - e) <= mixed_rtol * max(np.linalg.norm(e), 1e-6), np.linalg.norm(a - e)

    # Masking: what is masked does not reach the selected outputs.
    if masking is not None:
        perturb, select = masking
        perturbed = _numpy(layer(*perturb(call_args), **call_kwargs))
        _assert_close(select(perturbed), select(eager), atol, "outputs with masked inputs changed")
    return layer, eager
