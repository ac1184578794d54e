import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.model.losses import per_sample_flow_loss


def test_loss_by_hand():
    # Sample 0: vehicle error (3,4,0) -> 5; background error 1 (weighted 0.1 -> 0.1); class -1 error 10 ignored;
    # invalid vehicle point ignored. Labelled valid points: 2 -> (5 + 0.1) / 2 = 2.55.
    true = tf.constant([[[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]], tf.float32)
    pred = tf.constant([[[3, 4, 0], [1, 0, 0], [10, 0, 0], [7, 0, 0]]], tf.float32)
    cls = tf.constant([[1, 0, -1, 1]])
    valid = tf.constant([[True, True, True, False]])
    loss = per_sample_flow_loss(true, pred, cls, valid, background_weight=0.1).numpy()
    np.testing.assert_allclose(loss, [2.55], rtol=1e-5)
    # A sample without labelled points contributes 0 (and no NaN).
    empty = per_sample_flow_loss(true, pred, tf.constant([[-1, -1, -1, -1]]), valid).numpy()
    assert empty.tolist() == [0.0]


def test_zeroflow_speed_scale_by_hand():
    from ff3d_tf.model.losses import speed_scale
    # max(0.1, min(1, 1.8 s - 0.8)), s in m/s: 0 -> 0.1; 0.5 -> 0.1; 0.75 -> 0.55; 1.0 -> 1.0; 20 -> 1.0.
    flow = tf.constant([[0.0, 0, 0], [0.3, 0.4, 0], [0.75, 0, 0], [0, 0, 1.0], [12, 16, 0]], tf.float32)
    np.testing.assert_allclose(speed_scale(flow).numpy(), [0.1, 0.1, 0.55, 1.0, 1.0], rtol=1e-6)


def test_distillation_loss_by_hand():
    from ff3d_tf.model.losses import batch_flow_loss, per_sample_distillation_loss
    # Pseudo-labels: a fast point (10 m/s, scale 1) predicted 3-4-5 off -> 5; a static point (scale 0.1) predicted
    # 2 m/s off -> 0.2; a padded point ignored. Class ids do not matter (-1 counts too). Mean over 2: 2.6.
    pseudo = tf.constant([[[10.0, 0, 0], [0, 0, 0], [0, 0, 0]]])
    pred = tf.constant([[[13.0, 4, 0], [0, 2, 0], [9, 9, 9]]])
    valid = tf.constant([[True, True, False]])
    np.testing.assert_allclose(per_sample_distillation_loss(pseudo, pred, valid).numpy(), [2.6], rtol=1e-5)
    batch = {"flow_mps_t0": pseudo, "class_id_t0": tf.constant([[-1, -1, -1]]), "point_mask_t0": valid}
    outputs = {"flow_mps": pred, "point_valid": tf.constant([[True, True, True]])}
    # Divided by the global batch of 2; the human-label loss ignores class -1 and gives 0 here.
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, 2, pseudo_labels=True).numpy(), 1.3, rtol=1e-5)
    assert float(batch_flow_loss(batch, outputs, 0.1, 2)) == 0.0
    # A point without a pseudo-label (pseudo_valid_t0 False: outside the fitted region) does not count: only the fast
    # point's 5 remains, mean over 1, over the global batch of 2: 2.5.
    batch["pseudo_valid_t0"] = tf.constant([[True, False, True]])
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, 2, pseudo_labels=True).numpy(), 2.5, rtol=1e-5)


# --- DeFlow and DeltaFlow: NumPy references on hand-made batches ------------------------------------------------------
CLASS_WEIGHTS = (0.1, 1.0, 2.0, 2.5, 1.5)  # DeltaFlow: BACKGROUND, CAR, PEDESTRIAN, WHEELED_VRU, OTHER_VEHICLES
BUCKET_WEIGHTS = (0.1, 0.4, 0.5)  # slow, middle, fast


def _np_buckets(flow_true):
    speed = np.linalg.norm(flow_true.astype(np.float32), axis=-1)
    return speed, (speed < 0.4, (speed >= 0.4) & (speed <= 1.0), speed > 1.0)


