"""FastFlow3D: paper parameter counts, shapes, serialisation, pillarization by hand, equivariance, masking, XLA."""
import re

import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import load_config
from ff3d_tf.model import FastFlow3D, build_model
from ff3d_tf.model.layers import Pillarize

PAPER_ROWS = {"A": 544, "B": 0, "C": 37120, "D": 37120, "E": 37120, "F": 37120, "G": 74240, "H": 147968,
              "I": 147968, "J": 147968, "K": 147968, "L": 147968, "M": 295936, "N": 590848, "O": 590848,
              "P": 590848, "Q": 590848, "R": 590848, "S": 540672, "T": 311296, "U": 126976, "V": 36864, "W": 0,
              "X": 0, "Y": 4384, "Z": 99}


def test_paper_parameter_counts():
    model = build_model(load_config("configs/fastflow3d_waymo.yaml"))
    assert model.count_params() == 5_233_571
    assert dict(model.table_rows()) == PAPER_ROWS


def _inputs(rng, batch, n0, n1, extent=40.0):
    def cloud(n):
        xyz = rng.uniform(-extent, extent, (batch, n, 3)).astype(np.float32)
        xyz[..., 2] = rng.uniform(-2.5, 2.5, (batch, n))
        return xyz, rng.uniform(0, 1, (batch, n, 2)).astype(np.float32)
    p0, f0 = cloud(n0)
    p1, f1 = cloud(n1)
    return {"points_xyz_t0": tf.constant(p0), "point_features_t0": tf.constant(f0),
            "point_mask_t0": tf.ones([batch, n0], tf.bool), "points_xyz_tm1_in_t0": tf.constant(p1),
            "point_features_tm1": tf.constant(f1), "point_mask_tm1": tf.ones([batch, n1], tf.bool)}


def test_shapes_and_config_round_trip(tiny_config):
    model = build_model(tiny_config, point_chunk_size=100)  # several chunks per cloud
    inputs = _inputs(np.random.default_rng(0), 2, 300, 250)
    out = model(inputs)
    assert out["flow_mps"].shape == (2, 300, 3) and out["point_valid"].shape == (2, 300)
    clone = FastFlow3D.from_config(model.get_config())
    clone(inputs)
    clone.set_weights(model.get_weights())
    np.testing.assert_allclose(clone(inputs)["flow_mps"], out["flow_mps"], atol=1e-6)
    restored = keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(model))
    assert restored.get_config() == model.get_config()
    assert clone.point_encoder.chunk_size == restored.point_encoder.chunk_size == 100


def test_pillarization_by_hand():
    # Grid 4 x 4 over x, y in [-2, 2) (1 m pillars), z in [-1, 1].
    layer = Pillarize(4, 4, (-2.0, 2.0), (-2.0, 2.0), (-1.0, 1.0))
    pts = tf.constant([[[0.25, -1.5, 0.5],    # col floor(2.25)=2, row floor(0.5)=0 -> id 0*16 + 0*4 + 2 = 2
                        [-2.0, 1.99, -1.0],   # col 0, row 3 -> 12; z on the lower bound is valid
                        [2.0, 0.0, 0.0],      # x == max: outside
                        [0.0, 0.0, 1.5]]], tf.float32)  # z outside
    feats = tf.constant([[[0.3, 0.1]] * 4], tf.float32)
    enc, ids, valid = layer(pts, feats, tf.ones([1, 4], tf.bool))
    assert valid.numpy().tolist() == [[True, True, False, False]]
    assert ids.numpy().tolist() == [[2, 12, 16, 16]]  # invalid -> dummy id B*H*W = 16
    # Point 0: centre (0.5, -1.5, 0), offset (-0.25, 0, 0.5), features (0.3, 0.1).
    np.testing.assert_allclose(enc.numpy()[0, 0], [0.5, -1.5, 0.0, -0.25, 0.0, 0.5, 0.3, 0.1], atol=1e-6)
    np.testing.assert_array_equal(enc.numpy()[0, 2], np.zeros(8))


