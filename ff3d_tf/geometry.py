"""Rigid geometry, written once: poses, their check, ego motion between two frames, box and quaternion rotations.

Conventions (the whole project): a pose is a [4,4] float64 vehicle -> world transform; `t0_from_tm1` moves points of
the vehicle frame at t-1 into the vehicle frame at t0, T = inv(pose_t0) @ pose_tm1 (paper appendix); points are
[N,3] rows, transformed as p @ R^T + t. Each function has a TensorFlow form (graphs: the reader, the input pipeline,
the SavedModel) and, where NumPy callers need it, a NumPy form with the suffix `_np`; both compute the same formula.

The pose check: a pose is accepted when all 16 entries are finite, its bottom row is [0, 0, 0, 1] within
`POSE_RIGIDITY_TOLERANCE`, its rotation R has max |R^T R - I| <= `POSE_RIGIDITY_TOLERANCE` and det R > 0. WOD poses are
rigid to float64 precision and a rigid pose rounded through float32 (~1e-7) still passes; a zero, scaled, sheared or
mirrored matrix fails. The reader checks frame poses with it, the SavedModel and its predictor their pose arguments.
"""
from __future__ import annotations

import numpy as np
import tensorflow as tf

POSE_RIGIDITY_TOLERANCE = 1e-4
POSE_RULES = ("finite", "bottom_row", "orthonormal", "proper")  # checked in this order


def pose_rule_messages(name: str) -> dict[str, str]:
    """The message of each rule of the pose check, naming the pose `name` (one text for every caller)."""
    tol = f"{POSE_RIGIDITY_TOLERANCE:g}"
    return {"finite": f"{name} must be finite (it holds NaN or Inf)",
            "bottom_row": f"{name} must have the bottom row [0, 0, 0, 1] (within {tol})",
            "orthonormal": f"{name} must be rigid: its rotation R needs max |R^T R - I| <= {tol} "
                           f"(a zero, scaled or sheared matrix is not a pose)",
            "proper": f"{name} must be a rotation with det R > 0, not a reflection"}


def pose_rules_hold(pose) -> dict[str, tf.Tensor]:
    """Scalar bool tensors, one per rule of `POSE_RULES`: does the [4,4] float64 `pose` keep it. Each rule after
    "finite" is evaluated on the pose with non-finite entries zeroed, so it holds whenever the pose is not finite
    (the "finite" rule reports that case)."""
    pose = tf.convert_to_tensor(pose, tf.float64)
    finite = tf.reduce_all(tf.math.is_finite(pose))
    safe = tf.where(tf.math.is_finite(pose), pose, tf.zeros_like(pose))
    rotation = safe[:3, :3]
    gram_error = tf.reduce_max(tf.abs(tf.matmul(rotation, rotation, transpose_a=True) - tf.eye(3, dtype=tf.float64)))
    bottom_error = tf.reduce_max(tf.abs(safe[3] - tf.constant([0.0, 0.0, 0.0, 1.0], tf.float64)))
    orthonormal = gram_error <= POSE_RIGIDITY_TOLERANCE
    return {"finite": finite,
            "bottom_row": ~finite | (bottom_error <= POSE_RIGIDITY_TOLERANCE),
            "orthonormal": ~finite | orthonormal,
            "proper": ~finite | ~orthonormal | (tf.linalg.det(rotation) > 0)}


def is_rigid_pose(pose) -> tf.Tensor:
    """Scalar bool: the pose keeps every rule."""
    held = pose_rules_hold(pose)
    return tf.reduce_all(tf.stack([held[r] for r in POSE_RULES]))


def pose_problem_np(pose, name: str) -> str | None:
    """The message of the first rule the pose breaks, or None for a rigid transform (eager; same arithmetic as
    `pose_rules_hold`)."""
    held = pose_rules_hold(np.asarray(pose, np.float64))
    messages = pose_rule_messages(name)
    return next((messages[r] for r in POSE_RULES if not bool(held[r])), None)


def rigid_inverse(transform) -> tf.Tensor:
    """Closed-form inverse [R^T, -R^T t] of a rigid [4,4] float64 transform."""
    rotation_inv = tf.transpose(transform[:3, :3])
    translation_inv = -tf.linalg.matvec(rotation_inv, transform[:3, 3])
    return tf.concat([tf.concat([rotation_inv, translation_inv[:, None]], 1),
                      tf.constant([[0.0, 0.0, 0.0, 1.0]], tf.float64)], 0)


def t0_from_tm1(pose_t0, pose_tm1) -> tf.Tensor:
    """[4,4] float64: vehicle frame at t-1 -> vehicle frame at t0, inv(pose_t0) @ pose_tm1."""
    return tf.linalg.inv(pose_t0) @ pose_tm1


def t0_from_tm1_np(pose_t0, pose_tm1) -> np.ndarray:
    """NumPy `t0_from_tm1`."""
    return np.linalg.inv(np.asarray(pose_t0, np.float64)) @ np.asarray(pose_tm1, np.float64)


def transform_points(points_xyz, transform) -> tf.Tensor:
    """[N,3] float32 through a [4,4] float64 transform (computed in float64)."""
    p = tf.cast(points_xyz, tf.float64)
    return tf.cast(tf.linalg.matmul(p, transform[:3, :3], transpose_b=True) + transform[:3, 3], tf.float32)


def transform_points_np(points_xyz, transform) -> np.ndarray:
    """NumPy `transform_points`, float64 out."""
    transform = np.asarray(transform, np.float64)
    return np.asarray(points_xyz, np.float64) @ transform[:3, :3].T + transform[:3, 3]


def box_matrices_np(center, heading) -> np.ndarray:
    """[K,4,4] box -> parent-frame transforms of yaw-only boxes (WOD boxes; AV2 cuboids up to a negligible tilt):
    rotation by `heading` [K] (radians, about z) and translation `center` [K,3]."""
    heading = np.asarray(heading, np.float64).reshape(-1)
    m = np.tile(np.eye(4), (len(heading), 1, 1))
    c, s = np.cos(heading), np.sin(heading)
    m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = c, -s, s, c
    m[:, :3, 3] = np.asarray(center, np.float64).reshape(-1, 3)
    return m


def rotation_from_quaternion_np(qw, qx, qy, qz) -> np.ndarray:
    """[3,3] rotation of a unit quaternion (w, x, y, z), scalars."""
    return np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]])


def yaw_from_quaternion_np(qw, qx, qy, qz):
    """Heading about z (radians) of unit quaternions (arrays or scalars)."""
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
