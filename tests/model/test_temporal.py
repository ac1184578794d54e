"""The sweeps' meeting in the U-Net (`model.temporal`): DeltaFlow's decayed difference by hand, `stack` of two sweeps
is the paper's pair (same weights, same flow), both forwards agree for every variant and head, and a training step
reaches every weight."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import HEADS, replace_config
from ff3d_tf.model.fastflow3d import build_model

VARIANTS = (("stack", 3), ("delta", 3), ("delta", 5))


def _config(tiny_config, temporal, num_frames, **changes):
    return replace_config(tiny_config, {"model.temporal": temporal, "data.num_frames": num_frames, **changes})


def _inputs(num_frames, seed=0, n=200):
    rng = np.random.default_rng(seed)
    out = {}
    for cloud in schema.sweep_clouds(num_frames):
        keys = schema.cloud_keys(cloud)
        out[keys["xyz"]] = tf.constant(rng.uniform([-39, -39, -1], [39, 39, 2], (1, n, 3)), tf.float32)
        out[keys["features"]] = tf.constant(rng.uniform(0, 1, (1, n, 2)), tf.float32)
        out[keys["mask"]] = tf.constant(np.arange(n)[None] < n - 17)
    return out


def _delta(model, grids, points_per_cell=1):
    """The delta fusion's U-Net input of pillar sums on 1 x 1 x W grids of one channel, each cell holding
    `points_per_cell` valid points (so its mean is its sum divided by that)."""
    cells = grids[0].shape[2]
    ids = tf.constant(np.repeat(np.arange(cells, dtype=np.int32), points_per_cell)[None])
    valid = tf.ones_like(ids, tf.bool)
    bev, _ = model.fusion.encode(model, grids, [ids] * len(grids), [valid] * len(grids), for_head=False)
    return bev.numpy().ravel()


def test_delta_by_hand(tiny_config):
    """The delta fusion's input on 1 x 1 x 2 grids of one channel, one point a cell (means = sums). N = 2: the one term, grid_t0 - grid_tm1 (decay^0, divided by
    1). N = 3, decay 0.4: ((g0 - g1) + 0.4 (g0 - g2)) / 2."""
    g0, g1, g2 = (tf.constant(np.array(v, np.float32).reshape(1, 1, 2, 1)) for v in ([5, 1], [2, 3], [1, -4]))
    two = build_model(_config(tiny_config, "delta", 2), compile_mode="none")
    np.testing.assert_allclose(_delta(two, [g0, g1]), [3, -2])  # 5 - 2, 1 - 3
    three = build_model(_config(tiny_config, "delta", 3, **{"model.temporal_decay": 0.4}), compile_mode="none")
    # cell 0: ((5 - 2) + 0.4 (5 - 1)) / 2 = (3 + 1.6) / 2 = 2.3; cell 1: ((1 - 3) + 0.4 (1 + 4)) / 2 = 0 / 2 = 0
    np.testing.assert_allclose(_delta(three, [g0, g1, g2]), [2.3, 0.0], atol=1e-6)


def test_delta_by_hand_with_the_next_sweep_as_partner(tiny_config):
    """Argoverse 2 records hold t0, t+1, t-1 (slots 0, 1, 2): the difference is taken from the newest sweep, t+1
    (slot 1), the others ranked by recency (t0, then t-1). N = 3, decay 0.4: ((g1 - g0) + 0.4 (g1 - g2)) / 2."""
    g0, g1, g2 = (tf.constant(np.array(v, np.float32).reshape(1, 1, 2, 1)) for v in ([5, 1], [2, 3], [1, -4]))
    three = build_model(_config(tiny_config, "delta", 3, **{"model.temporal_decay": 0.4, "data.partner": "next"}),
                        compile_mode="none")
    # cell 0: ((2 - 5) + 0.4 (2 - 1)) / 2 = (-3 + 0.4) / 2 = -1.3; cell 1: ((3 - 1) + 0.4 (3 + 4)) / 2 = 4.8 / 2 = 2.4
    np.testing.assert_allclose(_delta(three, [g0, g1, g2]), [-1.3, 2.4], atol=1e-6)


def test_delta_differences_pillar_means(tiny_config):
    """Each sweep's grid enters as its pillar means (sums over the valid points' count): two points a cell halve the
    difference of the same sums, and a pillar that gains a point but keeps its mean differs by nothing."""
    g0, g1 = (tf.constant(np.array(v, np.float32).reshape(1, 1, 2, 1)) for v in ([5, 1], [2, 3]))
    two = build_model(_config(tiny_config, "delta", 2), compile_mode="none")
    np.testing.assert_allclose(_delta(two, [g0, g1], points_per_cell=2), [1.5, -1.0])  # (5 - 2) / 2, (1 - 3) / 2
    # Cell 0: 1 point of feature 4 at t0, 2 points of feature 4 (sum 8) at t-1: means 4 and 4, difference 0.
    ids_t0, ids_tm1 = tf.constant([[0]]), tf.constant([[0, 0]])
    sums_t0 = tf.constant(np.array([4, 0], np.float32).reshape(1, 1, 2, 1))
    sums_tm1 = tf.constant(np.array([8, 0], np.float32).reshape(1, 1, 2, 1))
    bev, _ = two.fusion.encode(two, [sums_t0, sums_tm1], [ids_t0, ids_tm1],
                               [tf.ones_like(ids_t0, tf.bool), tf.ones_like(ids_tm1, tf.bool)], for_head=False)
    np.testing.assert_allclose(bev.numpy().ravel(), [0, 0])


@pytest.mark.parametrize("partner", schema.PARTNERS)
def test_delta_of_a_constant_velocity_object_points_one_way_whatever_the_partner(tiny_config, partner):
    """One occupied cell per sweep on a 1 x 8 grid, the object one cell further (+x) each sweep, 5 sweeps. With either
    partner the newest sweep's cell is the only positive one and the trail lies behind it, each older sweep's cell
    weighted by the next power of the decay: every term of the sum points the same way (the authors' construction,
    mirrored for no record direction). By hand, decay 0.4, sum divided by 4:
    newest cell (1 + 0.4 + 0.16 + 0.064) / 4 = 0.406; then -1/4, -0.4/4, -0.16/4, -0.064/4 going back."""
    times = {"previous": (0, -1, -2, -3, -4), "next": (0, 1, -1, -2, -3)}[partner]  # sweep time of slots 0..4
    cell_of_newest = 4

    def grid(time):
        g = np.zeros((1, 1, 8, 1), np.float32)
        g[0, 0, cell_of_newest + time - max(times), 0] = 1.0
        return tf.constant(g)
    model = build_model(_config(tiny_config, "delta", 5, **{"model.temporal_decay": 0.4, "data.partner": partner}),
                        compile_mode="none")
    delta = _delta(model, [grid(t) for t in times])
    np.testing.assert_allclose(delta, [-0.016, -0.04, -0.1, -0.25, 0.406, 0, 0, 0], atol=1e-6)


@pytest.mark.parametrize("head", HEADS)
def test_stack_of_two_sweeps_is_the_pair(tiny_config, head):
    pair = build_model(replace_config(tiny_config, {"model.head": head}), compile_mode="none")
    stack = build_model(_config(tiny_config, "stack", 2, **{"model.head": head}), compile_mode="none")
    assert [v.shape for v in pair.weights] == [v.shape for v in stack.weights]
    stack.set_weights(pair.get_weights())
    x = _inputs(2)
    np.testing.assert_array_equal(stack(x)["flow_mps"].numpy(), pair(x)["flow_mps"].numpy())


@pytest.mark.parametrize("head", HEADS)
@pytest.mark.parametrize("temporal,num_frames", VARIANTS)
def test_fused_forward_equals_the_table(tiny_config, head, temporal, num_frames):
    cfg = _config(tiny_config, temporal, num_frames, **{"model.head": head})
    fused = build_model(cfg, compile_mode="none")
    table = build_model(replace_config(cfg, {"model.forward": "table"}), compile_mode="none")
    table.set_weights(fused.get_weights())
    x = _inputs(num_frames, seed=1)
    a, b = fused(x)["flow_mps"].numpy(), table(x)["flow_mps"].numpy()
    assert np.abs(a).max() > 0
    np.testing.assert_allclose(a, b, atol=1e-4 * np.abs(b).max())


def test_the_past_sweeps_change_the_flow_and_delta_width_does_not_grow(tiny_config):
    """The older sweeps are read (moving one changes the flow), and delta's weights are the same at N = 3 and 5."""
    model = build_model(_config(tiny_config, "delta", 3), compile_mode="none")
    x = _inputs(3, seed=2)
    moved = dict(x, points_xyz_tm2_in_t0=x["points_xyz_tm2_in_t0"] + [3.0, 0.0, 0.0])
    assert np.abs(model(x)["flow_mps"].numpy() - model(moved)["flow_mps"].numpy()).max() > 1e-4
    five = build_model(_config(tiny_config, "delta", 5), compile_mode="none")
    assert [v.shape for v in model.weights] == [v.shape for v in five.weights]
    pair = build_model(tiny_config, compile_mode="none")
    stack = build_model(_config(tiny_config, "stack", 3), compile_mode="none")
    assert model.count_params() < pair.count_params() < stack.count_params()


@pytest.mark.parametrize("compile_mode", ["none", "xla"])
def test_a_training_step_reaches_every_weight(tiny_config, compile_mode):
    cfg = _config(tiny_config, "delta", 3)
    model = build_model(cfg, compile_mode=compile_mode, job="train")
    x = _inputs(3, seed=3)
    flow_true = tf.constant(np.random.default_rng(4).normal(size=(1, 200, 3)), tf.float32)

    @tf.function(jit_compile=compile_mode == "xla")
    def grads():
        with tf.GradientTape() as tape:
            loss = tf.reduce_mean(tf.square(model(x, training=True, inline_stages=compile_mode == "xla")["flow_mps"]
                                            - flow_true))
        return loss, tape.gradient(loss, model.trainable_variables)
    loss, g = grads()
    assert np.isfinite(float(loss))
    assert [v.path for v, d in zip(model.trainable_variables, g) if d is None or not np.any(d.numpy())] == []
