"""Each framework internal of `ff3d_tf.internals`, exercised, on the versions it was checked on (`CHECKED_ON`): an
upgrade fails here first, naming the function to re-check."""
import importlib.metadata
import os
import subprocess
import sys

import numpy as np
import pytest
import tensorflow as tf

from conftest import ROOT
from ff3d_tf import internals

CHECKED = [(function, package, version) for function, packages in internals.CHECKED_ON.items()
           for package, version in packages.items()]


@pytest.mark.parametrize("function,package,version", CHECKED, ids=[f"{f}-{p}" for f, p, _ in CHECKED])
def test_installed_versions_are_the_checked_ones(function, package, version):
    try:
        installed = importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:  # `make install` installs every package listed in CHECKED_ON
        installed = None
    assert installed == version, (f"re-check internals.{function} on {package} {installed} (checked on {version}), "
                                  f"then update internals.CHECKED_ON")


def test_every_internal_is_listed_and_the_module_imports_no_framework():
    public = {n for n, v in vars(internals).items() if callable(v) and not n.startswith("_")
              and getattr(v, "__module__", None) == internals.__name__}
    assert public == set(internals.CHECKED_ON)
    code = ("import sys; import ff3d_tf.internals; "
            "print(sorted(m for m in ('tensorflow', 'jax', 'keras') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("dtype", [tf.float32, tf.bfloat16])
def test_fused_batch_norm(dtype):
    rng = np.random.default_rng(0)
    x = rng.normal(1.0, 2.0, (2, 3, 4, 5)).astype(np.float32)
    scale, offset = rng.uniform(0.5, 1.5, 5).astype(np.float32), rng.normal(0, 1, 5).astype(np.float32)
    xt = tf.cast(x, dtype)
    x = tf.cast(xt, tf.float32).numpy()  # the values the kernel sees
    tol = 1e-5 if dtype == tf.float32 else 2e-2
    y, mean, variance = internals.fused_batch_norm(xt, scale, offset, epsilon=1e-3, training=True)
    n = x.size // 5
    np.testing.assert_allclose(mean.numpy(), x.mean((0, 1, 2)), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(variance.numpy(), x.var((0, 1, 2)) * n / (n - 1), rtol=1e-5)  # Bessel's correction
    assert y.dtype == dtype
    expected = (x - x.mean((0, 1, 2))) / np.sqrt(x.var((0, 1, 2)) + 1e-3) * scale + offset
    np.testing.assert_allclose(tf.cast(y, tf.float32).numpy(), expected, rtol=tol, atol=tol)

    moving_mean, moving_var = rng.normal(0, 1, 5).astype(np.float32), rng.uniform(0.5, 2, 5).astype(np.float32)
    y, _, _ = internals.fused_batch_norm(xt, scale, offset, epsilon=1e-3, training=False, mean=moving_mean,
                                         variance=moving_var)
    expected = (x - moving_mean) / np.sqrt(moving_var + 1e-3) * scale + offset
    np.testing.assert_allclose(tf.cast(y, tf.float32).numpy(), expected, rtol=tol, atol=tol)


def test_fused_batch_norm_gradient_under_xla():
    """Its gradient (FusedBatchNormGradV3) compiles with XLA and equals that of the elementwise formula."""
    x = tf.constant(np.random.default_rng(1).normal(0, 1, (2, 3, 3, 4)).astype(np.float32))
    scale, offset = tf.constant([1.0, 0.5, 2.0, 1.5]), tf.constant([0.0, 1.0, -1.0, 0.5])

    @tf.function(jit_compile=True)
    def grads(fused):
        with tf.GradientTape() as tape:
            tape.watch([x, scale, offset])
            if fused:
                y = internals.fused_batch_norm(x, scale, offset, epsilon=1e-3, training=True)[0]
            else:
                mean, var = tf.nn.moments(x, [0, 1, 2])
                y = tf.nn.batch_normalization(x, mean, var, offset, scale, 1e-3)
            loss = tf.reduce_sum(tf.sin(y))
        return tape.gradient(loss, [x, scale, offset])
    for got, want in zip(grads(True), grads(False)):
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-4, atol=1e-5)


def test_checkpoint_variable_keys(tmp_path):
    root = tf.Module()
    root.layer = tf.Module()
    root.layer.kernel = tf.Variable(tf.zeros([2, 3]))
    root.layer.shared = root.bias = tf.Variable(tf.ones([3]))  # two paths to one variable
    root.odd = {"a/b.c": tf.Variable(1.0)}  # a name the key escapes
    checkpoint = tf.train.Checkpoint(net=root)
    prefix = checkpoint.write(str(tmp_path / "ckpt"))
    reader = tf.train.load_checkpoint(prefix)
    keys = internals.checkpoint_variable_keys(reader.get_tensor("_CHECKPOINTABLE_OBJECT_GRAPH"))
    saved = set(reader.get_variable_to_shape_map()) - {"_CHECKPOINTABLE_OBJECT_GRAPH"}
    assert set(keys.values()) == saved and len(keys) == 3  # save_counter is not written by `write`
    matched = tf.train.CheckpointView(prefix).match(checkpoint)  # node ids as the keys number them
    key_of = {id(obj): keys[node] for node, obj in matched.items() if node in keys}
    assert reader.get_variable_to_shape_map()[key_of[id(root.layer.kernel)]] == [2, 3]
    assert key_of[id(root.bias)] == key_of[id(root.layer.shared)]
    assert key_of[id(root.odd["a/b.c"])] == "net/odd/a.Sb..c/.ATTRIBUTES/VARIABLE_VALUE"
    with pytest.raises(Exception):  # not an object graph
        internals.checkpoint_variable_keys(b"\xff" * 40)


def test_adam_slots_are_the_moments_adam_updates():
    import keras
    weights = [keras.Variable(np.zeros((2, 3), np.float32)), keras.Variable(np.zeros(3, np.float32))]
    optimizer = keras.optimizers.Adam(0.1, beta_1=0.5, beta_2=0.75)
    optimizer.build(weights)
    grads = [tf.fill([2, 3], 2.0), tf.fill([3], -1.0)]
    optimizer.apply_gradients(zip(grads, weights))
    momentums, velocities = internals.adam_slots(optimizer)
    # First step from zero moments: m = (1 - b1) g, v = (1 - b2) g^2, one per weight, in build order.
    for m, v, g in zip(momentums, velocities, grads):
        np.testing.assert_allclose(np.asarray(m), 0.5 * g.numpy())
        np.testing.assert_allclose(np.asarray(v), 0.25 * g.numpy() ** 2)


def test_checkpoint_reader_reads_a_prefix(tmp_path):
    prefix = tf.train.Checkpoint(v=tf.Variable([1.0, 2.0])).write(str(tmp_path / "ckpt"))
    reader = internals.checkpoint_reader(prefix)
    (key,) = [k for k in reader.get_variable_to_shape_map() if k.startswith("v/")]
    np.testing.assert_array_equal(reader.get_tensor(key), [1.0, 2.0])


def test_profiler_xspace_reads_a_trace(tmp_path):
    tf.profiler.experimental.start(str(tmp_path))
    tf.function(lambda x: tf.matmul(x, x))(tf.ones([8, 8]))
    tf.profiler.experimental.stop()
    (path,) = [os.path.join(d, f) for d, _, fs in os.walk(tmp_path) for f in fs if f.endswith(".xplane.pb")]
    space = internals.profiler_xspace(path)
    names = {m.name for plane in space.planes for m in plane.event_metadata.values()}
    assert any("MatMul" in n for n in names), sorted(names)[:20]


def test_hlo_to_jax_exported():
    pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")
    spec = [tf.TensorSpec([2, 3], tf.float32), tf.TensorSpec([3], tf.int32)]
    fn = tf.function(lambda x, i: (x * 2.0 + 1.0, tf.linalg.matvec(x, tf.cast(i, tf.float32))), jit_compile=True)
    hlo = fn.experimental_get_compiler_ir(*spec)(stage="hlo_serialized")
    exported = internals.hlo_to_jax_exported(hlo, ["cpu", "cuda"])
    assert exported.platforms == ("cpu", "cuda")
    assert [a.shape for a in exported.in_avals] == [(2, 3), (3,)]
    x, i = np.arange(6, dtype=np.float32).reshape(2, 3), np.array([1, 0, 2], np.int32)
    want = fn(x, i)
    from jax import export
    got = export.deserialize(exported.serialize()).call(x, i)
    for g, w in zip(got, want):
        np.testing.assert_allclose(np.asarray(g), w.numpy(), rtol=1e-6)


def test_tf2onnx_custom_op_handlers_lower_segment_sums_and_selects():
    # The full checks against NumPy and TensorFlow are in tests/inference/test_onnx_export.py; here: that tf2onnx
    # still calls the handlers and that they write the ops they promise.
    import tf2onnx

    @tf.function
    def fn(values, ids):
        summed = tf.math.unsorted_segment_sum(values, ids, 3)
        return tf.where(tf.math.is_finite(summed), summed, tf.zeros_like(summed))

    proto, _ = tf2onnx.convert.from_function(
        fn, input_signature=[tf.TensorSpec([None, 2], tf.float32), tf.TensorSpec([None], tf.int32)], opset=17,
        custom_op_handlers=internals.tf2onnx_custom_op_handlers())
    nodes = {n.op_type: n for n in proto.graph.node}
    assert "ScatterElements" in nodes and "Where" in nodes and "UnsortedSegmentSum" not in nodes
    assert {a.name: a.s for a in nodes["ScatterElements"].attribute}.get("reduction") == b"add"


def test_onednn_enabled_follows_tensorflows_switch():
    """TensorFlow decides at start; a child process per setting (this process's TensorFlow is already started)."""
    code = "from ff3d_tf import internals; print(internals.onednn_enabled())"
    seen = {}
    for value in ("0", "1"):
        env = {**os.environ, "TF_ENABLE_ONEDNN_OPTS": value, "TF_CPP_MIN_LOG_LEVEL": "3"}
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                             check=True)
        seen[value] = out.stdout.strip().splitlines()[-1]
    assert seen == {"0": "False", "1": "True"}
