"""Training augmentation of model input pairs (`data.augment_*`; off in the paper config): a random height offset of
every cloud, random mirror flips of x and/or y with the flow flipped alike, and a per-point jitter.

DeltaFlow's training augmentation (Zhang et al., arXiv 2508.17054; KTH-RPL/OpenSceneFlow @848bf86 src/dataset.py
RandomHeight, RandomFlip and RandomJitter (lines 101-117), composed in train.py line 61 with `train_aug`; facts read,
no code copied): with probability p_height every cloud moves by one z offset drawn uniformly from a range; with
probability p_flip each of x and y is mirrored (independently), the clouds and the flow alike; every point of every
cloud moves by its own normal draw of standard deviation sigma per axis, clipped to [-clip, clip], the flow unchanged.

The first two keep the label true: a flip is linear, so the flow of a point, (p_t0 - p_tm1) / dt, flips with the
points; a common z offset cancels in p_t0 - p_tm1, so the flow is unchanged. The jitter is noise on the points that
the label does not follow, as the authors apply it. The poses (`pose_t0`, `pose_tm1`) keep
describing the clouds as recorded: the model and the loss never read them.

Applied to examples after the decode-once pair records are read (and after the studies and the crop, so a point an
offset moves out of the grid's z range is simply not valid for the model), in the training input only
(`ff3d_tf.training.input`): records stay reusable and evaluation always sees the recorded clouds. Each draw is a
function of a seed (`tf.random.stateless_uniform`): the same seed gives the same augmentation.
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf import schema

# Per-point keys holding positions (flipped and offset: every sweep's cloud) and flows (flipped only), all [N,3] in the
# vehicle frame at t0.
POSITION_KEYS = tuple(schema.cloud_keys(c)["xyz"] for c in schema.sweep_clouds(schema.MAX_NUM_FRAMES))
FLOW_KEYS = ("flow_mps_t0", schema.PSEUDO_FLOW_KEY)


def is_enabled(data_cfg) -> bool:
    """Whether `data_cfg` (a `DataConfig`) asks for any augmentation."""
    return (data_cfg.augment_height_offset_prob > 0 or data_cfg.augment_flip_prob > 0 or
            data_cfg.augment_jitter_sigma_m > 0)


def draw(data_cfg, seed) -> tuple:
    """(flip_x, flip_y, height_offset_m) drawn from `seed` (int [2], `tf.random.stateless_uniform`) by `data_cfg`'s
    probabilities and offset range: bool, bool, float32 (0 when the offset is not drawn)."""
    u = tf.random.stateless_uniform([4], seed)
    lo, hi = data_cfg.augment_height_offset_m
    offset_m = tf.where(u[0] < data_cfg.augment_height_offset_prob, lo + (hi - lo) * u[1], 0.0)
    return u[2] < data_cfg.augment_flip_prob, u[3] < data_cfg.augment_flip_prob, offset_m


def apply(example: dict, flip_x, flip_y, height_offset_m) -> dict:
    """`example` with x (and/or y) negated in its positions and flows and `height_offset_m` added to the z of its
    positions; every other key unchanged. flip_x, flip_y: bool scalars; height_offset_m: float32 scalar (m)."""
    scale = tf.stack([tf.where(flip_x, -1.0, 1.0), tf.where(flip_y, -1.0, 1.0), 1.0])
    shift = tf.stack([0.0, 0.0, tf.cast(height_offset_m, tf.float32)])
    out = dict(example)
    for key in (k for k in POSITION_KEYS if k in example):
        out[key] = example[key] * scale + shift
    for key in FLOW_KEYS:
        if key in example:
            out[key] = example[key] * scale
    return out


def jitter(example: dict, sigma_m: float, clip_m: float, seed) -> dict:
    """`example` with every point of every cloud moved by its own offset [3], each axis a normal draw of standard
    deviation `sigma_m` clipped to [-clip_m, clip_m] (m), drawn from `seed` (int [2]) and the cloud's slot; flows and
    every other key unchanged."""
    out = dict(example)
    for slot, key in enumerate(POSITION_KEYS):
        if key in example:
            noise = tf.random.stateless_normal(tf.shape(example[key]), tf.random.experimental.stateless_fold_in(
                seed, slot), stddev=sigma_m)
            out[key] = example[key] + tf.clip_by_value(noise, -clip_m, clip_m)
    return out


def augment_example(example: dict, data_cfg, seed) -> dict:
    """`apply` with the transforms `draw` gives for `seed`, then `jitter` (when `data.augment_jitter_sigma_m` > 0):
    one training example's augmentation."""
    out = apply(example, *draw(data_cfg, seed))
    if data_cfg.augment_jitter_sigma_m > 0:
        out = jitter(out, data_cfg.augment_jitter_sigma_m, data_cfg.augment_jitter_clip_m,
                     tf.random.experimental.stateless_fold_in(seed, len(POSITION_KEYS)))
    return out