def test_permuting_points_permutes_outputs(tiny_config):
    model = build_model(tiny_config)
    inputs = _inputs(np.random.default_rng(1), 1, 200, 180)
    perm = np.random.default_rng(2).permutation(200)
    perm1 = np.random.default_rng(3).permutation(180)
    permuted = dict(inputs)
    for k in ("points_xyz_t0", "point_features_t0", "point_mask_t0"):
        permuted[k] = tf.gather(inputs[k], perm, axis=1)
    for k in ("points_xyz_tm1_in_t0", "point_features_tm1", "point_mask_tm1"):
        permuted[k] = tf.gather(inputs[k], perm1, axis=1)
    a, b = model(inputs)["flow_mps"].numpy(), model(permuted)["flow_mps"].numpy()
    # Equal up to float32 rounding only: a pillar's sum (unsorted_segment_sum) adds its points in another order, and
    # the decoder carries that rounding (~1e-7 relative per add) through every layer; flows here reach ~35 m/s, where
    # one float32 ulp is ~4e-6. A wrong point order gives errors of the flows' own size (m/s), far above this bound.
    np.testing.assert_allclose(b[0], a[0][perm], rtol=1e-5, atol=1e-4)


def test_invalid_points_are_masked_and_do_not_change_others(tiny_config):
    model = build_model(tiny_config)
    inputs = _inputs(np.random.default_rng(4), 1, 100, 100)
    base = model(inputs)
    xyz = inputs["points_xyz_t0"].numpy().copy()
    xyz[0, :5] = [[1e4, 0, 0], [0, 0, 50.0], [np.nan, 0, 0], [0, np.inf, 0], [0, 0, 0]]
    mask = np.ones([1, 100], bool)
    mask[0, 4] = False  # padding
    changed = dict(inputs, points_xyz_t0=tf.constant(xyz), point_mask_t0=tf.constant(mask))
    out = model(changed)
    assert not out["point_valid"].numpy()[0, :5].any() and out["point_valid"].numpy()[0, 5:].all()
    np.testing.assert_array_equal(out["flow_mps"].numpy()[0, :5], np.zeros((5, 3)))
    assert np.isfinite(out["flow_mps"].numpy()).all()
    # The other points only lose the removed points' pillar contributions; with them removed from the input
    # entirely, predictions match exactly.
    dropped = {k: (v[:, 5:] if k.endswith("_t0") and k != "points_xyz_tm1_in_t0" else v) for k, v in changed.items()}
    np.testing.assert_allclose(model(dropped)["flow_mps"].numpy()[0], out["flow_mps"].numpy()[0, 5:], atol=1e-5)
    del base


def test_xla_matches_eager(tiny_config):
    model = build_model(tiny_config)
    inputs = _inputs(np.random.default_rng(5), 2, 400, 300)
    # Untrained outputs reach ~15 m/s, where float32 spacing alone is ~1e-6; scale the last layer so that outputs
    # are of a real flow's size (~1 m/s) and 1e-5 is a meaningful bound.
    model.head_z.kernel.assign(model.head_z.kernel * 0.1)
    eager = model(inputs)["flow_mps"].numpy()
    xla = tf.function(lambda x: model(x, inline_stages=True), jit_compile=True)(inputs)["flow_mps"].numpy()
    graph = tf.function(lambda x: model(x))(inputs)["flow_mps"].numpy()
    np.testing.assert_allclose(xla, eager, atol=1e-5)
    np.testing.assert_allclose(graph, eager, atol=1e-5)


@pytest.mark.parametrize("n", [0, 1])
def test_tiny_and_empty_clouds(tiny_config, n):
    model = build_model(tiny_config)
    out = model(_inputs(np.random.default_rng(6), 1, n, n))
    assert out["flow_mps"].shape == (1, n, 3)


