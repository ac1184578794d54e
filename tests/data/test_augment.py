"""Training augmentation (`ff3d_tf.data.augment`): the label moves with the points, a seed fixes the draw, probability
0 changes nothing, and the training input applies it (and only it: evaluation reads the recorded clouds)."""
import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import replace_config
from ff3d_tf.data import augment

DT_S = 0.1
ULP_20M = 4e-6  # float32 rounding of a coordinate up to 20 m (2 ulp), in an offset read back as a difference


def _rigid_pair(seed=0, n=50):
    """A pair whose t-1 cloud is the t0 cloud moved back by a rigid translation: flow = translation / dt."""
    rng = np.random.default_rng(seed)
    points_t0 = rng.uniform(-20, 20, (n, 3)).astype(np.float32)
    velocity_mps = np.array([3.0, -1.5, 0.25], np.float32)
    return {"points_xyz_t0": tf.constant(points_t0),
            "points_xyz_tm1_in_t0": tf.constant(points_t0 - velocity_mps * DT_S),
            "flow_mps_t0": tf.constant(np.tile(velocity_mps, (n, 1))),
            schema.PSEUDO_FLOW_KEY: tf.constant(np.tile(velocity_mps, (n, 1))),
            "class_id_t0": tf.constant(rng.integers(-1, 5, n).astype(np.int32)),
            "point_features_t0": tf.constant(rng.uniform(0, 1, (n, 2)).astype(np.float32))}


def _numpy(ex):
    return {k: v.numpy() for k, v in ex.items()}


def test_every_position_and_flow_key_is_handled():
    # A new [N,3] key of the schema must say whether it is a position or a flow (or the augmentation misses it).
    three = {k for k, spec in schema.POINT_KEYS.items() if spec.tail_shape == (3,)}
    assert three == set(augment.POSITION_KEYS) | set(augment.FLOW_KEYS)


def test_flip_twice_is_the_identity():
    ex = _rigid_pair()
    for flip_x, flip_y in ((True, False), (False, True), (True, True)):
        twice = augment.apply(augment.apply(ex, flip_x, flip_y, 0.0), flip_x, flip_y, 0.0)
        for k, v in _numpy(twice).items():
            np.testing.assert_array_equal(v, ex[k].numpy(), err_msg=k)
    once = _numpy(augment.apply(ex, True, True, 0.0))
    np.testing.assert_array_equal(once["points_xyz_t0"][:, :2], -ex["points_xyz_t0"].numpy()[:, :2])
    np.testing.assert_array_equal(once["flow_mps_t0"][:, 2], ex["flow_mps_t0"].numpy()[:, 2])


def test_the_label_moves_with_the_points():
    # Every combination of flips and an offset: the flow is still (t0 cloud - t-1 cloud) / dt, both flows alike, and
    # what is not a position or a flow is untouched.
    ex = _rigid_pair()
    for flip_x in (False, True):
        for flip_y in (False, True):
            out = _numpy(augment.apply(ex, flip_x, flip_y, 1.25))
            motion_mps = (out["points_xyz_t0"] - out["points_xyz_tm1_in_t0"]) / DT_S
            np.testing.assert_allclose(motion_mps, out["flow_mps_t0"], atol=2e-5)
            np.testing.assert_array_equal(out[schema.PSEUDO_FLOW_KEY], out["flow_mps_t0"])
            sign = np.array([-1 if flip_x else 1, -1 if flip_y else 1, 1], np.float32)
            np.testing.assert_array_equal(out["flow_mps_t0"], ex["flow_mps_t0"].numpy() * sign)
            np.testing.assert_allclose(out["points_xyz_t0"][:, 2], ex["points_xyz_t0"].numpy()[:, 2] + 1.25)
            for k in ("class_id_t0", "point_features_t0"):
                np.testing.assert_array_equal(out[k], ex[k].numpy())


