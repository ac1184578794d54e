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
