"""Training losses (`train.loss`). l2, human labels (paper Sec. 4 and appendix): mean L2 error over labelled points,
background weighted 0.1; pseudo-labels (ZeroFlow, Vedder et al., ICLR 2024): mean L2 error over every point, each
scaled by its pseudo-label speed (`speed_scale`). deflow: DeFlow's speed-bucketed mean (Zhang et al., ICRA 2024);
deltaflow: that plus DeltaFlow's class- and instance-balanced terms (Zhang et al., arXiv 2508.17054). See the
section "DeFlow's and DeltaFlow's losses" below for their constants and sources. seflow, teflow: without flow labels
(`ff3d_tf.model.selfsup_losses`). Which labels and fields each reads: `ff3d_tf.config.LOSS_SPECS`; the function of
each name: `LOSS_FUNCTIONS`."""
from __future__ import annotations

import dataclasses

import numpy as np
import tensorflow as tf

from ff3d_tf import metrics_av2, schema
from ff3d_tf.config import LOSS_SPECS, SelfSupConfig
from ff3d_tf.model import selfsup_losses


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


@dataclasses.dataclass(frozen=True)
class LossContext:
    """What a loss reads of the config beside the batch: the labels it trains on (`data.labels`), the background
    weight (`train.background_weight`), the self-supervision's weights (`selfsup`) and the partner sweep
    (`data.partner`, None: "previous")."""
    labels: str = "human"
    background_weight: float = 0.1
    selfsup: SelfSupConfig = SelfSupConfig()
    partner: str | None = None

    @classmethod
    def of(cls, cfg) -> "LossContext":
        """The context of an ExperimentConfig."""
        return cls(cfg.data.labels, cfg.train.background_weight, cfg.selfsup, getattr(cfg.data, "partner", None))


def _l2_loss(batch, outputs, valid, context: LossContext):
    if context.labels == "pseudo":
        return per_sample_distillation_loss(batch["flow_mps_t0"], outputs["flow_mps"], valid)
    return per_sample_flow_loss(batch["flow_mps_t0"], outputs["flow_mps"], batch["class_id_t0"], valid,
                                context.background_weight)


def _deflow_loss(batch, outputs, valid, context: LossContext):
    if context.labels != "pseudo":
        valid &= batch["class_id_t0"] >= 0  # unlabelled points (class -1) carry no label
    return per_sample_deflow_loss(batch["flow_mps_t0"], outputs["flow_mps"], valid)


def _deltaflow_loss(batch, outputs, valid, context: LossContext):
    valid &= batch["class_id_t0"] >= 0
    meta_class = deltaflow_meta_class(batch["class_id_t0"], batch.get("category_t0"))
    return per_sample_deltaflow_loss(batch["flow_mps_t0"], outputs["flow_mps"], valid, meta_class,
                                     batch.get("instance_id_t0"))


def _seflow_loss(batch, outputs, valid, context: LossContext):
    return selfsup_losses.per_sample_self_supervised_loss(batch, {**outputs, "point_valid": valid}, context.selfsup,
                                                          context.partner, temporal=False)


def _teflow_loss(batch, outputs, valid, context: LossContext):
    return selfsup_losses.per_sample_self_supervised_loss(batch, {**outputs, "point_valid": valid}, context.selfsup,
                                                          context.partner, temporal=True)


# train.loss -> fn(batch, outputs, valid [B,N] bool, LossContext) -> [B]: one per name of `config.LOSS_SPECS`, which
# says which labels each trains on and which fields of the batch it reads (tests/model/test_losses.py ties the two).
LOSS_FUNCTIONS = {"l2": _l2_loss, "deflow": _deflow_loss, "deltaflow": _deltaflow_loss, "seflow": _seflow_loss,
                  "teflow": _teflow_loss}


