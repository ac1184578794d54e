"""The training step (`ff3d_tf.model.step`): its Adam is Keras' Adam, clipping, the non-finite skip, and a stateless
step of the tiny model equals the same step computed by hand with the model's own variables and Keras' optimizer."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import internals
from ff3d_tf.config import replace_config
from ff3d_tf.model import step as step_lib

SHAPES = [(3, 4), (4,), (2, 1, 3)]


def _cfg(tiny_config, **train):
    return replace_config(tiny_config, {f"train.{k}": v for k, v in train.items()})


def _state(rng, num_stats=2):
    """A TrainState of random values (slots as after some steps), iterations 0."""
    def values(scale=1.0, positive=False):
        return [tf.constant((np.abs(a) if positive else a) * scale)
                for a in (rng.standard_normal(s).astype(np.float32) for s in SHAPES)]
    stats = [tf.constant(rng.standard_normal(4).astype(np.float32)) for _ in range(num_stats)]
    return step_lib.TrainState(values(), stats, values(0.1), values(0.01, positive=True), tf.constant(0, tf.int64))


def _grads(rng, scale=1.0):
    return [tf.constant(rng.standard_normal(s).astype(np.float32) * scale) for s in SHAPES]


def _assert_states_equal(a: step_lib.TrainState, b: step_lib.TrainState):
    for x, y in zip(tf.nest.flatten(a), tf.nest.flatten(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("schedule", [{"lr_schedule": "cosine", "warmup_steps": 1, "num_steps": 6},
                                      {"lr_schedule": "constant"}])
def test_adam_update_equals_keras_adam(tiny_config, schedule):
    """Three updates of a few weights: the written-out Adam against `keras.optimizers.Adam.apply_gradients`."""
    cfg = _cfg(tiny_config, learning_rate=1e-2, **schedule)
    rng = np.random.default_rng(0)
    state = _state(rng)._replace(adam_m=[tf.zeros(s) for s in SHAPES], adam_v=[tf.zeros(s) for s in SHAPES])
    weights = [tf.Variable(w) for w in state.weights]
    optimizer = step_lib.make_optimizer(cfg)
    optimizer.build(weights)
    for _ in range(3):
        grads = _grads(rng)
        optimizer.apply_gradients(zip(grads, weights))
        state = step_lib.adam_update(cfg, state, grads)
    momentums, velocities = internals.adam_slots(optimizer)
    keras_state = step_lib.TrainState(weights, state.bn_statistics, momentums, velocities, optimizer.iterations)
    _assert_states_equal(state, keras_state)
    assert int(state.iterations) == 3


def _numpy_adam(w, g, m, v, t, lr, b1, b2, eps):
    """Adam (Kingma and Ba, Algorithm 1) in float64 with Keras' placement of epsilon (outside the bias correction of
    v): m_t = b1 m + (1 - b1) g, v_t = b2 v + (1 - b2) g^2, w -= lr sqrt(1 - b2^t) / (1 - b1^t) m_t / (sqrt(v_t) + eps)."""
    m = b1 * m + (1 - b1) * g
    v = b2 * v + (1 - b2) * g * g
    return w - lr * np.sqrt(1 - b2 ** t) / (1 - b1 ** t) * m / (np.sqrt(v) + eps), m, v


@pytest.mark.parametrize("compiled", [False, True])
def test_adam_apply_equals_numpy_adam(compiled):
    """Five updates of three tensors, starting at step 7 with non-zero slots: the per-tensor Adam against NumPy;
    compiled: inside one XLA program, with the step and learning rate as tensors."""
    rng = np.random.default_rng(3)
    lr, b1, b2, eps = 3e-3, 0.85, 0.99, 1e-6
    w = [rng.standard_normal(s) for s in SHAPES]
    w_start = [a.copy() for a in w]
    m = [0.1 * rng.standard_normal(s) for s in SHAPES]
    v = [0.01 * np.abs(rng.standard_normal(s)) for s in SHAPES]
    params, slots_m, slots_v = ([tf.constant(a, tf.float32) for a in arrays] for arrays in (w, m, v))
    apply = step_lib.adam_apply
    if compiled:
        apply = tf.function(step_lib.adam_apply, jit_compile=True)
    for k in range(5):
        g = [rng.standard_normal(s) for s in SHAPES]
        params, slots_m, slots_v = apply(params, [tf.constant(a, tf.float32) for a in g], slots_m, slots_v,
                                         tf.constant(7 + k), tf.constant(lr) if compiled else lr, b1, b2, eps)
        w, m, v = map(list, zip(*(_numpy_adam(*x, t=8 + k, lr=lr, b1=b1, b2=b2, eps=eps) for x in zip(w, g, m, v))))
    for got, want in zip(params + slots_m + slots_v, w + m + v):
        np.testing.assert_allclose(np.asarray(got), want, rtol=2e-5, atol=1e-7)
    moved = max(np.abs(a - b).max() for a, b in zip(w, w_start))
    assert moved > 1e-3, moved  # the updates moved the weights far beyond the comparison's tolerance


def _fixed_loss_and_grads(loss, grads, new_bn_statistics):
    return lambda weights, bn_statistics, batch: (tf.constant(loss), grads, new_bn_statistics)


def test_step_reduces_then_clips_then_updates(tiny_config):
    """The all_reduce hook's gradients are the ones clipped (to `train.grad_clip_norm`) and applied; grad_norm is
    their norm before clipping."""
    cfg = _cfg(tiny_config, grad_clip_norm=0.5)
    rng = np.random.default_rng(1)
    state, grads = _state(rng), _grads(rng, scale=10.0)
    new_stats = [s + 1.0 for s in state.bn_statistics]

    def two_replicas(loss, grads, new_bn_statistics):
        return 2.0 * loss, [2.0 * g for g in grads], new_bn_statistics
    result = step_lib.train_step_fn(cfg, _fixed_loss_and_grads(3.0, grads, new_stats), all_reduce=two_replicas)(
        state, {})
    summed = [2.0 * g for g in grads]
    clipped, norm = tf.clip_by_global_norm(summed, 0.5)
    assert bool(result.finite) and float(result.loss) == 6.0
    np.testing.assert_allclose(float(result.grad_norm), float(norm), rtol=1e-6)
    np.testing.assert_allclose(float(tf.linalg.global_norm(clipped)), 0.5, rtol=1e-6)
    _assert_states_equal(result.state, step_lib.adam_update(cfg, state._replace(bn_statistics=new_stats), clipped))


@pytest.mark.parametrize("bad", ["loss", "grads"])
def test_nonfinite_step_changes_nothing(tiny_config, bad):
    """A NaN loss or an infinite gradient: weights, BatchNorm statistics (though the forward moved them), Adam's slots
    and iteration count all stay as they were."""
    cfg = _cfg(tiny_config, grad_clip_norm=1.0)
    rng = np.random.default_rng(2)
    state, grads = _state(rng), _grads(rng)
    if bad == "grads":
        grads[1] = tf.tensor_scatter_nd_update(grads[1], [[2]], [np.inf])
    loss = np.nan if bad == "loss" else 1.0
    new_stats = [s + 1.0 for s in state.bn_statistics]
    result = step_lib.train_step_fn(cfg, _fixed_loss_and_grads(loss, grads, new_stats))(state, {})
    assert not bool(result.finite)
    _assert_states_equal(result.state, state)


def test_stateless_step_of_the_tiny_model_equals_keras_training(tiny_segment, tiny_config):
    """One step of the tiny model on a real batch, stateless and on the model's variables, against a tape over
    `model(..., training=True)`, `batch_flow_loss` and Keras' Adam; the stateless step leaves every variable as it
    was."""
    from ff3d_tf.data import pairs
    from ff3d_tf.model import build_model
    from ff3d_tf.model.forward import model_inputs
    from ff3d_tf.model.losses import batch_flow_loss
    cfg = _cfg(tiny_config, learning_rate=1e-2)
    batch = next(iter(pairs.batch_examples(pairs.pair_dataset([tiny_segment], cfg), 2, cfg.data.point_bucket_base)))
    model, manual = build_model(cfg, compile_mode="none"), build_model(cfg, compile_mode="none")
    manual.set_weights(model.get_weights())
    variables_before = [v.numpy().copy() for v in model.variables]
    state = step_lib.TrainState([tf.constant(v.numpy()) for v in model.trainable_variables],
                                [tf.constant(v.numpy()) for v in model.non_trainable_variables],
                                [tf.zeros(v.shape) for v in model.trainable_variables],
                                [tf.zeros(v.shape) for v in model.trainable_variables], tf.constant(0, tf.int64))
    result = step_lib.train_step_fn(cfg, step_lib.loss_and_grads_fn(cfg, model, 2))(state, batch)
    for before, v in zip(variables_before, model.variables):
        np.testing.assert_array_equal(before, v.numpy())

    optimizer = step_lib.make_optimizer(cfg)
    with tf.GradientTape() as tape:
        loss = batch_flow_loss(batch, manual(model_inputs(batch), training=True), cfg.train.background_weight, 2)
    grads = tape.gradient(loss, manual.trainable_variables)
    optimizer.apply_gradients(zip(grads, manual.trainable_variables))
    momentums, velocities = internals.adam_slots(optimizer)
    expected = step_lib.TrainState(manual.trainable_variables, manual.non_trainable_variables, momentums, velocities,
                                   optimizer.iterations)
    assert bool(result.finite) and float(result.loss) == float(loss) and float(loss) > 0
    np.testing.assert_allclose(float(result.grad_norm), float(tf.linalg.global_norm(grads)), rtol=1e-6)
    _assert_states_equal(result.state, expected)

    on_variables = step_lib.loss_and_grads_fn(cfg, model, 2, on_variables=True)
    loss_v, grads_v, stats_v = on_variables(state.weights, state.bn_statistics, batch)
    assert float(loss_v) == float(loss)
    for a, b in zip(grads_v + stats_v, grads + manual.non_trainable_variables):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
