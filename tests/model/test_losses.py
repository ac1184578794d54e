import numpy as np
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
