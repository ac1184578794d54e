"""DeFlow's GRU point decoder (`model.head=gru`, `ff3d_tf.model.gru_head`): the layer through the shared harness and
against a NumPy reference, 0 iterations as a plain MLP, the chunk loop's own gradient against automatic
differentiation, parameter counts by hand, and the model with this head in every compile mode and precision."""
import re

import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import load_config, replace_config
from ff3d_tf.model import FastFlow3D, build_model
from ff3d_tf.model.gru_head import GRUHead
from tests.model.layer_harness import run_layer_test

B, N, H, W = 2, 40, 4, 6  # tiny: 4 x 6 pillars
CHANNELS = (5, 5, 4)  # pillar embedding t0, t-1, decoder output: Hd = 14
SETTINGS = dict(input_units=6, mlp_units=4, iterations=2, chunk_size=7, zero_init_output=False)


def _head_inputs(seed=0, n=N):
    """Grids [B,H,W,C_i], offsets [B,n,3] (m, within a 0.33 m pillar), pillar ids (the dummy id B*H*W where
    invalid), valid [B,n]."""
    rng = np.random.default_rng(seed)
    grids = [tf.constant(rng.normal(0, 1, (B, H, W, c)).astype(np.float32)) for c in CHANNELS]
    valid = rng.uniform(0, 1, (B, n)) < 0.8
    offsets = np.where(valid[..., None], rng.uniform(-0.16, 0.16, (B, n, 3)), 0.0).astype(np.float32)
    ids = np.where(valid, rng.integers(0, H * W, (B, n)) + np.arange(B)[:, None] * H * W, B * H * W)
    return grids, tf.constant(offsets), tf.constant(ids.astype(np.int32)), tf.constant(valid)


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _gelu(x):
    from math import erf
    return 0.5 * x * (1.0 + np.vectorize(erf)(x / np.sqrt(2.0)))


def _reference(layer, grids, offsets, ids, valid):
    """NumPy (float64) DeFlow decoder: h_0 = the point's cells of the grids, x = offset encoding, `iterations` GRU
    steps on the full concatenations [h, x] and [r * h, x], MLP on [h, x]; 0 for invalid points."""
    def dense(sub, x):
        return x @ sub.kernel.numpy().astype(np.float64) + sub.bias.numpy()

    cells = np.concatenate([g.numpy().reshape(-1, g.shape[-1]) for g in grids], -1).astype(np.float64)
    v = valid.numpy().reshape(-1)
    h = cells[np.where(v, ids.numpy().reshape(-1), 0)]
    x = dense(layer.offset_encoder, offsets.numpy().reshape(-1, 3).astype(np.float64))
    for _ in range(layer.iterations):
        z = _sigmoid(dense(layer.update_gate, np.concatenate([h, x], -1)))
        r = _sigmoid(dense(layer.reset_gate, np.concatenate([h, x], -1)))
        q = np.tanh(dense(layer.candidate, np.concatenate([r * h, x], -1)))
        h = (1 - z) * h + z * q
    flow = dense(layer.mlp_output, _gelu(dense(layer.mlp_hidden, np.concatenate([h, x], -1))))
    return np.where(v[:, None], flow, 0.0).reshape(B, -1, 3)


def _perturb_invalid(args):
    """Invalid points get garbage offsets and the id of some real pillar: they must still be masked."""
    grids, offsets, ids, valid = args
    v = valid.numpy()
    offsets = np.where(v[..., None], offsets.numpy(), 1e3).astype(np.float32)
    ids = np.where(v, ids.numpy(), 3).astype(np.int32)
    return grids, tf.constant(offsets), tf.constant(ids), valid


