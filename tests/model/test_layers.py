"""Every layer through the shared harness (config, eager == graph == XLA with gradients, mixed precision, masking),
plus each layer's values against an independent NumPy reference."""
import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.model import layers as L
from ff3d_tf.model import ops
from tests.model.layer_harness import run_layer_test

RNG = np.random.default_rng(0)
B, N, H, W = 2, 40, 4, 6  # tiny: 4 x 6 pillars


def _encodings(n=N, seed=0):
    """Encodings [B,n,8] with channels of different scale (as the real ones), a mask with padding, pillar ids."""
    rng = np.random.default_rng(seed)
    enc = rng.normal(0, 1, (B, n, 8)).astype(np.float32) * np.array([20, 20, 1, .1, .1, .5, 1, 1], np.float32)
    valid = rng.uniform(0, 1, (B, n)) < 0.8
    ids = rng.integers(0, H * W, (B, n)) + np.arange(B)[:, None] * H * W
    ids = np.where(valid, ids, B * H * W).astype(np.int32)
    return tf.constant(enc), tf.constant(valid), tf.constant(ids)


def _perturb_masked(values_index, mask_index):
    """perturb(call_args): values at masked positions replaced by large garbage."""
    def perturb(args):
        args = list(args)
        valid = np.asarray(args[mask_index])
        values = np.asarray(args[values_index]).copy()
        values[~valid] = 1e3
        args[values_index] = tf.constant(values)
        return tuple(args)
    return perturb


def test_pillarize():
    xyz = RNG.uniform(-3, 3, (B, N, 3)).astype(np.float32)
    feats = RNG.uniform(0, 1, (B, N, 2)).astype(np.float32)
    mask = RNG.uniform(0, 1, (B, N)) < 0.8
    run_layer_test(L.Pillarize, dict(num_pillars_x=W, num_pillars_y=H, x_range_m=(-3.0, 3.0), y_range_m=(-2.0, 2.0),
                                     z_range_m=(-1.0, 1.0)),
                   (tf.constant(xyz), tf.constant(feats), tf.constant(mask)),
                   expected_output_shapes=((B, N, 8), (B, N), (B, N)), mixed_precision=False,
                   # masked points: zero encoding, the dummy id, invalid, whatever their coordinates
                   masking=(_perturb_masked(0, 2), lambda out: out))


def test_masked_batch_norm_matches_numpy():
    enc, valid, _ = _encodings()
    layer, out = run_layer_test(L.MaskedBatchNorm, dict(momentum=0.9, epsilon=1e-3), (enc, valid),
                                {"training": True}, expected_output_shapes=(B, N, 8),
                                masking=(_perturb_masked(0, 1), lambda out: out[np.asarray(valid)]))
    x, v = enc.numpy()[valid.numpy()], valid.numpy()
    mean, var = x.mean(0), x.var(0)  # statistics of the valid points only
    expected = (enc.numpy() - mean) / np.sqrt(var + 1e-3)  # gamma 1, beta 0
    np.testing.assert_allclose(out[v], expected[v], atol=1e-4)


def _point_encoder_reference(encs, valids, ids, kernel, projections, epsilon=1e-3):
    """NumPy rows A, B: BN with joint statistics over the valid points of all clouds, ReLU(x @ K), pillar sums, and
    concat(feature, encoding) @ projection per point where a cloud has a projection."""
    joint = np.concatenate([e[v] for e, v in zip(encs, valids)])
    mean, var = joint.mean(0), joint.var(0)
    grids, rows = [], []
    for e, v, i, p in zip(encs, valids, ids, projections):
        f = np.maximum(((e - mean) / np.sqrt(var + epsilon)) @ kernel, 0) * v[..., None]
        grid = np.zeros((B * H * W + 1, kernel.shape[1]), np.float64)
        np.add.at(grid, i.reshape(-1), f.reshape(-1, kernel.shape[1]))
        grids.append(grid[:-1].reshape(B, H, W, -1))
        rows.append(None if p is None else np.concatenate([f, e], -1) @ p)
    return grids, rows


PROJECTION = tf.constant(RNG.normal(0, 0.3, (5 + 8, 3)).astype(np.float32))  # [C + 8, 3]