def np_deflow(flow_true, flow_pred, valid):
    """One sample: sum over the speed buckets of the mean error (m over a 0.1 s sweep) of its valid points."""
    err = np.linalg.norm(flow_pred - flow_true, axis=-1) * 0.1
    _, buckets = _np_buckets(flow_true)
    return sum(err[m & valid].mean() for m in buckets if (m & valid).any())


def np_deltaflow(flow_true, flow_pred, valid, meta, instance=None):
    """One sample, written as DeltaFlow's paper and code describe it, with loops."""
    err = np.linalg.norm(flow_pred - flow_true, axis=-1) * 0.1
    speed, buckets = _np_buckets(flow_true)
    total = np_deflow(flow_true, flow_pred, valid)
    for c, wc in enumerate(CLASS_WEIGHTS):
        for m, wb in zip(buckets, BUCKET_WEIGHTS):
            sel = m & valid & (meta == c)
            if sel.any():
                total += wc * wb * err[sel].mean()
    if instance is not None:
        terms = []
        for i in np.unique(instance[valid & (instance >= 0)]):
            sel = valid & (instance == i)
            if speed[sel].mean() <= 0.4:
                continue
            e = err[sel].mean()
            terms.append(e * np.exp(e) * CLASS_WEIGHTS[np.bincount(meta[sel], minlength=5).argmax()])
        total += np.mean(terms) if terms else 0.0
    return total


def _hand_batch():
    """Two samples of 8 points. Sample 0: every bucket and four classes, two moving instances (a car, a cyclist), a
    static one (not counted), an unlabelled point (class -1), an invalid point and padding. Sample 1: every point
    static (the middle and fast buckets empty) and no instance."""
    flow_true = np.array([
        [[0, 0, 0], [0.4, 0, 0], [1.0, 0, 0], [8, 0, 0], [8, 6, 0], [0, 3, 0], [0, 3.5, 0], [0, 0, 0]],
        [[0, 0, 0], [0.1, 0, 0], [0, 0.2, 0], [0, 0, 0], [0.3, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]], np.float32)
    flow_pred = flow_true + np.array([
        [[1, 0, 0], [0, 2, 0], [0, 0, -3], [4, 3, 0], [0, 12, 0], [-2, 0, 0], [1, 1, 1], [9, 9, 9]],
        [[0.5, 0, 0], [0, 1, 0], [2, 0, 0], [0, 0, 4], [0, 3, 0], [7, 0, 0], [0, 0, 0], [0, 0, 0]]], np.float32)
    class_id = np.array([[0, 3, 2, 1, 1, 4, 4, -1], [0, 0, 1, 2, 0, -1, -1, -1]], np.int32)
    mask = np.array([[1, 1, 1, 1, 1, 1, 1, 0], [1, 1, 1, 1, 1, 1, 0, 0]], bool)
    point_valid = np.array([[1, 1, 1, 1, 1, 1, 1, 1], [1, 1, 1, 1, 0, 1, 1, 1]], bool)
    instance = np.array([[-1, 5, 2, 0, 0, 3, 3, -1], [-1, -1, 1, 4, -1, -1, -1, -1]], np.int32)
    return flow_true, flow_pred, class_id, mask, point_valid, instance


def _tf_batch(flow_true, class_id, mask, **extras):
    return {"flow_mps_t0": tf.constant(flow_true), "class_id_t0": tf.constant(class_id),
            "point_mask_t0": tf.constant(mask), **{k: tf.constant(v) for k, v in extras.items()}}


def test_deflow_by_hand():
    from ff3d_tf.model.losses import per_sample_deflow_loss
    # Errors 1, 2, 3, 5 m/s -> 0.1, 0.2, 0.3, 0.5 m over a 0.1 s sweep; speeds 0 (slow), 0.5 (middle), 5 and 5
    # (fast): 0.1 + 0.2 + (0.3 + 0.5) / 2 = 0.7. Without the slow and middle points only the fast mean remains.
    true = tf.constant([[[0, 0, 0], [0.5, 0, 0], [5, 0, 0], [0, 5, 0]]], tf.float32)
    pred = true + tf.constant([[[1, 0, 0], [0, 2, 0], [0, 0, 3], [3, 4, 0]]], tf.float32)
    valid = tf.constant([[True, True, True, True]])
    np.testing.assert_allclose(per_sample_deflow_loss(true, pred, valid).numpy(), [0.7], rtol=1e-5)
    only_fast = tf.constant([[False, False, True, True]])
    np.testing.assert_allclose(per_sample_deflow_loss(true, pred, only_fast).numpy(), [0.4], rtol=1e-5)
    assert per_sample_deflow_loss(true, pred, tf.zeros_like(valid)).numpy().tolist() == [0.0]  # no point: 0, no NaN


def test_deflow_and_deltaflow_match_their_numpy_references():
    from ff3d_tf.model.losses import DELTAFLOW_META_OF_PAPER_CLASS, batch_flow_loss
    flow_true, flow_pred, class_id, mask, point_valid, instance = _hand_batch()
    outputs = {"flow_mps": tf.constant(flow_pred), "point_valid": tf.constant(point_valid)}
    labelled = mask & point_valid & (class_id >= 0)
    meta = np.vectorize(lambda c: DELTAFLOW_META_OF_PAPER_CLASS.get(int(c), 0))(class_id)
    # WOD's classes: background 0 and sign 3 -> BACKGROUND, vehicle -> CAR, pedestrian -> PEDESTRIAN, cyclist ->
    # WHEELED_VRU
    assert meta[0].tolist()[:7] == [0, 0, 2, 1, 1, 3, 3]
    deflow = [np_deflow(flow_true[i], flow_pred[i], labelled[i]) for i in range(2)]
    delta = [np_deltaflow(flow_true[i], flow_pred[i], labelled[i], meta[i], instance[i]) for i in range(2)]
    no_instances = [np_deltaflow(flow_true[i], flow_pred[i], labelled[i], meta[i]) for i in range(2)]
    assert delta[0] > no_instances[0] and delta[1] == no_instances[1]  # sample 1's only instance is static
    global_batch = 4  # the batch's sum divided by the global batch
    batch = _tf_batch(flow_true, class_id, mask, instance_id_t0=instance)
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, global_batch, loss="deflow").numpy(),
                               sum(deflow) / global_batch, rtol=1e-5)
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, global_batch, loss="deltaflow").numpy(),
                               sum(delta) / global_batch, rtol=1e-5)
    # Records without instance ids: DeltaFlow without its instance term.
    del batch["instance_id_t0"]
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, global_batch, loss="deltaflow").numpy(),
                               sum(no_instances) / global_batch, rtol=1e-5)