def test_gru_head_through_the_harness_and_against_numpy():
    grids, offsets, ids, valid = _head_inputs()
    layer, out = run_layer_test(GRUHead, SETTINGS, (grids, offsets, ids, valid), expected_output_shapes=(B, N, 3),
                                masking=(_perturb_invalid, lambda out: out))
    assert layer.hidden_units == sum(CHANNELS)
    np.testing.assert_allclose(out, _reference(layer, grids, offsets, ids, valid), atol=1e-5)
    assert np.abs(out).max() > 0.1 and not out[~valid.numpy()].any()


def test_point_order_invariance():
    """Permuting the points (within each sample) permutes the flows."""
    grids, offsets, ids, valid = _head_inputs(1)
    layer = GRUHead(**SETTINGS)
    perm = np.random.default_rng(2).permutation(N)
    out = layer(grids, offsets, ids, valid).numpy()
    permuted = layer(grids, *(tf.gather(t, perm, axis=1) for t in (offsets, ids, valid))).numpy()
    np.testing.assert_allclose(permuted, out[:, perm], atol=1e-6)


def test_zero_iterations_is_a_plain_mlp():
    """K = 0: no gate weights; the flow is MLP([h_0, x]) with x the offset encoding: GELU(. @ W1 + b1) @ W2 + b2."""
    grids, offsets, ids, valid = _head_inputs(3)
    layer = GRUHead(**{**SETTINGS, "iterations": 0})
    out = layer(grids, offsets, ids, valid).numpy()
    assert layer.gates == [] and [v.path.split("/")[1] for v in layer.weights] == [
        "offset_encoder", "offset_encoder", "mlp_hidden", "mlp_hidden", "mlp_output", "mlp_output"]
    hd, i, m = sum(CHANNELS), 6, 4
    assert layer.count_params() == (3 * i + i) + ((hd + i) * m + m) + (m * 3 + 3)
    cells = np.concatenate([g.numpy().reshape(-1, g.shape[-1]) for g in grids], -1)
    v = valid.numpy().reshape(-1)
    h0 = cells[np.where(v, ids.numpy().reshape(-1), 0)]
    x = offsets.numpy().reshape(-1, 3) @ layer.offset_encoder.kernel.numpy() + layer.offset_encoder.bias.numpy()
    hidden = _gelu(np.concatenate([h0, x], -1) @ layer.mlp_hidden.kernel.numpy() + layer.mlp_hidden.bias.numpy())
    mlp = hidden @ layer.mlp_output.kernel.numpy() + layer.mlp_output.bias.numpy()
    np.testing.assert_allclose(out.reshape(-1, 3)[v], mlp[v], atol=1e-5)


@pytest.mark.parametrize("compiled", ["eager", "xla", "graph_unknown_point_count"])
def test_chunked_gradient_matches_autodiff(compiled):
    """The chunk loop's own gradient (7 points a chunk: several chunks and a padded last one) equals automatic
    differentiation of the same decoder written whole with the Dense layers' own calls: flows, and gradients with
    respect to every grid and every variable."""
    grids, offsets, ids, valid = _head_inputs(4)
    layer = GRUHead(**SETTINGS)
    layer(grids, offsets, ids, valid)
    upstream = tf.random.stateless_normal((B, N, 3), seed=[1, 2])

    def chunked(grids, offsets, ids, valid):
        with tf.GradientTape() as tape:
            tape.watch(grids)
            loss = tf.reduce_sum(layer(grids, offsets, ids, valid) * upstream)
        return loss, tape.gradient(loss, list(grids) + layer.trainable_variables)

    if compiled == "xla":
        chunked = tf.function(chunked, jit_compile=True)
    elif compiled == "graph_unknown_point_count":  # the loop's count known only at run time
        chunked = tf.function(chunked, input_signature=[[tf.TensorSpec([B, H, W, c]) for c in CHANNELS],
                                                        tf.TensorSpec([B, None, 3]), tf.TensorSpec([B, None], tf.int32),
                                                        tf.TensorSpec([B, None], tf.bool)])
    loss, grads = chunked(grids, offsets, ids, valid)

    with tf.GradientTape() as tape:
        tape.watch(grids)
        cells = tf.concat([tf.reshape(g, [-1, g.shape[-1]]) for g in grids], -1)
        h = tf.gather(cells, tf.minimum(ids, B * H * W - 1))
        x = layer.offset_encoder(offsets)
        for _ in range(layer.iterations):
            z = tf.sigmoid(layer.update_gate(tf.concat([h, x], -1)))
            r = tf.sigmoid(layer.reset_gate(tf.concat([h, x], -1)))
            h = (1 - z) * h + z * tf.tanh(layer.candidate(tf.concat([r * h, x], -1)))
        flow = layer.mlp_output(tf.nn.gelu(layer.mlp_hidden(tf.concat([h, x], -1)), approximate=False))
        flow = tf.where(valid[..., None], flow, 0.0)
        ref_loss = tf.reduce_sum(flow * upstream)
    ref = tape.gradient(ref_loss, list(grids) + layer.trainable_variables)
    np.testing.assert_allclose(loss.numpy(), ref_loss.numpy(), rtol=1e-5)
    assert len(grads) == len(ref) == 3 + 12
    for got, want, name in zip(grads, ref, ["grid"] * 3 + [v.path for v in layer.trainable_variables]):
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-4, atol=1e-5, err_msg=name)
        assert np.abs(want.numpy()).max() > 0, name


