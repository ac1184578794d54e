"""Training loss (paper Sec. 4 and appendix): mean L2 error over labelled points, background weighted 0.1."""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf import schema


def point_weights(class_id, point_valid, background_weight: float = 0.1):
    """Per-point loss weight [B,N]: 0 for class -1 or invalid points, `background_weight` for class 0, 1 otherwise."""
    w = tf.where(class_id == schema.CLASS_BACKGROUND, background_weight, 1.0)
    keep = tf.logical_and(point_valid, class_id >= 0)
    return tf.where(keep, w, 0.0)


def per_sample_flow_loss(flow_true_mps, flow_pred_mps, class_id, point_valid, background_weight: float = 0.1):
    """[B] loss: sum_i w_i * ||pred_i - true_i||_2 / (number of labelled valid points of the sample).

    flow_* [B,N,3] m/s; class_id [B,N] int32; point_valid [B,N] bool (model output AND real point). A sample with no
    labelled point contributes 0.
    """
    w = point_weights(class_id, point_valid, background_weight)
    sq = tf.reduce_sum(tf.square(tf.cast(flow_pred_mps, tf.float32) - flow_true_mps), -1)
    l2 = tf.sqrt(sq + 1e-12)  # eps keeps the gradient finite at a perfect prediction
    labelled = tf.reduce_sum(tf.cast(w > 0, tf.float32), -1)
    return tf.reduce_sum(w * l2, -1) / tf.maximum(labelled, 1.0)


def batch_flow_loss(batch, outputs, background_weight: float, global_batch_size: int):
    """One replica's training loss: `per_sample_flow_loss` over the points that are real (`point_mask_t0`) and valid
    for the model, summed over the batch and divided by the global batch (`tf.nn.compute_average_loss`).

    batch: flow_mps_t0 [B,N,3], class_id_t0 [B,N], point_mask_t0 [B,N]; outputs: the model's flow_mps, point_valid.
    """
    valid = outputs["point_valid"] & batch["point_mask_t0"]
    per_sample = per_sample_flow_loss(batch["flow_mps_t0"], outputs["flow_mps"], batch["class_id_t0"], valid,
                                      background_weight)
    return tf.nn.compute_average_loss(per_sample, global_batch_size=global_batch_size)
