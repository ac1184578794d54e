"""SavedModel export for serving: raw clouds + poses in, ego compensation inside, flow out.

`serving_default(points_tm1 [N1,5], points_t0 [N0,5], pose_tm1 [4,4] float64, pose_t0 [4,4] float64)` where each
cloud holds x, y, z, intensity, elongation in its own vehicle frame and poses are vehicle -> world. Returns
`flow_mps` [N0,3] (m/s, vehicle frame at t0) and `point_valid` [N0] bool. One trace serves every N0, N1 (0 included):
point counts are padded inside to the buckets of `ff3d_tf.data.pairs.bucket_size`, and the XLA-compiled model runs once
per bucket.

Inputs are checked inside the signature (so every client gets the same rules) and again, with a Python error, by
`SavedModelPredictor`:
- each pose must be a rigid transform: all 16 entries finite, bottom row [0, 0, 0, 1] and a rotation R with
  max |R^T R - I| <= POSE_TOLERANCE and det R > 0; else `InvalidArgumentError` (signature) or `ValueError`
  (predictor) naming `pose_tm1` or `pose_t0` and the rule broken;
- points with a NaN/Inf coordinate or feature are not errors: they are masked like points outside the grid
  (`point_valid` false, flow 0);
- dtype, rank and width are fixed by the signature ([N,5] float32 clouds, [4,4] float64 poses); N may be 0.
"""
from __future__ import annotations

import numpy as np
import tensorflow as tf

from ff3d_tf.data.pairs import _bucket_size_tf, transform_points
from ff3d_tf.data.wod_format import POSE_RIGIDITY_TOLERANCE
from ff3d_tf.model.fastflow3d import FastFlow3D

# max |R^T R - I| and max |bottom row - [0, 0, 0, 1]| of an accepted pose: the reader's tolerance for frame poses
POSE_TOLERANCE = POSE_RIGIDITY_TOLERANCE
POSE_NAMES = ("pose_tm1", "pose_t0")


def _pose_rules(name: str) -> dict:
    """The message of each pose rule (one text for the signature's and the predictor's checks)."""
    return {"finite": f"{name} must be finite (it holds NaN or Inf)",
            "bottom_row": f"{name} must have the bottom row [0, 0, 0, 1] (within {POSE_TOLERANCE:g})",
            "orthonormal": f"{name} must be rigid: its rotation R needs max |R^T R - I| <= {POSE_TOLERANCE:g} "
                           f"(a zero, scaled or sheared matrix is not a pose)",
            "proper": f"{name} must be a rotation with det R > 0, not a reflection"}


def pose_problem(pose: np.ndarray, name: str) -> str | None:
    """The first rule a [4,4] vehicle -> world pose breaks (message naming `name`), or None for a rigid transform."""
    rules = _pose_rules(name)
    pose = np.asarray(pose, np.float64)
    if not np.isfinite(pose).all():
        return rules["finite"]
    if np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0]).max() > POSE_TOLERANCE:
        return rules["bottom_row"]
    rotation = pose[:3, :3]
    if np.abs(rotation.T @ rotation - np.eye(3)).max() > POSE_TOLERANCE:
        return rules["orthonormal"]
    if np.linalg.det(rotation) <= 0:
        return rules["proper"]
    return None


def _pose_assertions(pose, name: str) -> list:
    """Graph-side `pose_problem`: one assertion op per rule, each failing with that rule's message."""
    rules = _pose_rules(name)
    finite = tf.reduce_all(tf.math.is_finite(pose))
    safe = tf.where(tf.math.is_finite(pose), pose, tf.zeros_like(pose))  # later rules see finite numbers only
    rotation = safe[:3, :3]
    gram_error = tf.reduce_max(tf.abs(tf.matmul(rotation, rotation, transpose_a=True) - tf.eye(3, dtype=tf.float64)))
    bottom_error = tf.reduce_max(tf.abs(safe[3] - tf.constant([0.0, 0.0, 0.0, 1.0], tf.float64)))
    return [tf.debugging.Assert(finite, [rules["finite"]]),
            tf.debugging.Assert(~finite | (bottom_error <= POSE_TOLERANCE), [rules["bottom_row"]]),
            tf.debugging.Assert(~finite | (gram_error <= POSE_TOLERANCE), [rules["orthonormal"]]),
            tf.debugging.Assert(~finite | (gram_error > POSE_TOLERANCE) | (tf.linalg.det(rotation) > 0),
                                [rules["proper"]])]