def test_chunk_size_does_not_change_flows():
    grids, offsets, ids, valid = _head_inputs(5, n=50)
    one = GRUHead(**{**SETTINGS, "chunk_size": 1 << 18})
    out = one(grids, offsets, ids, valid).numpy()
    for chunk in (1, 7, 50, 64):
        several = GRUHead(**{**SETTINGS, "chunk_size": chunk})
        several(grids, offsets, ids, valid)
        several.set_weights(one.get_weights())
        np.testing.assert_allclose(several(grids, offsets, ids, valid).numpy(), out, atol=1e-6, err_msg=chunk)


# -- the model with the GRU head ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def gru_config(tiny_config):
    return replace_config(tiny_config, {"model.head": "gru"})


def _model_inputs(seed=0, batch=2, n0=300, n1=260):
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


def test_parameter_counts_by_hand(gru_config):
    """Tiny config: C = 16 (point features, and row V's depth), head_hidden_dim 8. Hd = 3C = 48 (pillar embeddings
    at t0 and t-1, decoder output), I = C = 16, M = 8. The paper config: 5,233,571 - rows Y, Z + the GRU head."""
    model = build_model(gru_config)
    c, hd, m = 16, 48, 8
    head = {"GRU-x": 3 * c + c, "GRU-z": (hd + c) * hd + hd, "GRU-r": (hd + c) * hd + hd,
            "GRU-q": (hd + c) * hd + hd, "MLP-1": (hd + c) * m + m, "MLP-2": m * 3 + 3}
    rows = dict(model.table_rows())
    assert {k: rows[k] for k in head} == head and "Y" not in rows and rows["W"] == 0
    paper = dict(build_model(replace_config(gru_config, {"model.head": "paper"})).table_rows())
    assert model.count_params() == sum(paper.values()) - paper["Y"] - paper["Z"] + sum(head.values()) == sum(
        rows.values())
    full = load_config("configs/fastflow3d_waymo.yaml", ("model.head=gru",))
    head_params = 4 * 64 + 3 * (256 * 192 + 192) + (256 * 32 + 32) + (32 * 3 + 3)
    assert build_model(full).count_params() == 5_233_571 - 4384 - 99 + head_params == 5_385_699