def per_sample_training_loss(batch, outputs, background_weight: float, pseudo_labels: bool = False,
                             loss: str = "l2", context: LossContext | None = None):
    """[B] each sample's training loss over the points that are real (`point_mask_t0`) and valid for the model.

    loss (`train.loss`, `LOSS_FUNCTIONS`): "l2" the paper's `per_sample_flow_loss` (with pseudo-labels, ZeroFlow's
    `per_sample_distillation_loss`); "deflow" `per_sample_deflow_loss` over the labelled points (with pseudo-labels,
    over the points with a pseudo-label); "deltaflow" `per_sample_deltaflow_loss` over the labelled points,
    meta-classes from `category_t0` where the batch has it (Argoverse 2 records) else from `class_id_t0`, the instance
    term where the batch has `instance_id_t0`; "seflow", "teflow" (`data.labels=self`): the self-supervised losses of
    `ff3d_tf.model.selfsup_losses`, from the batch's `dynamic_cluster_*` fields.
    batch: flow_mps_t0 [B,N,3] (the pseudo-labels when training on them), class_id_t0 [B,N], point_mask_t0 [B,N];
    with pseudo-labels, optionally pseudo_valid_t0 [B,N] (points without a pseudo-label do not count);
    outputs: the model's flow_mps, point_valid. `context`: the labels and settings (`LossContext.of(cfg)`); without
    it, human labels or with `pseudo_labels` pseudo-labels, and `background_weight`.
    """
    if context is None:
        context = LossContext("pseudo" if pseudo_labels else "human", background_weight)
    if loss not in LOSS_FUNCTIONS:
        raise ValueError(f"loss={loss!r}: one of {', '.join(LOSS_FUNCTIONS)}")
    if context.labels not in LOSS_SPECS[loss].labels:
        raise ValueError(f"loss={loss!r} trains on {' or '.join(LOSS_SPECS[loss].labels)} labels, not "
                         f"{context.labels} labels")
    valid = outputs["point_valid"] & batch["point_mask_t0"]
    if context.labels == "pseudo" and schema.PSEUDO_VALID_KEY in batch:
        valid &= batch[schema.PSEUDO_VALID_KEY]
    return LOSS_FUNCTIONS[loss](batch, outputs, valid, context)


def batch_flow_loss(batch, outputs, background_weight: float, global_batch_size: int, pseudo_labels: bool = False,
                    loss: str = "l2", context: LossContext | None = None):
    """One replica's training loss: `per_sample_training_loss` (`train.loss`; see there for `batch`, `outputs` and
    `context`) summed over the batch and divided by the global batch (`tf.nn.compute_average_loss`), so that N
    replicas' losses add up to the loss of their whole batch on one."""
    per_sample = per_sample_training_loss(batch, outputs, background_weight, pseudo_labels, loss, context)
    return tf.nn.compute_average_loss(per_sample, global_batch_size=global_batch_size)


# --- DeFlow's and DeltaFlow's losses ----------------------------------------------------------------------------------
# DeFlow (Zhang et al., ICRA 2024, arXiv 2401.16122) and DeltaFlow (Zhang et al., arXiv 2508.17054); facts read in
# KTH-RPL/DeFlow scripts/network/loss_func.py @072486bb5ab7e3540d347a750172565c81694045 (deflowLoss), OpenSceneFlow's
# src/lossfuncs/supervise.py (deflowLoss, deltaflowLoss) with src/utils/av2_eval.py
# @2a9c474f2455672bca5d235cae77a46d2d36c9fa (BUCKETED_METACATAGORIES) and src/trainer.py (loss_calculator: one loss
# per sample); no code copied:
# - the label speed (theirs |flow per sweep| / 0.1 s, here |flow_mps_t0|) is bucketed as < 0.4, 0.4 <= s <= 1.0
#   and > 1.0 m/s;
# - the per-point error is the displacement error over one sweep in metres (their flows are metres per sweep): here
#   ||pred - true|| (m/s) x DEFLOW_FRAME_S, so that DeltaFlow's e exp(e) sees the same numbers;
# - DeltaFlow's class term: sum over meta-class c and bucket k of w_c b_k (mean error of the points of c in k), with
#   w = (0.1, 1.0, 2.0, 2.5, 1.5) for (BACKGROUND, CAR, PEDESTRIAN, WHEELED_VRU, OTHER_VEHICLES) and
#   b = (0.1, 0.4, 0.5); a category in no meta-class (road signs, animals) counts as BACKGROUND, as theirs does;
# - DeltaFlow's instance term: over the instances whose mean label speed exceeds 0.4 m/s, the mean of
#   e exp(e) w_c, e the instance's mean error, c the most frequent meta-class of its points;
# - an empty bucket (or meta-class cell) contributes 0; each sample (pair) has its own loss (their trainer loops over
#   the batch), and the batch's is the sum over samples divided by the global batch (`tf.nn.compute_average_loss`;
#   theirs sums over the samples: the same gradient direction, which Adam's update does not scale with).
DEFLOW_FRAME_S = 0.1
DEFLOW_SPEED_EDGES_MPS = (0.4, 1.0)
DELTAFLOW_META_CLASSES = ("BACKGROUND", "CAR", "PEDESTRIAN", "WHEELED_VRU", "OTHER_VEHICLES")
DELTAFLOW_CLASS_WEIGHTS = (0.1, 1.0, 2.0, 2.5, 1.5)  # per DELTAFLOW_META_CLASSES
DELTAFLOW_BUCKET_WEIGHTS = (0.1, 0.4, 0.5)  # per speed bucket, slow to fast
DELTAFLOW_MOVING_INSTANCE_MPS = 0.4  # an instance counts when its points' mean label speed is above this
# WOD's paper classes -> meta-class (index into DELTAFLOW_META_CLASSES): vehicle -> CAR (WOD does not split off
# trucks and buses), pedestrian -> PEDESTRIAN, cyclist -> WHEELED_VRU, sign -> BACKGROUND (as DeltaFlow counts
# Argoverse's road-sign categories), background -> BACKGROUND.
DELTAFLOW_META_OF_PAPER_CLASS = {schema.CLASS_BACKGROUND: 0, schema.CLASS_VEHICLE: 1, schema.CLASS_PEDESTRIAN: 2,
                                 schema.CLASS_SIGN: 0, schema.CLASS_CYCLIST: 3}