def test_deltaflow_meta_classes_from_argoverse_categories():
    from ff3d_tf import metrics_av2
    from ff3d_tf.model.losses import batch_flow_loss, deltaflow_meta_class
    names = ["NONE", "REGULAR_VEHICLE", "PEDESTRIAN", "BICYCLIST", "BOX_TRUCK", "STOP_SIGN", "DOG", "NONE"]
    category = metrics_av2.label_index(names).astype(np.int32)[None]
    # the category decides, not the paper class; categories in no meta-class (signs, animals) are BACKGROUND
    got = deltaflow_meta_class(tf.zeros([1, 8], tf.int32), tf.constant(category)).numpy()
    assert got.tolist() == [[0, 1, 2, 3, 4, 0, 0, 0]]
    assert deltaflow_meta_class(tf.constant([[-1, 0, 1, 2, 3, 4, 9]])).numpy().tolist() == [[0, 0, 1, 2, 0, 3, 0]]
    flow_true, flow_pred, class_id, mask, point_valid, instance = _hand_batch()
    outputs = {"flow_mps": tf.constant(flow_pred), "point_valid": tf.constant(point_valid)}
    labelled = mask & point_valid & (class_id >= 0)
    categories = np.concatenate([category, category], 0)
    batch = _tf_batch(flow_true, class_id, mask, instance_id_t0=instance, category_t0=categories)
    meta = got.repeat(2, 0)
    want = sum(np_deltaflow(flow_true[i], flow_pred[i], labelled[i], meta[i], instance[i]) for i in range(2))
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, 2, loss="deltaflow").numpy(), want / 2,
                               rtol=1e-5)