def test_model_config_round_trip_and_chunking(gru_config):
    model = build_model(gru_config, point_chunk_size=100)  # several chunks per cloud
    assert model.head_gru.chunk_size == 100 and not hasattr(model, "head_y")
    inputs = _model_inputs(1)
    out = model(inputs)["flow_mps"].numpy()
    assert out.shape == (2, 300, 3) and np.abs(out).max() > 0 and not out[:, -20:].any()
    config = model.get_config()
    assert (config["head"], config["gru_iterations"]) == ("gru", 4)
    one_chunk = FastFlow3D.from_config({**config, "point_chunk_size": 1 << 20})
    one_chunk.build()
    one_chunk.set_weights(model.get_weights())
    # Equal up to float32 rounding: the pillar sums add their points in another order with other chunks.
    np.testing.assert_allclose(one_chunk(inputs)["flow_mps"].numpy(), out, atol=1e-4)
    restored = keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(model))
    assert restored.get_config() == config
    # An older config (no head keys) is the paper head.
    old = {k: v for k, v in config.items() if k not in ("head", "gru_iterations")}
    assert FastFlow3D.from_config(old).head == "paper"


def test_model_permuting_points_permutes_flows(gru_config):
    model = build_model(gru_config, point_chunk_size=64)
    inputs = _model_inputs(2, batch=1, n0=200, n1=180)
    perm = np.random.default_rng(3).permutation(200)
    permuted = dict(inputs, **{k: tf.gather(inputs[k], perm, axis=1)
                               for k in ("points_xyz_t0", "point_features_t0", "point_mask_t0")})
    a, b = model(inputs)["flow_mps"].numpy(), model(permuted)["flow_mps"].numpy()
    np.testing.assert_allclose(b[0], a[0][perm], rtol=1e-5, atol=1e-4)


def _models_in_modes(cfg):
    keras.utils.set_random_seed(2)
    models = {m: build_model(cfg, m, point_chunk_size=128) for m in ("none", "hybrid", "xla")}
    for m in models.values():
        m.set_weights(models["none"].get_weights())
    return models


def test_outputs_equal_across_compile_modes(gru_config):
    models = _models_in_modes(gru_config)
    inputs = _model_inputs(4)
    reference = models["none"](inputs)["flow_mps"].numpy()  # eager
    assert 0.1 < np.abs(reference).max() < 50
    for mode, model in models.items():
        out = tf.function(lambda x: model(x))(inputs)["flow_mps"].numpy()
        np.testing.assert_allclose(out, reference, atol=1e-4, err_msg=mode)


@pytest.mark.parametrize("mode", ["hybrid", pytest.param("xla", marks=pytest.mark.slow)])
def test_gradients_equal_across_compile_modes(gru_config, mode):
    models = _models_in_modes(gru_config)
    inputs = _model_inputs(4, batch=1)

    def grads(model, jit_compile):  # the trainer's choice of outer compilation
        def loss_and_grads(x):
            with tf.GradientTape() as tape:
                loss = tf.reduce_sum(tf.square(model(x, training=True, inline_stages=jit_compile)["flow_mps"]))
            return tape.gradient(loss, model.trainable_variables)
        return [g.numpy() for g in tf.function(loss_and_grads, jit_compile=jit_compile)(inputs)]

    want = grads(models["none"], False)
    for g, w, v in zip(grads(models[mode], mode == "xla"), want, models[mode].trainable_variables):
        np.testing.assert_allclose(g, w, atol=1e-4 * np.abs(w).max() + 1e-6, err_msg=v.path)
    names = [v.path for v, g in zip(models["none"].trainable_variables, want) if not np.abs(g).any()]
    assert not names, names  # every weight, row A included (through both the U-Net and the head), gets a gradient


