"""The point encoding split into programs (compile mode hybrid's per-cloud programs, `compile.hybrid_encode`, the
plan's `point_programs`): the pillar sums equal tf.math.unsorted_segment_sum and a NumPy reference to float32 rounding (empty pillars, masked and
padded points, repeated ids), in eager, graph and XLA; gradients equal; the clouds' programs depend on nothing of
each other; the model's forward and gradients equal those of the single program and of no XLA."""
import keras
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib
from ff3d_tf.model import ops
from ff3d_tf.model.layers import PointEncoder
from ff3d_tf.model.plan import ExecutionPlan, resolve

H, W, C = 6, 5, 8  # a small grid: many points per pillar, empty pillars


def _clouds(seed, batch=2, n=(70, 53), padded=80):
    """Two clouds of point rows [B,P,8] (the encoding itself: `encode` is the identity here), masks with padding and
    masked points, pillar ids with repeats (few pillars) and every pillar of the last row left empty."""
    rng = np.random.default_rng(seed)
    points, valid, ids = [], [], []
    for count in n:
        p = rng.normal(size=(batch, padded, 8)).astype(np.float32)
        v = np.zeros((batch, padded), bool)
        v[:, :count] = rng.uniform(size=(batch, count)) > 0.2  # masked points among the real ones, then padding
        cells = rng.integers(0, (H - 1) * W, size=(batch, padded))  # the last row of pillars stays empty
        i = (np.arange(batch)[:, None] * H * W + cells).astype(np.int32)
        i[~v] = batch * H * W  # invalid points: the dummy segment, as Pillarize gives them
        points.append(p), valid.append(v), ids.append(i)
    return points, valid, ids


def _numpy_sums(layer, points, valid, ids):
    """The pillar sums by hand: each valid point's feature relu(BN(x) @ K) added into its pillar (moving BN
    statistics), [B,H,W,C] per cloud."""
    kernel = layer.dense.kernel.numpy()
    bn = layer.norm
    scale = bn.gamma.numpy() / np.sqrt(bn.moving_variance.numpy() + bn.epsilon)
    grids = []
    for p, v, i in zip(points, valid, ids):
        batch = p.shape[0]
        features = np.maximum(((p - bn.moving_mean.numpy()) * scale + bn.beta.numpy()) @ kernel, 0.0)
        grid = np.zeros((batch * H * W, C), np.float64)
        np.add.at(grid, i[v], features[v])
        grids.append(grid.reshape(batch, H, W, C))
    return grids


def _layer(chunk_size):
    keras.utils.set_random_seed(1)
    layer = PointEncoder(C, W, H, chunk_size=chunk_size)
    layer.build((None, None, 8))
    # Non-trivial moving statistics, so that the normalisation matters.
    layer.norm.moving_mean.assign(np.linspace(-0.3, 0.3, 8).astype(np.float32))
    layer.norm.moving_variance.assign(np.linspace(0.5, 2.0, 8).astype(np.float32))
    return layer


@pytest.mark.parametrize("how,chunk_size", [("eager", 16), ("graph", 16), ("xla", 16), ("graph", ops.ONE_CHUNK)])
def test_programs_per_cloud_equal_segment_sum_and_numpy(how, chunk_size):
    layer = _layer(chunk_size)
    points, valid, ids = _clouds(seed=0)
    args = ([tf.constant(p) for p in points], [tf.constant(v) for v in valid], [tf.constant(i) for i in ids])

    def run(stage):
        grids, _ = layer(*args, stage=stage)
        return grids

    staged = {"eager": lambda: run(compile_lib.xla_function),
              "graph": tf.function(lambda: run(compile_lib.xla_function)),
              "xla": tf.function(lambda: run(None), jit_compile=True)}[how]()
    inline = tf.function(lambda: run(None))()
    for got, plain, reference, p, v, i in zip(staged, inline, _numpy_sums(layer, points, valid, ids), points, valid,
                                              ids):
        np.testing.assert_allclose(got.numpy(), reference, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(got.numpy(), plain.numpy(), rtol=1e-6, atol=1e-6)
        # Against tf.math.unsorted_segment_sum of the same features (invalid points dropped with id -1).
        kernel = layer.dense.kernel
        bn = layer.norm
        mean, scale, beta = bn.normalizer([tf.constant(p)], [tf.constant(v)])
        features = tf.nn.relu(((p - mean) * scale + beta) @ kernel)
        flat = tf.math.unsorted_segment_sum(tf.reshape(features, [-1, C]),
                                            tf.reshape(tf.where(v, i, -1), [-1]), p.shape[0] * H * W)
        np.testing.assert_allclose(got.numpy().reshape(-1, C), flat.numpy(), rtol=1e-5, atol=1e-5)
    assert not np.any(staged[0].numpy()[:, H - 1])  # the empty row of pillars stays zero


@pytest.mark.parametrize("training", [True])
def test_gradients_per_cloud_equal_single_program(training):
    layer = _layer(chunk_size=16)
    points, valid, ids = _clouds(seed=1)
    args = ([tf.constant(p) for p in points], [tf.constant(v) for v in valid], [tf.constant(i) for i in ids])
    upstream = [tf.constant(np.random.default_rng(2).normal(size=(2, H, W, C)).astype(np.float32)) for _ in range(2)]
    variables = layer.trainable_variables

    def grads(stage):
        @tf.function
        def f(points):
            with tf.GradientTape() as tape:
                tape.watch(points)
                grids, _ = layer(points, args[1], args[2], training=training, stage=stage)
                total = tf.add_n([tf.reduce_sum(g * u) for g, u in zip(grids, upstream)])
            return tape.gradient(total, variables + points)
        return f(args[0])

    for a, b in zip(grads(compile_lib.xla_function), grads(None)):
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=2e-5, atol=2e-5)