class FlowServingModule(tf.Module):
    def __init__(self, model: FastFlow3D, bucket_base: int, jit_compile: bool = True):
        super().__init__()
        self.model = model
        self.bucket_base = int(bucket_base)
        self._infer = tf.function(lambda inputs: model(inputs, training=False), jit_compile=jit_compile)

    def _pad(self, points, n):
        target = _bucket_size_tf(n, self.bucket_base)
        return tf.pad(points, [[0, target - n], [0, 0]])[None], tf.sequence_mask(n, target)[None]

    @tf.function(input_signature=[tf.TensorSpec([None, 5], tf.float32, name="points_tm1"),
                                  tf.TensorSpec([None, 5], tf.float32, name="points_t0"),
                                  tf.TensorSpec([4, 4], tf.float64, name="pose_tm1"),
                                  tf.TensorSpec([4, 4], tf.float64, name="pose_t0")])
    def serve(self, points_tm1, points_t0, pose_tm1, pose_t0):
        checks = _pose_assertions(pose_tm1, "pose_tm1") + _pose_assertions(pose_t0, "pose_t0")
        with tf.control_dependencies(checks):  # no flow from a pose that is not rigid
            pose_tm1, pose_t0 = tf.identity(pose_tm1), tf.identity(pose_t0)
        n0, n1 = tf.shape(points_t0)[0], tf.shape(points_tm1)[0]
        xyz_tm1 = transform_points(points_tm1[:, :3], tf.linalg.inv(pose_t0) @ pose_tm1)
        p0, m0 = self._pad(points_t0, n0)
        p1, m1 = self._pad(tf.concat([xyz_tm1, points_tm1[:, 3:]], -1), n1)
        out = self._infer({"points_xyz_t0": p0[..., :3], "point_features_t0": p0[..., 3:], "point_mask_t0": m0,
                           "points_xyz_tm1_in_t0": p1[..., :3], "point_features_tm1": p1[..., 3:],
                           "point_mask_tm1": m1})
        return {"flow_mps": out["flow_mps"][0, :n0], "point_valid": out["point_valid"][0, :n0]}


def export_saved_model(model: FastFlow3D, path: str, bucket_base: int, jit_compile: bool = True) -> str:
    module = FlowServingModule(model, bucket_base, jit_compile)
    tf.saved_model.save(module, path, signatures={"serving_default": module.serve})
    return path


class SavedModelPredictor:
    """Calls a SavedModel's serving signature; raises a clear `ValueError` naming the argument on bad input.

    Wrong dtype, rank or width, and poses that are not rigid transforms (`pose_problem`), fail here before the call.
    One instance may be called from several threads at once (the loaded function holds no per-call state).
    """

    _SPECS = {"points_tm1": (tf.float32, (None, 5)), "points_t0": (tf.float32, (None, 5)),
              "pose_tm1": (tf.float64, (4, 4)), "pose_t0": (tf.float64, (4, 4))}

    def __init__(self, path: str):
        self.path = path
        self.loaded = tf.saved_model.load(path)
        self.fn = self.loaded.signatures["serving_default"]

    def __call__(self, points_tm1, points_t0, pose_tm1, pose_t0) -> dict:
        values = {"points_tm1": points_tm1, "points_t0": points_t0, "pose_tm1": pose_tm1, "pose_t0": pose_t0}
        tensors = {}
        for name, (dtype, shape) in self._SPECS.items():
            t = tf.convert_to_tensor(values[name])
            if t.dtype != dtype or t.shape.rank != len(shape):
                raise ValueError(f"{self.path}: input {name} must be {dtype.name} of rank {len(shape)}, got "
                                 f"{t.dtype.name} with shape {t.shape}")
            if any(want is not None and want != got for want, got in zip(shape, t.shape)):
                shape_text = ", ".join("N" if d is None else str(d) for d in shape)
                raise ValueError(f"{self.path}: input {name} must have shape [{shape_text}], got {t.shape}")
            tensors[name] = t
        for name in POSE_NAMES:
            problem = pose_problem(tensors[name].numpy(), name)
            if problem:
                raise ValueError(f"{self.path}: {problem}")
        return self.fn(**tensors)