def test_point_stages_hold_no_per_point_hidden_array(gru_config):
    """At several chunks per cloud the decode program, forward and backward, has no [N, Hd] array (hidden state,
    gates, their gradients) and no [N, 8] encoding (each chunk computes its points' offsets): only one chunk's,
    [128, Hd]; n is above the grid's 32 x 32 cells."""
    model = build_model(gru_config, point_chunk_size=128)
    n, hd = 1500, 3 * gru_config.model.point_feature_dim
    encoded = model.encode_points(_model_inputs(5, batch=1, n0=n, n1=n))
    grid = model.dense_stages(encoded["bev_features"])

    def decode_and_grads(grid, encoded):
        with tf.GradientTape() as tape:
            tape.watch([grid, encoded["bev_features"]])
            loss = tf.reduce_sum(tf.square(model.decode_points(grid, encoded)["flow_mps"]))
        return tape.gradient(loss, [grid, encoded["bev_features"]] + model.head_gru.trainable_variables)

    hlo = tf.function(decode_and_grads, jit_compile=True).experimental_get_compiler_ir(grid, encoded)(
        stage="optimized_hlo")
    per_point = re.compile(r"f32\[(?:1,)?(\d+),(\d+)\]")
    wide = {m.group(0) for m in per_point.finditer(hlo) if int(m.group(1)) >= n and
            (int(m.group(2)) == 8 or int(m.group(2)) >= hd)}
    assert not wide, wide
    assert "f32[128,%d]" % hd in hlo and "f32[128,8]" in hlo


def test_mixed_precision_head_stays_float32(gru_config):
    m32 = build_model(gru_config)
    m16 = build_model(replace_config(gru_config, {"model.mixed_precision": True}))
    assert m16.conv_dtype == "bfloat16" and m16.head_gru.compute_dtype == "float32"
    assert all(v.dtype == "float32" for v in m16.head_gru.weights)
    m16.set_weights(m32.get_weights())
    inputs = _model_inputs(6, batch=1)
    a, b = m32(inputs)["flow_mps"], m16(inputs)["flow_mps"]
    assert b.dtype == tf.float32
    assert np.linalg.norm(b - a) / np.linalg.norm(a) < 0.05

    @tf.function
    def grads(x):  # the model's own mode: hybrid on CPU
        with tf.GradientTape() as tape:
            loss = tf.reduce_sum(tf.square(m16(x, training=True)["flow_mps"]))
        return tape.gradient(loss, m16.trainable_variables)
    assert all(np.isfinite(g.numpy()).all() for g in grads(inputs))


def test_label_free_training_step_stateless_equals_on_variables(gru_config):
    """The training step's loss and gradients (`step.loss_and_grads_fn`) with pseudo-labels (label-free training,
    ZeroFlow's loss): stateless (the portable export's path, the weights passed in) equals the model's own variables
    (the trainer's path); every weight of the head gets a gradient."""
    from ff3d_tf.model.step import loss_and_grads_fn
    cfg = replace_config(gru_config, {"data.source": "pair_records", "data.labels": "pseudo"})
    model = build_model(cfg, "none", point_chunk_size=128)
    inputs = _model_inputs(7, batch=2, n0=200, n1=180)
    rng = np.random.default_rng(8)
    batch = {**inputs, "flow_mps_t0": tf.constant(rng.normal(0, 2, (2, 200, 3)).astype(np.float32)),
             "class_id_t0": tf.fill([2, 200], -1), "pseudo_valid_t0": tf.constant(rng.uniform(size=(2, 200)) < 0.7)}
    weights = [v.value for v in model.trainable_variables]
    statistics = [v.value for v in model.non_trainable_variables]
    results = [tf.function(loss_and_grads_fn(cfg, model, 2, on_variables=on_variables))(weights, statistics, batch)
               for on_variables in (False, True)]
    (loss, grads, _), (loss_v, grads_v, _) = results
    assert np.isfinite(loss.numpy()) and loss.numpy() > 0
    np.testing.assert_allclose(loss.numpy(), loss_v.numpy(), rtol=1e-6)
    for g, w, v in zip(grads, grads_v, model.trainable_variables):
        np.testing.assert_allclose(g.numpy(), w.numpy(), rtol=1e-5, atol=1e-6 * np.abs(w.numpy()).max(),
                                   err_msg=v.path)
        if v.path.startswith("gru/"):
            assert np.abs(g.numpy()).max() > 0, v.path
