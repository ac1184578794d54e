"""Compile modes (`model.compile`): what each compiles, equal outputs and gradients, the whole-program XLA path."""
import logging

import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib
from ff3d_tf.model import fastflow3d

MODES = ("xla", "hybrid", "none")


def _inputs(seed=5, batch=2, n0=300, n1=260):
    rng = np.random.default_rng(seed)

    def cloud(n):
        xyz = rng.uniform(-38, 38, (batch, n, 3)).astype(np.float32)
        xyz[..., 2] = rng.uniform(-2.5, 2.5, (batch, n))
        return tf.constant(xyz), tf.constant(rng.uniform(0, 1, (batch, n, 2)).astype(np.float32))
    p0, f0 = cloud(n0)
    p1, f1 = cloud(n1)
    mask0 = np.ones((batch, n0), bool)
    mask0[:, -20:] = False  # padding
    return {"points_xyz_t0": p0, "point_features_t0": f0, "point_mask_t0": tf.constant(mask0),
            "points_xyz_tm1_in_t0": p1, "point_features_tm1": f1, "point_mask_tm1": tf.ones([batch, n1], tf.bool)}


def _models(cfg, chunk=128):
    """One model per mode with the same weights; several point chunks; outputs of a real flow's size (~1 m/s)."""
    keras.utils.set_random_seed(2)
    models = {m: build_model(cfg, m, point_chunk_size=chunk) for m in MODES}
    models["none"].head_z.kernel.assign(models["none"].head_z.kernel * 0.1)
    for m in MODES:
        models[m].set_weights(models["none"].get_weights())
    return models


def test_config_switch_and_auto(tiny_config, caplog):
    assert tiny_config.model.compile == "auto"
    with pytest.raises(ConfigError, match=r"model.compile='fast': one of auto, xla, hybrid, none"):
        replace_config(tiny_config, {"model.compile": "fast"})
    assert compile_lib.resolve_compile_mode("auto", "CPU", cpu_kind="onednn_avx512") == "hybrid"
    assert compile_lib.resolve_compile_mode("auto", "GPU") == "xla"
    assert compile_lib.resolve_compile_mode("none", "GPU") == "none"
    with caplog.at_level(logging.INFO, logger="ff3d_tf.model.fastflow3d"):
        model = build_model(tiny_config)
    auto = compile_lib.resolve_compile_mode("auto", "CPU", job="inference")  # these tests run on CPU: per CPU class
    assert model.compile_mode == auto
    assert f"model.compile=auto -> {auto} for inference (" in caplog.text
    # Precision is resolved (and logged) for the resolved mode: float32 unless asked (tests/model/test_precision.py).
    assert "model.mixed_precision=false -> float32 (as set; everything in float32)" in caplog.text
    assert model.conv_dtype == "float32"
    assert replace_config(tiny_config, {"model.compile": "xla"}).model.jit_compile
    with pytest.raises(ValueError, match="resolve 'auto'"):
        fastflow3d.FastFlow3D(**fastflow3d.model_kwargs(tiny_config), plan={"compile_mode": "auto"})


def _hybrid_programs():
    """How many XLA programs compile mode hybrid's forward launches: the point encoding (`compile_lib.hybrid_encode`;
    per cloud, the plan's default: each cloud's pillar cells and each cloud's encoding and scatter) and the head."""
    return 4 + 1


def _xla_functions(graph_def):
    """Names of the library functions XLA must compile, and the op types each function holds."""
    ops = {f.signature.name: {n.op for n in f.node_def} for f in graph_def.library.function}
    return {f.signature.name for f in graph_def.library.function if f.attr["_XlaMustCompile"].b}, ops


def test_each_mode_compiles_what_it_says(tiny_config):
    inputs = _inputs()
    for mode, model in _models(tiny_config).items():
        graph_def = tf.function(lambda x: model(x)).get_concrete_function(inputs).graph.as_graph_def()
        xla, ops = _xla_functions(graph_def)
        outer_ops = {n.op for n in graph_def.node}
        xla_ops = set().union(*(ops[f] for f in xla)) if xla else set()
        if mode == "none":
            assert not xla and "Conv2D" in outer_ops
        elif mode == "xla":
            assert len(xla) == 1 and {"Conv2D", "UnsortedSegmentSum", "GatherV2"} <= xla_ops
            assert "Conv2D" not in outer_ops
        else:  # hybrid: the point stages in XLA, the convolutions outside it
            assert len(xla) == _hybrid_programs() and {"UnsortedSegmentSum", "GatherV2"} <= xla_ops
            assert "Conv2D" not in xla_ops
            assert "Conv2D" in outer_ops