@pytest.mark.parametrize("chunk_size", [1 << 18, 7])  # one chunk; several chunks and a padded last one
def test_point_encoder_matches_numpy(chunk_size):
    (e0, v0, i0), (e1, v1, i1) = _encodings(N, 1), _encodings(N - 9, 2)

    def perturb_masked_t0(args):  # the first cloud's masked encodings -> garbage
        (enc0, enc1), valids, ids = args
        return [_perturb_masked(0, 1)((enc0, valids[0]))[0], enc1], valids, ids

    layer, (grids, rows) = run_layer_test(
        L.PointEncoder, dict(units=5, num_pillars_x=W, num_pillars_y=H, chunk_size=chunk_size),
        ([e0, e1], [v0, v1], [i0, i1]), {"point_projections": (PROJECTION, None), "training": True},
        expected_output_shapes=([(B, H, W, 5), (B, H, W, 5)], [(B, N, 3), None]),
        float32_under_mixed=(0, 1),  # pillar sums accumulate in float32 under mixed precision
        # masked points add nothing to the grids; their rows are arbitrary (the caller masks them)
        masking=(perturb_masked_t0, lambda out: (out[0], out[1][0][np.asarray(v0)])))
    ref_grids, ref_rows = _point_encoder_reference([e0.numpy(), e1.numpy()], [v0.numpy(), v1.numpy()],
                                                   [i0.numpy(), i1.numpy()], layer.dense.kernel.numpy(),
                                                   [PROJECTION.numpy(), None])
    np.testing.assert_allclose(grids[0], ref_grids[0], atol=1e-4)
    np.testing.assert_allclose(grids[1], ref_grids[1], atol=1e-4)
    v = v0.numpy()
    np.testing.assert_allclose(rows[0][v], ref_rows[0][v], atol=1e-4)


@pytest.mark.parametrize("compiled", ["eager", "xla", "graph_unknown_point_count"])
def test_point_encoder_chunked_gradient_matches_autodiff(compiled):
    """The chunk loop's own gradient equals automatic differentiation of the plain (unchunked) formula: grid and
    projected rows, with respect to the encodings, BN, kernel and projection."""
    enc, valid, ids = _encodings(N, 3)
    layer = L.PointEncoder(units=5, num_pillars_x=W, num_pillars_y=H, chunk_size=6)
    layer(enc, valid, ids, point_projections=PROJECTION, training=True)
    upstream = tf.random.stateless_normal((B, H, W, 5), seed=[1, 2])
    upstream_rows = tf.random.stateless_normal((B, N, 3), seed=[3, 4]) * tf.cast(valid, tf.float32)[..., None]

    def chunked(enc, valid, ids, projection):
        with tf.GradientTape() as tape:
            tape.watch([enc, projection])
            grid, rows = layer(enc, valid, ids, point_projections=projection, training=True)
            loss = tf.reduce_sum(grid * upstream) + tf.reduce_sum(rows * upstream_rows)
        return loss, tape.gradient(loss, [enc, projection] + layer.trainable_variables)

    if compiled == "xla":
        chunked = tf.function(chunked, jit_compile=True)
    elif compiled == "graph_unknown_point_count":  # the loop's count known only at run time
        chunked = tf.function(chunked, input_signature=[tf.TensorSpec([B, None, 8]), tf.TensorSpec([B, None], tf.bool),
                                                        tf.TensorSpec([B, None], tf.int32), tf.TensorSpec([13, 3])])
    loss, (d_enc, d_projection, *d_vars) = chunked(enc, valid, ids, PROJECTION)

    # Reference: the same function written directly with differentiable TF ops, no loop.
    gamma, beta, kernel = [tf.identity(v) for v in (layer.norm.gamma, layer.norm.beta, layer.dense.kernel)]
    projection = tf.identity(PROJECTION)
    with tf.GradientTape() as tape:
        tape.watch([enc, gamma, beta, kernel, projection])
        w = tf.cast(valid, tf.float32)[..., None]
        mean = tf.reduce_sum(enc * w, [0, 1]) / tf.reduce_sum(w)
        var = tf.reduce_sum(tf.square(enc - mean) * w, [0, 1]) / tf.reduce_sum(w)
        normed = (enc - mean) * gamma / tf.sqrt(var + 1e-3) + beta
        feat = tf.nn.relu(tf.einsum("bnc,cu->bnu", normed, kernel)) * w
        ref_grid = tf.math.unsorted_segment_sum(feat, ids, B * H * W + 1)[:-1]
        ref_rows = tf.einsum("bnc,cu->bnu", tf.concat([feat, enc], -1), projection)
        ref_loss = (tf.reduce_sum(tf.reshape(ref_grid, [B, H, W, 5]) * upstream) +
                    tf.reduce_sum(ref_rows * upstream_rows))
    ref = tape.gradient(ref_loss, [enc, projection, gamma, beta, kernel])
    np.testing.assert_allclose(loss.numpy(), ref_loss.numpy(), rtol=1e-5)
    np.testing.assert_allclose(d_enc.numpy(), ref[0].numpy(), atol=1e-4)
    np.testing.assert_allclose(d_projection.numpy(), ref[1].numpy(), rtol=1e-4, atol=1e-4)
    for got, want in zip(d_vars, ref[2:]):  # gamma, beta, kernel in the layer's variable order
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-4, atol=1e-4)


