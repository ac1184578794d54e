"""SavedModel export for serving: raw clouds + poses in, ego compensation inside, flow out.

`serving_default(points_tm1 [N1,5], points_t0 [N0,5], pose_tm1 [4,4] float64, pose_t0 [4,4] float64)` where each
cloud holds x, y, z, intensity, elongation in its own vehicle frame and poses are vehicle -> world. Returns
`flow_mps` [N0,3] (m/s, vehicle frame at t0) and `point_valid` [N0] bool. One trace serves every N0, N1 (0 included):
point counts are padded inside to the buckets of `ff3d_tf.data.pairs.bucket_size`, and the XLA-compiled model runs once
per bucket.
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf.data.pairs import _bucket_size_tf, transform_points
from ff3d_tf.model.fastflow3d import FastFlow3D


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
    """Calls a SavedModel's serving signature; raises a clear error on wrong rank or dtype."""

    def __init__(self, path: str):
        self.path = path
        self.loaded = tf.saved_model.load(path)
        self.fn = self.loaded.signatures["serving_default"]

    def __call__(self, points_tm1, points_t0, pose_tm1, pose_t0) -> dict:
        args = {"points_tm1": (points_tm1, tf.float32, 2), "points_t0": (points_t0, tf.float32, 2),
                "pose_tm1": (pose_tm1, tf.float64, 2), "pose_t0": (pose_t0, tf.float64, 2)}
        tensors = {}
        for name, (value, dtype, rank) in args.items():
            t = tf.convert_to_tensor(value)
            if t.dtype != dtype or t.shape.rank != rank:
                raise ValueError(f"{self.path}: input {name} must be {dtype.name} of rank {rank}, got "
                                 f"{t.dtype.name} with shape {t.shape}")
            tensors[name] = t
        return self.fn(**tensors)