def test_outputs_equal_across_modes(tiny_config):
    models = _models(tiny_config)
    inputs = _inputs()
    reference = models["none"](inputs)["flow_mps"].numpy()  # eager
    assert 0.1 < np.abs(reference).max() < 20
    for mode, model in models.items():
        out = tf.function(lambda x: model(x))(inputs)
        np.testing.assert_allclose(out["flow_mps"].numpy(), reference, atol=1e-4, err_msg=mode)  # m/s
        np.testing.assert_array_equal(out["flow_mps"].numpy()[:, -20:], 0.0)  # padding gets no flow


@pytest.mark.parametrize("mode", ["hybrid", pytest.param("xla", marks=pytest.mark.slow)])
def test_gradients_equal_across_modes(tiny_config, mode):
    models = _models(tiny_config)
    inputs = _inputs()

    def grads(model, jit_compile):  # the trainer's choice of outer compilation
        def loss_and_grads(x):
            with tf.GradientTape() as tape:
                loss = tf.reduce_sum(tf.square(model(x, training=True, inline_stages=jit_compile)["flow_mps"]))
            return tape.gradient(loss, model.trainable_variables)
        return [g.numpy() for g in tf.function(loss_and_grads, jit_compile=jit_compile)(inputs)]

    want = grads(models["none"], False)
    got = grads(models[mode], mode == "xla")
    for g, w, v in zip(got, want, models["none"].trainable_variables):
        np.testing.assert_allclose(g, w, atol=1e-4 * np.abs(w).max() + 1e-6, err_msg=v.path)


@pytest.mark.parametrize("mode", ["hybrid", pytest.param("xla", marks=pytest.mark.slow),
                                  pytest.param("none", marks=pytest.mark.slow)])
def test_whole_program_xla_stateless_call(tiny_config, mode):
    """The portable export's path: `stateless_call` under one jit_compile=True function, with the weights as inputs."""
    inputs = _inputs(batch=1)
    model = _models(tiny_config)[mode]
    trainable = [v.value for v in model.trainable_variables]
    non_trainable = [v.value for v in model.non_trainable_variables]

    def forward(inline):
        return tf.function(lambda t, n, x: model.stateless_call(t, n, x, inline_stages=inline)[0]["flow_mps"],
                           jit_compile=True)
    fn = forward(True)
    graph_def = fn.get_concrete_function(trainable, non_trainable, inputs).graph.as_graph_def()
    assert not _xla_functions(graph_def)[0]  # traced inline: one program, no nested stage functions
    expected = model(inputs)["flow_mps"].numpy()
    np.testing.assert_allclose(fn(trainable, non_trainable, inputs).numpy(), expected, atol=1e-4)
    # A caller that forgets the flag: the stages' own XLA functions nest in its program, with the same values.
    forgot = forward(False)
    nested = _xla_functions(forgot.get_concrete_function(trainable, non_trainable, inputs).graph.as_graph_def())[0]
    assert len(nested) == {"xla": 1, "hybrid": _hybrid_programs(), "none": 0}[mode]
    np.testing.assert_allclose(forgot(trainable, non_trainable, inputs).numpy(), expected, atol=1e-4)
    # The weights passed in are the ones used: row Z's kernel doubled (its bias is zero) doubles the flow.
    doubled = [2.0 * t if t.shape.rank == 2 and t.shape[-1] == 3 else t for t in trainable]
    np.testing.assert_allclose(fn(doubled, non_trainable, inputs).numpy(), 2.0 * expected, rtol=1e-3, atol=1e-3)


def test_mixed_precision_trains_in_every_mode(tiny_config):
    """A bfloat16 training step compiles and gives finite gradients in every mode. Regression: in mode xla (the GPU
    default) XLA rejected the step ("floating point types of different precisions") because TensorFlow lowers the
    bilinear upsampling's gradient to float32 for bfloat16 inputs; U2 now runs in float32."""
    cfg = replace_config(tiny_config, {"model.mixed_precision": True})
    models = _models(cfg)
    inputs = _inputs()
    norms = {}
    for mode, model in models.items():
        @tf.function(jit_compile=mode == "xla")
        def grads(x, model=model):
            with tf.GradientTape() as tape:
                loss = tf.reduce_mean(tf.square(model(x, training=True, inline_stages=mode == "xla")["flow_mps"]))
            return tape.gradient(loss, model.trainable_variables)
        g = grads(inputs)
        assert all(t is not None and t.dtype == tf.float32 for t in g), mode
        norms[mode] = float(tf.linalg.global_norm(g))
        assert np.isfinite(norms[mode]) and norms[mode] > 0, (mode, norms[mode])
    # Same weights: bfloat16 rounding differs between backends, the gradients agree to its precision.
    assert max(norms.values()) / min(norms.values()) < 1.1, norms
