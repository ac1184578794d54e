"""The model's convolution forms (fields of the execution plan, `ff3d_tf.model.plan`): the stride-2 convolution
whose gradients are computed phase by phase (`ops.conv2d_stride2`), the 1x1 convolution as a matrix product and the choice between them
(`layers.Conv2D`), a chain of convolutions as one composed convolution (`ops.conv_chain_same`), rows U5-V composed
with the head's grid part (`FastFlow3D.grid_stages`) and each decoder block's U6 with the next block's U1
(`layers.UpsampleSkip.into_next`). Each against TensorFlow's own convolutions and their gradients, or against the
model's plain forms (the whole forward against the table's: tests/model/test_plan.py)."""
import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.model import build_model
from ff3d_tf.model import layers as L
from ff3d_tf.model import ops
from ff3d_tf.model.plan import resolve


def _value_and_gradients(conv, x, kernel, dy, jit_compile):
    def run(x, kernel):
        with tf.GradientTape() as tape:
            tape.watch([x, kernel])
            y = conv(x, kernel)
        return [y] + tape.gradient(y, [x, kernel], output_gradients=dy)
    return [t.numpy() for t in tf.function(run, jit_compile=jit_compile)(x, kernel)]


@pytest.mark.parametrize("jit_compile", [False, True])
@pytest.mark.parametrize("shape", [(2, 8, 6, 3), (1, 4, 10, 5)])
def test_conv2d_stride2_values_and_gradients_are_tensorflows(shape, jit_compile):
    """The convolution, its input gradient and its kernel gradient equal TensorFlow's stride-2 SAME convolution's (its
    Conv2D and the gradients TensorFlow registers for it), eagerly and under XLA, on grids that are not square."""
    rng = np.random.default_rng(0)
    b, h, w, c = shape
    x = tf.constant(rng.normal(size=shape).astype(np.float32))
    kernel = tf.constant(rng.normal(size=(3, 3, c, 4)).astype(np.float32))
    dy = tf.constant(rng.normal(size=(b, h // 2, w // 2, 4)).astype(np.float32))
    want = _value_and_gradients(lambda x, k: tf.nn.conv2d(x, k, 2, "SAME"), x, kernel, dy, jit_compile)
    got = _value_and_gradients(ops.conv2d_stride2, x, kernel, dy, jit_compile)
    for name, g, v in zip(("output", "input gradient", "kernel gradient"), got, want):
        assert g.shape == v.shape, name
        np.testing.assert_allclose(g, v, rtol=1e-5, atol=1e-5 * np.abs(v).max(), err_msg=name)


def _chain(x, kernels):
    for k in kernels:
        x = tf.nn.conv2d(x, k, 1, "SAME")
    return x


def _random(rng, *shape):
    return tf.constant(rng.normal(size=shape).astype(np.float32))


def test_composed_kernel_is_the_two_convolutions():
    """Without padding (no border), a convolution by `composed_kernel(a, b)` is the convolution by a then by b."""
    rng = np.random.default_rng(1)
    x, a, b = _random(rng, 1, 9, 11, 4), _random(rng, 3, 3, 4, 5), _random(rng, 5, 3, 5, 2)
    want = tf.nn.conv2d(tf.nn.conv2d(x, a, 1, "VALID"), b, 1, "VALID").numpy()
    composed = ops.composed_kernel(a, b)
    assert composed.shape == (7, 5, 4, 2)
    np.testing.assert_allclose(tf.nn.conv2d(x, composed, 1, "VALID").numpy(), want, rtol=1e-5,
                               atol=1e-5 * np.abs(want).max())


def _chain_values_and_gradients(fn, x, kernels, dy, jit_compile):
    def run(x, *kernels):
        with tf.GradientTape() as tape:
            tape.watch([x, *kernels])
            y = fn(x, list(kernels))
        return [y] + tape.gradient(y, [x, *kernels], output_gradients=dy)
    return [t.numpy() for t in tf.function(run, jit_compile=jit_compile)(x, *kernels)]


@pytest.mark.parametrize("jit_compile", [False, True])
@pytest.mark.parametrize("kernel_shape", [(3, 3), (5, 3), (1, 1)])
def test_conv2d_same_by_taps_is_tensorflows(kernel_shape, jit_compile):
    """The matrix product to every tap and the shifted sums: TensorFlow's SAME convolution, its input gradient and
    its kernel gradient, on a grid that is not square and with kernels that are not."""
    rng = np.random.default_rng(2)
    x, kernel, dy = _random(rng, 2, 7, 9, 5), _random(rng, *kernel_shape, 5, 3), _random(rng, 2, 7, 9, 3)
    want = _chain_values_and_gradients(_chain, x, [kernel], dy, jit_compile)
    got = _chain_values_and_gradients(lambda x, k: ops.conv2d_same_by_taps(x, k[0]), x, [kernel], dy, jit_compile)
    for name, g, v in zip(("output", "input gradient", "kernel gradient"), got, want):
        assert g.shape == v.shape, name
        np.testing.assert_allclose(g, v, rtol=1e-5, atol=1e-5 * np.abs(v).max(), err_msg=name)


@pytest.mark.parametrize("jit_compile", [False, True])
@pytest.mark.parametrize("grid", [(12, 14), (16, 10), (6, 9)])
def test_conv_chain_same_is_the_chain(grid, jit_compile):
    """Three 3x3 SAME convolutions one after the other (as rows U5, U6 and V with the head): `conv_chain_same`'s
    output and the gradients of its input and of every kernel equal the chain's, with the border strips (12 x 14,
    16 x 10: the smallest sides that take them are 10) and without them (6 x 9: the chain itself)."""
    rng = np.random.default_rng(3)
    h, w = grid
    x, dy = _random(rng, 1, h, w, 6), _random(rng, 1, h, w, 3)
    kernels = [_random(rng, 3, 3, 6, 5), _random(rng, 3, 3, 5, 4), _random(rng, 3, 3, 4, 3)]
    want = _chain_values_and_gradients(_chain, x, kernels, dy, jit_compile)
    got = _chain_values_and_gradients(ops.conv_chain_same, x, kernels, dy, jit_compile)
    names = ("output", "input gradient", "first kernel's gradient", "second kernel's gradient",
             "third kernel's gradient")
    for name, g, v in zip(names, got, want):
        assert g.shape == v.shape, name
        np.testing.assert_allclose(g, v, rtol=1e-5, atol=1e-5 * np.abs(v).max(), err_msg=name)


def test_the_composed_kernel_alone_differs_on_the_border():
    """What the border strips of `conv_chain_same` are for: the composed kernel alone differs from the chain on the
    cells within two of the border (the chain's zero padding of its intermediate grids) and equals it inside."""
    rng = np.random.default_rng(4)
    x = _random(rng, 1, 12, 12, 4)
    kernels = [_random(rng, 3, 3, 4, 4), _random(rng, 3, 3, 4, 4), _random(rng, 3, 3, 4, 2)]
    want = _chain(x, kernels).numpy()
    composed = ops.composed_kernel(ops.composed_kernel(kernels[0], kernels[1]), kernels[2])
    alone = ops.conv2d_same_by_taps(x, composed).numpy()
    tolerance = 1e-5 * np.abs(want).max()
    np.testing.assert_allclose(alone[:, 2:-2, 2:-2], want[:, 2:-2, 2:-2], atol=tolerance)
    for ring in (alone[:, :2] - want[:, :2], alone[:, -2:] - want[:, -2:], alone[:, :, :2] - want[:, :, :2]):
        assert np.abs(ring).max() > 100 * tolerance


def test_stride2_by_phases_applies_only_where_it_computes_the_same():
    assert ops.stride2_by_phases_applies((2, 8, 6, 3), (3, 3, 3, 4), (2, 2), "same")
    assert not ops.stride2_by_phases_applies((2, 7, 6, 3), (3, 3, 3, 4), (2, 2), "same")  # odd: SAME pads the front
    assert not ops.stride2_by_phases_applies((2, None, 6, 3), (3, 3, 3, 4), (2, 2), "same")  # size unknown
    assert not ops.stride2_by_phases_applies((2, 8, 6, 3), (3, 3, 3, 4), (1, 1), "same")
    assert not ops.stride2_by_phases_applies((2, 8, 6, 3), (5, 5, 3, 4), (2, 2), "same")
    assert not ops.stride2_by_phases_applies((2, 8, 6, 3), (3, 3, 3, 4), (2, 2), "valid")


def _op_types(layer, x):
    graph = tf.function(layer).get_concrete_function(x).graph
    return {op.type for op in graph.get_operations()}


@pytest.mark.parametrize("kernel_size,strides,phases", [(1, 1, False), (3, 2, True), (3, 1, False)])
def test_conv2d_layer_equals_keras_conv2d(kernel_size, strides, phases):
    """`layers.Conv2D` with the weights of Keras's Conv2D: the same output and gradients in every form, and the op it
    runs: a matrix product for 1x1 (`matmul_1x1`), the phase-gradient op where asked for (`stride2_phase_gradients`),
    Keras's convolution with both off."""
    rng = np.random.default_rng(1)
    x = tf.constant(rng.normal(size=(2, 8, 6, 5)).astype(np.float32))
    keras_conv = keras.layers.Conv2D(4, kernel_size, strides=strides, padding="same", use_bias=False)
    ours = L.Conv2D(4, kernel_size, strides=strides, padding="same", use_bias=False)
    keras_conv.build(x.shape)
    ours.build(x.shape)
    ours.set_weights(keras_conv.get_weights())

    def outputs_and_gradients(layer):
        with tf.GradientTape() as tape:
            tape.watch(x)
            y = layer(x)
            loss = tf.reduce_sum(y * y)
        return [y.numpy()] + [g.numpy() for g in tape.gradient(loss, [x, layer.kernel])]

    want = outputs_and_gradients(keras_conv)
    for forms in (False, True):
        ours.matmul_1x1, ours.stride2_phase_gradients = forms, forms and phases
        for g, v in zip(outputs_and_gradients(ours), want):
            np.testing.assert_allclose(g, v, rtol=1e-5, atol=1e-5 * np.abs(v).max(), err_msg=str(forms))
        ops_run = _op_types(ours, x)
        if not forms or kernel_size == 3:
            assert "Conv2D" in ops_run and "MatMul" not in ops_run, forms
        else:
            assert "MatMul" in ops_run and "Conv2D" not in ops_run
        if forms and phases:  # the custom gradient's identity op wraps the phase-gradient convolution
            assert "IdentityN" in ops_run
        else:
            assert "IdentityN" not in ops_run


def test_strided_gradients_by_phases_where_xla_compiles_on_a_cpu(tiny_config):
    """The plan's rule (`plan.resolve`), and the model's stride-2 convolutions told it."""
    for mode, device, expected in (("xla", "CPU", True), ("xla", "GPU", False), ("hybrid", "CPU", False),
                                   ("none", "CPU", False)):
        assert resolve(tiny_config.model, "train", mode, device)[0].stride2_phase_gradients is expected
    for mode in ("xla", "hybrid"):
        model = build_model(tiny_config, mode)
        flags = {block.name: block.conv.stride2_phase_gradients for stage in model.encoder_stages
                 for block in stage}
        assert set(flags.values()) == {mode == "xla"}, (mode, flags)


def _inputs(seed=3, n0=400, n1=380):
    rng = np.random.default_rng(seed)

    def cloud(n):
        xyz = rng.uniform(-38, 38, (1, n, 3)).astype(np.float32)
        xyz[..., 2] = rng.uniform(-2.5, 2.5, (1, n))
        return tf.constant(xyz), tf.constant(rng.uniform(0, 1, (1, n, 2)).astype(np.float32))
    p0, f0 = cloud(n0)
    p1, f1 = cloud(n1)
    return {"points_xyz_t0": p0, "point_features_t0": f0, "point_mask_t0": tf.ones([1, n0], tf.bool),
            "points_xyz_tm1_in_t0": p1, "point_features_tm1": f1, "point_mask_tm1": tf.ones([1, n1], tf.bool)}


def test_grid_stages_compose_rows_u5_to_v_with_the_head(tiny_config):
    """With the paper head, `grid_stages` is rows C-V (`dense_stages`) followed by the head's grid kernel, computed
    as one chain from row U's merged input (U5, U6, V and the head: the inference plan's `decoder_chain`); the same
    cell flow as the layers one after the other, and as the plan without those forms."""
    keras.utils.set_random_seed(4)
    model = build_model(tiny_config, "none")
    assert model.plan.decoder_chain and model.plan.v_with_head
    bev = tf.constant(np.random.default_rng(5).normal(size=(
        2, tiny_config.grid.num_pillars_y, tiny_config.grid.num_pillars_x,
        tiny_config.model.point_feature_dim)).astype(np.float32))
    k_grid = model.head_y.composed_with(model.head_z)[0]
    for training in (True, False):
        want = tf.einsum("bhwc,cu->bhwu", model.dense_stages(bev, training), k_grid).numpy()
        got = model.grid_stages(bev, training).numpy()
        assert got.shape == want.shape and got.shape[-1] == 3 and np.abs(want).max() > 0
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
    plain = build_model(tiny_config, plan=model.plan.replace(v_with_head=False, decoder_chain=False,
                                                              u6_into_next_u1=False, matmul_1x1=False))
    plain.set_weights(model.get_weights())
    np.testing.assert_allclose(plain.grid_stages(bev).numpy(), want, rtol=1e-5, atol=1e-5 * np.abs(want).max())


def test_upsample_skip_into_next_is_the_next_blocks_u1(tiny_config):
    """Row S's output read by row T's U1, as S computes it (`UpsampleSkip.into_next`: U6 and T's U1 as one 3x3
    convolution): the same as the layers one after the other, also where S's own U1 output is given."""
    keras.utils.set_random_seed(7)
    s, t, _ = build_model(tiny_config, "none").upsample_skips
    rng = np.random.default_rng(8)
    alpha = _random(rng, 1, 4, 4, s.u1.kernel.shape[2])
    beta = _random(rng, 1, 8, 8, s.u3.kernel.shape[2])
    want = t.u1(s([alpha, beta])).numpy()
    assert want.shape == (1, 8, 8, t.u1.filters) and np.abs(want).max() > 0
    for got in (s.into_next([alpha, beta], t), s.into_next([None, beta], t, u1=s.u1(alpha))):
        np.testing.assert_allclose(got.numpy(), want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