def test_mixed_precision_close_to_float32(tiny_config):
    import dataclasses
    cfg16 = dataclasses.replace(tiny_config, model=dataclasses.replace(tiny_config.model, mixed_precision=True))
    m32, m16 = build_model(tiny_config), build_model(cfg16)
    assert m16.conv_C.conv.compute_dtype == "bfloat16" and m16.conv_C.conv.kernel.dtype == "float32"
    m16.set_weights(m32.get_weights())
    inputs = _inputs(np.random.default_rng(7), 1, 300, 300)
    a, b = m32(inputs), m16(inputs)
    assert b["flow_mps"].dtype == tf.float32
    np.testing.assert_array_equal(a["point_valid"].numpy(), b["point_valid"].numpy())
    rel = np.linalg.norm(b["flow_mps"] - a["flow_mps"]) / np.linalg.norm(a["flow_mps"])
    assert rel < 0.05, rel


def test_flow_equals_the_table_rows_called_one_by_one(tiny_config):
    """The fused forward evaluates rows A-Z in its own order (head rows Y, Z composed into one linear map, each
    point's own share of the flow taken while its features are computed); the result equals the layers of the table
    called one after the other through their public calls, with the [N, C] point features built whole, and the
    table forward (tests/model/test_plan.py compares the two in every form, with gradients)."""
    model = build_model(tiny_config)
    model.head_z.kernel.assign(model.head_z.kernel * 0.1)  # flows of a real size (~1 m/s), see test_xla_matches_eager
    inputs = _inputs(np.random.default_rng(8), 2, 300, 280)
    enc, ids, valid = model.pillarize(inputs["points_xyz_t0"], inputs["point_features_t0"], inputs["point_mask_t0"])
    encoded = model.encode_points(inputs)
    features = tf.nn.relu(model.point_encoder.dense(model.point_encoder.norm(enc, valid)))  # row A, inference BN
    features = tf.where(valid[..., None], features, 0.0)
    grid_flow_embedding = model.dense_stages(encoded["bev_features"])  # rows C-V
    row_x = tf.concat([model.head_y.ungrid(grid_flow_embedding, ids), features, enc], -1)  # rows W, X
    expected = model.head_z(model.head_y(row_x))  # rows Y, Z
    v = valid.numpy()
    assert v.sum() > 400
    np.testing.assert_allclose(model(inputs)["flow_mps"].numpy()[v], expected.numpy()[v], atol=1e-5)
    np.testing.assert_allclose(model.table_forward(inputs)["flow_mps"].numpy()[v], expected.numpy()[v], atol=1e-5)


def test_point_stages_hold_no_per_point_feature_array(tiny_config):
    """At several chunks per cloud, neither point stage has an [N, C] array (point features) nor an [N, 8] one (the
    encoding: each chunk computes its own from the 5 input values of its points): memory per point stays a few floats
    at any cloud size (at 1M points, no 256 MB feature array)."""
    model = build_model(tiny_config, point_chunk_size=128)
    n, c = 1500, tiny_config.model.point_feature_dim  # n above the grid's 32 x 32 cells
    inputs = _inputs(np.random.default_rng(9), 1, n, n)
    encode = tf.function(lambda x: model.encode_points(x), jit_compile=True)
    encoded = encode(inputs)
    grid = model.grid_stages(encoded["bev_features"])
    decode = tf.function(lambda g, e: model.decode_points(g, e), jit_compile=True)
    hlo = (encode.experimental_get_compiler_ir(inputs)(stage="optimized_hlo") +
           decode.experimental_get_compiler_ir(grid, encoded)(stage="optimized_hlo"))
    per_point = re.compile(r"f32\[(?:1,)?(\d+),(\d+)\]")
    wide = {m.group(0) for m in per_point.finditer(hlo) if int(m.group(1)) >= n and int(m.group(2)) in (c, 8)}
    assert not wide, wide
    chunked = re.findall(r"f32\[\d+,128,8\]", hlo)  # the encoding padded to whole chunks, [K, 128, 8]
    assert not chunked, chunked
    assert "f32[128,%d]" % c in hlo and "f32[128,8]" in hlo  # one chunk's features and encoding
