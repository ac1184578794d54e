"""Training losses. Human labels (paper Sec. 4 and appendix): mean L2 error over labelled points, background weighted
0.1. Pseudo-labels (ZeroFlow, Vedder et al., ICLR 2024): mean L2 error over every point, each scaled by its
pseudo-label speed (`speed_scale`)."""
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


# ZeroFlow's "fast mover" scale: 0.1 below 0.5 m/s, 1 above 1 m/s, linear between: max(0.1, min(1, 1.8 s - 0.8)) with
# s the pseudo-label speed in m/s. The authors' code (kylevedder/zeroflow, models/fast_flow_3d.py,
# FastFlow3DDistillationLoss) computes s in m/s from flow per 0.1 s frame, and writes min(0.1, max(1.8 s - 0.8, 1)),
# which is 0.1 for every point (the known bug); this is the formula its comment and the paper describe.
SPEED_SCALE_MIN, SPEED_SCALE_SLOPE_PER_MPS, SPEED_SCALE_OFFSET = 0.1, 1.8, 0.8


def speed_scale(flow_mps):
    """[...]: ZeroFlow's per-point loss scale from the pseudo-label flow [..., 3] in m/s."""
    speed_mps = tf.norm(flow_mps, axis=-1)
    return tf.clip_by_value(SPEED_SCALE_SLOPE_PER_MPS * speed_mps - SPEED_SCALE_OFFSET, SPEED_SCALE_MIN, 1.0)


def per_sample_distillation_loss(flow_pseudo_mps, flow_pred_mps, point_valid):
    """[B] loss: mean over the valid points of `speed_scale(pseudo) * ||pred - pseudo||_2` (ZeroFlow); 0 for a
    sample without valid points. Every point counts: pseudo-labels have no class."""
    w = tf.where(point_valid, speed_scale(flow_pseudo_mps), 0.0)
    l2 = tf.sqrt(tf.reduce_sum(tf.square(tf.cast(flow_pred_mps, tf.float32) - flow_pseudo_mps), -1) + 1e-12)
    count = tf.reduce_sum(tf.cast(point_valid, tf.float32), -1)
    return tf.reduce_sum(w * l2, -1) / tf.maximum(count, 1.0)


def batch_flow_loss(batch, outputs, background_weight: float, global_batch_size: int, pseudo_labels: bool = False):
    """One replica's training loss: `per_sample_flow_loss` (or, for `pseudo_labels`,
    `per_sample_distillation_loss`) over the points that are real (`point_mask_t0`) and valid for the model, summed
    over the batch and divided by the global batch (`tf.nn.compute_average_loss`).

    batch: flow_mps_t0 [B,N,3] (the pseudo-labels when training on them), class_id_t0 [B,N], point_mask_t0 [B,N];
    with pseudo-labels, optionally pseudo_valid_t0 [B,N] (points without a pseudo-label do not count);
    outputs: the model's flow_mps, point_valid.
    """
    valid = outputs["point_valid"] & batch["point_mask_t0"]
    if pseudo_labels:
        if schema.PSEUDO_VALID_KEY in batch:
            valid &= batch[schema.PSEUDO_VALID_KEY]
        per_sample = per_sample_distillation_loss(batch["flow_mps_t0"], outputs["flow_mps"], valid)
    else:
        per_sample = per_sample_flow_loss(batch["flow_mps_t0"], outputs["flow_mps"], batch["class_id_t0"], valid,
                                          background_weight)
    return tf.nn.compute_average_loss(per_sample, global_batch_size=global_batch_size)