def test_instance_term_by_hand_and_empty_cases():
    from ff3d_tf.model.losses import per_sample_instance_loss
    # Two moving instances: a car (mean speed 5 m/s, mean error 0.2 m) and a pedestrian (1 m/s, error 0.1 m); a
    # static instance (0.3 m/s) does not count: (0.2 e^0.2 * 1.0 + 0.1 e^0.1 * 2.0) / 2.
    err = tf.constant([[0.1, 0.3, 0.1, 5.0, 9.0]])
    flow = tf.constant([[[5, 0, 0], [5, 0, 0], [0, 1, 0], [0.3, 0, 0], [9, 9, 9]]], tf.float32)
    meta = tf.constant([[1, 1, 2, 1, 1]])
    ids = tf.constant([[0, 0, 2, 3, -1]])
    valid = tf.constant([[True, True, True, True, True]])
    want = (0.2 * np.exp(0.2) * 1.0 + 0.1 * np.exp(0.1) * 2.0) / 2
    np.testing.assert_allclose(per_sample_instance_loss(err, flow, valid, meta, ids).numpy(), [want], rtol=1e-5)
    # no moving instance, no instance at all: 0 (no NaN); an id >= N never counts
    np.testing.assert_allclose(per_sample_instance_loss(err, flow * 0, valid, meta, ids).numpy(), [0.0])
    np.testing.assert_allclose(per_sample_instance_loss(err, flow, valid, meta, -tf.ones_like(ids)).numpy(), [0.0])
    beyond = tf.where(ids >= 0, ids + 5, -1)
    np.testing.assert_allclose(per_sample_instance_loss(err, flow, valid, meta, beyond).numpy(), [0.0])


def test_new_losses_compile_with_xla_and_have_finite_gradients():
    from ff3d_tf.model.losses import batch_flow_loss
    flow_true, flow_pred, class_id, mask, point_valid, instance = _hand_batch()
    batch = _tf_batch(flow_true, class_id, mask, instance_id_t0=instance)
    pred = tf.Variable(flow_pred)

    def loss_and_grad(name):
        with tf.GradientTape() as tape:
            loss = batch_flow_loss(batch, {"flow_mps": pred, "point_valid": tf.constant(point_valid)}, 0.1, 2,
                                   loss=name)
        return loss, tape.gradient(loss, pred)

    for name in ("deflow", "deltaflow"):
        eager_loss, eager_grad = loss_and_grad(name)
        xla_loss, xla_grad = tf.function(lambda n=name: loss_and_grad(n), jit_compile=True)()
        np.testing.assert_allclose(xla_loss.numpy(), eager_loss.numpy(), rtol=1e-5)
        np.testing.assert_allclose(xla_grad.numpy(), eager_grad.numpy(), rtol=1e-4, atol=1e-7)
        assert np.isfinite(eager_grad.numpy()).all() and np.abs(eager_grad.numpy()).sum() > 0
        # padding, invalid and unlabelled points get no gradient
        ignored = ~(mask & point_valid & (class_id >= 0))
        assert np.all(eager_grad.numpy()[ignored] == 0)


def test_pseudo_labels_take_deflow_but_not_deltaflow():
    from ff3d_tf.model.losses import batch_flow_loss
    # Pseudo-labels have no classes: deflow counts every point with a pseudo-label (class -1 included).
    pseudo = np.array([[[0, 0, 0], [5, 0, 0], [0, 0, 0]]], np.float32)
    pred = pseudo + np.array([[[1, 0, 0], [0, 3, 0], [9, 9, 9]]], np.float32)
    batch = _tf_batch(pseudo, np.array([[-1, -1, -1]], np.int32), np.array([[True, True, True]]),
                      pseudo_valid_t0=np.array([[True, True, False]]))
    outputs = {"flow_mps": tf.constant(pred), "point_valid": tf.constant([[True, True, True]])}
    np.testing.assert_allclose(batch_flow_loss(batch, outputs, 0.1, 1, pseudo_labels=True, loss="deflow").numpy(),
                               0.1 + 0.3, rtol=1e-5)
    with pytest.raises(ValueError, match="human labels"):
        batch_flow_loss(batch, outputs, 0.1, 1, pseudo_labels=True, loss="deltaflow")