def _call_ops(graph):
    """The function-call ops of a graph (the programs a hybrid forward launches), by name."""
    return {op.name: op for op in graph.get_operations() if op.type in ("StatefulPartitionedCall",
                                                                         "PartitionedCall")}


def _depends_on(op, other, seen=None):
    seen = set() if seen is None else seen
    for x in list(op.inputs) + list(op.control_inputs):
        source = x.op if hasattr(x, "op") else x
        if source is other:
            return True
        if source.name not in seen:
            seen.add(source.name)
            if _depends_on(source, other, seen):
                return True
    return False


def test_hybrid_launches_the_clouds_as_independent_programs(tiny_config):
    model = build_model(tiny_config, "hybrid")
    assert model.plan.point_programs == "per_cloud"
    rng = np.random.default_rng(0)
    inputs = {"points_xyz_t0": tf.constant(rng.uniform(-20, 20, (1, 64, 3)).astype(np.float32)),
              "point_features_t0": tf.constant(rng.uniform(0, 1, (1, 64, 2)).astype(np.float32)),
              "point_mask_t0": tf.ones([1, 64], tf.bool),
              "points_xyz_tm1_in_t0": tf.constant(rng.uniform(-20, 20, (1, 48, 3)).astype(np.float32)),
              "point_features_tm1": tf.constant(rng.uniform(0, 1, (1, 48, 2)).astype(np.float32)),
              "point_mask_tm1": tf.ones([1, 48], tf.bool)}
    graph = tf.function(lambda x: model(x)).get_concrete_function(inputs).graph
    programs = [op for op in _call_ops(graph).values() if op.get_attr("_XlaMustCompile")]
    encoders = [op for op in programs if "encode_cloud" in op.get_attr("f").name]
    assert len(encoders) == 2, [op.get_attr("f").name for op in programs]
    assert not _depends_on(encoders[0], encoders[1]) and not _depends_on(encoders[1], encoders[0])


@pytest.mark.parametrize("training", [True])
def test_model_per_cloud_equals_one_program_and_no_xla(tiny_config, training):
    from tests.model.test_fastflow3d import _inputs  # the tests' random clouds
    inputs = _inputs(np.random.default_rng(3), 2, 300, 250, extent=20.0)
    results = {}
    for name, mode, programs in (("none", "none", "one"), ("one", "hybrid", "one"),
                                 ("per_cloud", "hybrid", "per_cloud")):
        keras.utils.set_random_seed(0)
        plan = resolve(tiny_config.model, "train", compile_mode=mode)[0].replace(point_programs=programs)
        model = build_model(tiny_config, point_chunk_size=128, plan=plan)

        @tf.function
        def f(x, model=model):
            with tf.GradientTape() as tape:
                flow = model(x, training=training)["flow_mps"]
                loss = tf.reduce_sum(tf.square(flow))
            return flow, tape.gradient(loss, model.trainable_variables)
        results[name] = f(inputs)
    for name in ("one", "per_cloud"):
        np.testing.assert_allclose(results[name][0].numpy(), results["none"][0].numpy(), rtol=1e-4, atol=1e-4)
        for a, b in zip(results[name][1], results["none"][1]):
            scale = max(float(np.abs(b.numpy()).max()), 1e-6)
            np.testing.assert_allclose(a.numpy() / scale, b.numpy() / scale, atol=1e-4)


def test_hybrid_point_programs_checked():
    with pytest.raises(ValueError, match="per_cloud, one"):
        ExecutionPlan(compile_mode="hybrid", point_programs="rows")