# Argoverse 2 label index (`category_t0`) -> meta-class, through the challenge's meta-classes of `metrics_av2`.
_META_OF_AV2_LABEL = np.array([DELTAFLOW_META_CLASSES.index(metrics_av2.META_CLASSES[m]) if m >= 0 else 0
                               for m in metrics_av2.META_OF_LABEL], np.int32)
_META_OF_PAPER_CLASS = np.array([DELTAFLOW_META_OF_PAPER_CLASS[c] for c in sorted(DELTAFLOW_META_OF_PAPER_CLASS)],
                                np.int32)


def speed_buckets(flow_true_mps):
    """[..., 3] float32 one-hot of DeFlow's label-speed bucket of each point (< 0.4, 0.4..1.0, > 1.0 m/s) from its
    label flow [..., 3] in m/s."""
    speed_mps = tf.norm(flow_true_mps, axis=-1)
    lo, hi = DEFLOW_SPEED_EDGES_MPS
    return tf.cast(tf.stack([speed_mps < lo, (speed_mps >= lo) & (speed_mps <= hi), speed_mps > hi], -1), tf.float32)


def frame_errors_m(flow_true_mps, flow_pred_mps):
    """[B,N] the displacement error of each point over DeFlow's sweep (`DEFLOW_FRAME_S`), metres."""
    sq = tf.reduce_sum(tf.square(tf.cast(flow_pred_mps, tf.float32) - flow_true_mps), -1)
    return tf.sqrt(sq + 1e-12) * DEFLOW_FRAME_S  # eps keeps the gradient finite at a perfect prediction


def _cell_means(errors_m, cells):
    """[B, ...] mean of `errors_m` [B,N] over the points of each cell (`cells` [B,N, ...] 0/1 membership); 0 for an
    empty cell."""
    extra = len(cells.shape) - 2
    weighted = tf.reshape(errors_m, tf.concat([tf.shape(errors_m), tf.ones([extra], tf.int32)], 0)) * cells
    return tf.reduce_sum(weighted, 1) / tf.maximum(tf.reduce_sum(cells, 1), 1.0)


def per_sample_deflow_loss(flow_true_mps, flow_pred_mps, point_valid):
    """[B] DeFlow's loss: the sum over the three speed buckets of the mean error (m per sweep) of the sample's valid
    points in the bucket; an empty bucket adds 0. flow_* [B,N,3] m/s; point_valid [B,N] bool."""
    buckets = speed_buckets(flow_true_mps) * tf.cast(point_valid, tf.float32)[..., None]
    return tf.reduce_sum(_cell_means(frame_errors_m(flow_true_mps, flow_pred_mps), buckets), -1)


def deltaflow_meta_class(class_id, category=None):
    """[B,N] int32 meta-class (index into DELTAFLOW_META_CLASSES) of each point: from its Argoverse 2 label index
    `category` where given, else from its paper class `class_id` (`DELTAFLOW_META_OF_PAPER_CLASS`). Ids outside
    the tables (-1: no label, padding) read as BACKGROUND; such points are not labelled and never count."""
    if category is not None:
        table, ids = _META_OF_AV2_LABEL, category
    else:
        table, ids = _META_OF_PAPER_CLASS, class_id
    ids = tf.cast(ids, tf.int32)
    inside = (ids >= 0) & (ids < len(table))
    return tf.where(inside, tf.gather(tf.constant(table), tf.clip_by_value(ids, 0, len(table) - 1)), 0)