def test_a_seed_fixes_the_draw_and_probability_zero_changes_nothing(tiny_config):
    cfg = replace_config(tiny_config, {"data.augment_height_offset_prob": 0.5, "data.augment_height_offset_m":
                                       [-0.5, 2.0], "data.augment_flip_prob": 0.5})
    ex = _rigid_pair()
    seeds = [tf.constant([0, i], tf.int64) for i in range(16)]
    first = [_numpy(augment.augment_example(ex, cfg.data, s)) for s in seeds]
    again = [_numpy(augment.augment_example(ex, cfg.data, s)) for s in seeds]
    for a, b in zip(first, again):
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
    draws = [tuple(np.asarray(v).item() for v in augment.draw(cfg.data, s)) for s in seeds]
    assert len(set(draws)) > 8  # different seeds, different draws: flips both ways, offsets in range
    assert {d[0] for d in draws} == {True, False} and {d[1] for d in draws} == {True, False}
    offsets = [d[2] for d in draws if d[2] != 0.0]
    assert offsets and all(-0.5 <= o <= 2.0 for o in offsets) and len(offsets) < len(draws)
    # probability 0 (the default): the example as it was, whatever the seed
    assert not augment.is_enabled(tiny_config.data)
    for s in seeds[:4]:
        out = _numpy(augment.augment_example(ex, tiny_config.data, s))
        for k in out:
            np.testing.assert_array_equal(out[k], ex[k].numpy())


def test_jitter_moves_each_point_by_its_own_clipped_draw_and_leaves_the_flow(tiny_config):
    """sigma 0.01 m, clip 0.05 m (the authors' RandomJitter defaults): per-axis offsets with a standard deviation
    near sigma over 4,000 draws (sample sd of N(0, 0.01^2) is within 5% of 0.01 with overwhelming probability), none
    beyond the clip; each cloud gets its own draw; flows unchanged; the same seed the same offsets."""
    cfg = replace_config(tiny_config, {"data.augment_jitter_sigma_m": 0.01, "data.augment_jitter_clip_m": 0.05})
    assert augment.is_enabled(cfg.data)
    ex = _rigid_pair(n=2000)
    seed = tf.constant([3, 4], tf.int64)
    out = _numpy(augment.augment_example(ex, cfg.data, seed))
    moved = {k: out[k] - ex[k].numpy() for k in ("points_xyz_t0", "points_xyz_tm1_in_t0")}
    for offsets in moved.values():
        assert np.abs(offsets).max() <= 0.05 + ULP_20M
        assert abs(offsets.std() - 0.01) < 0.0005
    assert not np.allclose(moved["points_xyz_t0"], moved["points_xyz_tm1_in_t0"])
    np.testing.assert_array_equal(out["flow_mps_t0"], ex["flow_mps_t0"].numpy())
    again = _numpy(augment.augment_example(ex, cfg.data, seed))
    np.testing.assert_array_equal(again["points_xyz_t0"], out["points_xyz_t0"])
    tight = replace_config(cfg, {"data.augment_jitter_clip_m": 0.005})
    assert np.abs(_numpy(augment.augment_example(ex, tight.data, seed))["points_xyz_t0"] -
                  ex["points_xyz_t0"].numpy()).max() <= 0.005 + ULP_20M


def test_the_training_input_augments_reproducibly(tiny_segment, tiny_config):
    from ff3d_tf.training.input import training_dataset

    def first_batches(cfg, count=2):
        return [{k: v.numpy() for k, v in b.items()} for b in training_dataset([tiny_segment], cfg, 2).take(count)]

    plain = first_batches(tiny_config)
    cfg = replace_config(tiny_config, {"data.augment_height_offset_prob": 1.0, "data.augment_flip_prob": 0.5})
    augmented, again = first_batches(cfg), first_batches(cfg)
    for a, b in zip(augmented, again):  # the same seed, the same stream
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    for p, a in zip(plain, augmented):  # the same pairs, moved: the offset changes every cloud's height
        np.testing.assert_array_equal(p["class_id_t0"], a["class_id_t0"])
        real = p["point_mask_t0"]
        assert not np.allclose(p["points_xyz_t0"][real][:, 2], a["points_xyz_t0"][real][:, 2])
        np.testing.assert_allclose(np.abs(p["flow_mps_t0"]), np.abs(a["flow_mps_t0"]))
