"""`model.remat_encoder`: the encoder stages' activations recomputed in the backward pass. Same gradients and the same
moving statistics as without it, in graph mode and as one XLA program; XLA keeps the recomputation (more encoder
convolutions in the optimized program, none merged away). What it saves and costs: benchmarks/remat_cpu.json."""
import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.model import build_model

from tests.model.test_compile import _inputs


def _model(cfg, remat, mode):
    keras.utils.set_random_seed(2)
    model = build_model(replace_config(cfg, {"model.remat_encoder": remat}), mode, point_chunk_size=128)
    model.head_z.kernel.assign(model.head_z.kernel * 0.1)
    return model


def _moving_statistics(model):
    return [v.numpy() for v in model.non_trainable_variables if "moving" in v.path]


def _loss_and_grads(model, jit_compile):
    def fn(x):
        with tf.GradientTape() as tape:
            loss = tf.reduce_sum(tf.square(model(x, training=True, inline_stages=jit_compile)["flow_mps"]))
        return loss, tape.gradient(loss, model.trainable_variables)
    return tf.function(fn, jit_compile=jit_compile)


def test_config_key(tiny_config):
    assert tiny_config.model.remat_encoder is False  # the paper's training holds its activations
    with pytest.raises(ConfigError, match=r"model.remat_encoder: expected true/false, got 'yes'"):
        replace_config(tiny_config, {"model.remat_encoder": "yes"})
    model = _model(tiny_config, True, "none")
    assert model.plan.remat_encoder and model.get_config()["plan"]["remat_encoder"] is True


@pytest.mark.parametrize("mode,jit", [("none", False), ("xla", True)])
def test_same_gradients_and_statistics(tiny_config, mode, jit):
    inputs = _inputs()
    results = {}
    for remat in (False, True):
        model = _model(tiny_config, remat, mode)
        before = _moving_statistics(model)
        loss, grads = _loss_and_grads(model, jit)(inputs)
        results[remat] = (float(loss), [g.numpy() for g in grads], _moving_statistics(model))
        # the statistics moved, once: a second assignment by the recomputation would move them again
        assert any(not np.allclose(a, b) for a, b in zip(before, results[remat][2]))
    assert results[True][0] == pytest.approx(results[False][0], rel=1e-6)
    for got, want in zip(results[True][1], results[False][1]):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max() + 1e-7)
    for got, want in zip(results[True][2], results[False][2]):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


def test_inference_is_unchanged(tiny_config):
    inputs = _inputs()
    want = _model(tiny_config, False, "none")(inputs)["flow_mps"].numpy()
    np.testing.assert_array_equal(_model(tiny_config, True, "none")(inputs)["flow_mps"].numpy(), want)


def test_xla_keeps_the_recomputation(tiny_config):
    """XLA would merge a recomputation that does not wait on the backward with the forward's run (same ops, same
    inputs): with remat_encoder the optimized program has one more forward convolution per encoder block."""
    inputs = _inputs()
    convolutions = {}
    for remat in (False, True):
        fn = _loss_and_grads(_model(tiny_config, remat, "xla"), True)
        hlo = fn.experimental_get_compiler_ir(inputs)(stage="optimized_hlo")
        convolutions[remat] = sum(" convolution(" in line for line in hlo.splitlines())
    assert convolutions[True] - convolutions[False] == sum(tiny_config.model.encoder_depths)