def per_sample_instance_loss(errors_m, flow_true_mps, point_valid, meta_class, instance_id):
    """[B] DeltaFlow's instance term: the mean over the sample's moving instances (mean label speed of their valid
    points > `DELTAFLOW_MOVING_INSTANCE_MPS`) of e exp(e) w_c, with e the instance's mean error (m per sweep) and c
    the most frequent meta-class of its points (ties to the lower index); 0 without a moving instance.

    errors_m [B,N] (`frame_errors_m`); instance_id [B,N] int32, numbered within each sample from 0, -1 for none (ids
    >= N do not count: the training input numbers them densely, `ff3d_tf.training.input`). One segment sum over
    every (sample, instance) at once: no loop, static shapes (XLA).
    """
    shape = tf.shape(errors_m)
    b, n = shape[0], shape[1]
    ids = tf.cast(instance_id, tf.int32)
    keep = point_valid & (ids >= 0) & (ids < n)
    segment = tf.where(keep, tf.range(b)[:, None] * n + ids, b * n)  # b * n: the points of no instance
    num_segments = b * n + 1
    ones = tf.cast(keep, tf.float32)
    speed_mps = tf.norm(flow_true_mps, axis=-1)
    num_classes = len(DELTAFLOW_META_CLASSES)
    per_point = tf.concat([ones[..., None], (errors_m * ones)[..., None], (speed_mps * ones)[..., None],
                           tf.one_hot(meta_class, num_classes) * ones[..., None]], -1)  # [B,N,3+C]
    sums = tf.math.unsorted_segment_sum(per_point, segment, num_segments)[:-1]
    sums = tf.reshape(sums, [b, n, 3 + num_classes])  # [sample, instance, ...]
    count = sums[..., 0]
    mean_error_m = sums[..., 1] / tf.maximum(count, 1.0)
    mean_speed_mps = sums[..., 2] / tf.maximum(count, 1.0)
    # mode: counts are whole numbers, so count * C - index is largest for the most points, then the lowest index
    mode = tf.argmax(sums[..., 3:] * num_classes - tf.range(num_classes, dtype=tf.float32), -1, output_type=tf.int32)
    moving = (count > 0) & (mean_speed_mps > DELTAFLOW_MOVING_INSTANCE_MPS)
    e = tf.where(moving, mean_error_m, 0.0)  # exp only of the counted errors: no inf in a discarded branch
    term = tf.where(moving, e * tf.exp(e) * tf.gather(tf.constant(DELTAFLOW_CLASS_WEIGHTS, tf.float32), mode), 0.0)
    return tf.reduce_sum(term, -1) / tf.maximum(tf.reduce_sum(tf.cast(moving, tf.float32), -1), 1.0)


def per_sample_deltaflow_loss(flow_true_mps, flow_pred_mps, point_valid, meta_class, instance_id=None):
    """[B] DeltaFlow's loss: `per_sample_deflow_loss` + the class term (the bucket means per meta-class, weighted by
    class and bucket) + `per_sample_instance_loss` (left out when `instance_id` is None: records without instance
    ids). meta_class [B,N] int32 (`deltaflow_meta_class`)."""
    errors_m = frame_errors_m(flow_true_mps, flow_pred_mps)
    buckets = speed_buckets(flow_true_mps) * tf.cast(point_valid, tf.float32)[..., None]  # [B,N,3]
    loss = tf.reduce_sum(_cell_means(errors_m, buckets), -1)
    cells = tf.one_hot(meta_class, len(DELTAFLOW_META_CLASSES))[..., :, None] * buckets[..., None, :]  # [B,N,C,3]
    weights = tf.constant(DELTAFLOW_CLASS_WEIGHTS)[:, None] * tf.constant(DELTAFLOW_BUCKET_WEIGHTS)[None, :]
    loss += tf.reduce_sum(_cell_means(errors_m, cells) * weights, [1, 2])
    if instance_id is not None:
        loss += per_sample_instance_loss(errors_m, flow_true_mps, point_valid, meta_class, instance_id)
    return loss