def test_conv_block():
    x = tf.constant(RNG.normal(0, 1, (B, 8, 8, 3)).astype(np.float32))
    run_layer_test(L.ConvBlock, dict(filters=4, strides=2), (x,), {"training": True},
                   expected_output_shapes=(B, 4, 4, 4))


def _conv_block_off_initial_values(input_shape, strides):
    """A 4-filter ConvBlock whose BatchNorm gamma, beta, moving mean and variance are random, and those four."""
    block = L.ConvBlock(4, strides=strides)
    block.build(input_shape)
    values = (RNG.uniform(0.5, 1.5, 4).astype(np.float32), RNG.normal(0, 1, 4).astype(np.float32),
              RNG.normal(0, 1, 4).astype(np.float32), RNG.uniform(0.5, 2, 4).astype(np.float32))
    for variable, value in zip((block.bn.gamma, block.bn.beta, block.bn.moving_mean, block.bn.moving_variance),
                               values):
        variable.assign(value)
    return block, values


@pytest.mark.parametrize("training", [True, False])
def test_conv_block_batch_norm_matches_numpy(training):
    """The fused BatchNorm computes Keras' BatchNormalization: batch statistics (biased variance) in training, moving
    statistics updated with momentum 0.99, moving statistics in inference; epsilon 1e-3."""
    x = tf.constant(RNG.normal(0, 1, (B, 8, 8, 3)).astype(np.float32))
    block, (gamma, beta, mean0, var0) = _conv_block_off_initial_values(x.shape, strides=1)
    conv = block.conv(x).numpy()  # [B,8,8,4]
    out = block(x, training=training).numpy()
    if training:
        mean, variance = conv.mean((0, 1, 2)), conv.var((0, 1, 2))  # biased, as Keras
        np.testing.assert_allclose(block.bn.moving_mean.numpy(), 0.99 * mean0 + 0.01 * mean, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(block.bn.moving_variance.numpy(), 0.99 * var0 + 0.01 * variance, rtol=1e-6)
    else:
        mean, variance = mean0, var0
        np.testing.assert_array_equal(block.bn.moving_mean.numpy(), mean0)
    expected = np.maximum((conv - mean) / np.sqrt(variance + 1e-3) * gamma + beta, 0.0)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("strides", [1, 2])
def test_conv_block_folded_batch_norm_matches_numpy(strides):
    """Inference with the BatchNorm folded into the kernel and a bias (`fold_batch_norm`, the fold_bn export variant)
    gives the unfolded block's numbers: conv, (y - mean) / sqrt(var + eps) * gamma + beta, ReLU; at stride 2 with
    Keras' SAME padding. Training ignores the folding."""
    x = tf.constant(RNG.normal(0, 1, (B, 9, 9, 3)).astype(np.float32))  # odd size: stride 2 pads unevenly
    block, (gamma, beta, mean, var) = _conv_block_off_initial_values(x.shape, strides)
    conv = block.conv(x).numpy()
    expected = np.maximum((conv - mean) / np.sqrt(var + 1e-3) * gamma + beta, 0.0)
    block.fold_batch_norm = True  # as `FastFlow3D` sets it from the plan's fold_batch_norm
    np.testing.assert_allclose(block(x, training=False).numpy(), expected, rtol=1e-5, atol=1e-5)
    unfolded_training = L.ConvBlock(4, strides=strides)
    unfolded_training.build(x.shape)
    for a, b in zip(unfolded_training.weights, block.weights):
        a.assign(b)
    np.testing.assert_allclose(block(x, training=True).numpy(), unfolded_training(x, training=True).numpy(),
                               rtol=1e-6, atol=1e-6)


def _bilinear_2x_matrix(n):
    """[2n, n]: output o samples input coordinate (o + 0.5) / 2 - 0.5 (half-pixel centres), linear between the two
    nearest inputs, clamped to the edges: rows 2i = 0.75 e_i + 0.25 e_(i-1), rows 2i+1 = 0.75 e_i + 0.25 e_(i+1)."""
    m = np.zeros((2 * n, n))
    for o in range(2 * n):
        c = min(max((o + 0.5) / 2 - 0.5, 0.0), n - 1.0)
        lo = int(np.floor(c))
        hi = min(lo + 1, n - 1)
        m[o, lo] += 1.0 - (c - lo)
        m[o, hi] += c - lo
    return m


@pytest.mark.parametrize("shape", [(2, 1, 1, 3), (1, 2, 3, 4), (2, 7, 5, 3)])
def test_bilinear_upsample_2x_matches_numpy_and_keras(shape):
    """Values: the interpolation matrices in NumPy (and Keras's bilinear UpSampling2D, the same interpolation);
    gradient: the matrices' transposes, up^T(g) = M_h^T g M_w, in eager TensorFlow and in one XLA program."""
    _, h, w, _ = shape
    x = RNG.normal(0, 1, shape).astype(np.float32)
    g = RNG.normal(0, 1, (shape[0], 2 * h, 2 * w, shape[3])).astype(np.float32)
    mh, mw = _bilinear_2x_matrix(h), _bilinear_2x_matrix(w)
    expected = np.einsum("oh,bhwc,pw->bopc", mh, x, mw)
    expected_grad = np.einsum("oh,bopc,pw->bhwc", mh, g, mw)
    layer = L.BilinearUpsample2x()
    keras_out = keras.layers.UpSampling2D(2, interpolation="bilinear")(x)
    np.testing.assert_allclose(keras_out, expected, atol=1e-5)

    def value_and_grad(x):
        with tf.GradientTape() as tape:
            tape.watch(x)
            y = layer(x)
            loss = tf.reduce_sum(y * g)
        return y, tape.gradient(loss, x)

    for fn in (value_and_grad, tf.function(value_and_grad, jit_compile=True)):
        y, grad = fn(tf.constant(x))
        np.testing.assert_allclose(y, expected, atol=1e-5)
        np.testing.assert_allclose(grad, expected_grad, atol=1e-5)


def test_upsample_skip():
    alpha = tf.constant(RNG.normal(0, 1, (B, 4, 4, 6)).astype(np.float32))
    beta = tf.constant(RNG.normal(0, 1, (B, 8, 8, 4)).astype(np.float32))
    run_layer_test(L.UpsampleSkip, dict(depth=5, bottleneck_depth=3), ([alpha, beta],),
                   expected_output_shapes=(B, 8, 8, 5))


def test_ungrid_head_is_row_y_on_row_x():
    """Row Y on row X (W's cell embedding, the point feature, the encoding, concatenated): X @ K + b, and its kernel's
    parts (`split_kernel`) are the blocks that multiply each part."""
    bev = tf.constant(RNG.normal(0, 1, (B, H, W, 6)).astype(np.float32))
    feats = tf.constant(RNG.normal(0, 1, (B, N, 4)).astype(np.float32))
    enc, valid, ids = _encodings(N, 4)
    x = tf.concat([L.UngridHead.ungrid(bev, ids), feats, enc], -1)  # W, X
    layer, out = run_layer_test(L.UngridHead, dict(units=3, grid_channels=6, point_channels=4), (x,),
                                expected_output_shapes=(B, N, 3))
    kernel, bias = layer.kernel.numpy(), layer.bias.numpy()
    cells = bev.numpy().reshape(B * H * W, 6)
    ungrid = cells[np.minimum(ids.numpy(), B * H * W - 1)]  # W: each point's pillar embedding
    expected = np.concatenate([ungrid, feats.numpy(), enc.numpy()], -1) @ kernel + bias  # X, Y
    v = valid.numpy()
    np.testing.assert_allclose(out[v], expected[v], atol=1e-4)
    k_grid, k_point, k_enc = layer.split_kernel(kernel)
    np.testing.assert_allclose(ungrid @ k_grid + feats.numpy() @ k_point + enc.numpy() @ k_enc + bias, expected,
                               atol=1e-4)
    with pytest.raises(ValueError, match="row X has 18 channels"):
        L.UngridHead(units=3, grid_channels=6, point_channels=4).build((None, None, 17))


def test_ungrid_head_composed_with_output_layer():
    """Rows Y and Z called one after the other equal the composed map the model evaluates: the grid part projected
    on the grid and gathered, plus the point feature and encoding parts, plus the composed bias."""
    bev = tf.constant(RNG.normal(0, 1, (B, H, W, 6)).astype(np.float32))
    feats = tf.constant(RNG.normal(0, 1, (B, N, 4)).astype(np.float32))
    enc, valid, ids = _encodings(N, 5)
    head = L.UngridHead(units=7, grid_channels=6, point_channels=4)
    output = keras.layers.Dense(3, bias_initializer="random_normal")
    expected = output(head(tf.concat([head.ungrid(bev, ids), feats, enc], -1)))
    k_grid, k_point, k_enc, bias = head.composed_with(output)
    got = (head.ungrid(ops.dense_last_axis(bev, k_grid), ids) + ops.dense_last_axis(feats, k_point) +
           ops.dense_last_axis(enc, k_enc) + bias)
    v = valid.numpy()
    np.testing.assert_allclose(got.numpy()[v], expected.numpy()[v], atol=1e-5)
