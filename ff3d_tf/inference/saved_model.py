"""SavedModel export for serving: raw clouds + poses in, ego compensation inside, flow out.

`serving_default(points_tm1 [N1,5], points_t0 [N0,5], pose_tm1 [4,4] float64, pose_t0 [4,4] float64)` where each
cloud holds x, y, z, intensity, elongation in its own vehicle frame and poses are vehicle -> world (a model of more
sweeps takes every cloud, oldest first, then every pose: `ff3d_tf.predictor.serving_names`). Returns
`flow_mps` [N0,3] (m/s, vehicle frame at t0) and `point_valid` [N0] bool. The clouds are in the order of the model's
slots, oldest slot first: `points_tm{N-1}`, ..., `points_tm1`, `points_t0`. For a model of `data.partner=previous`
(WOD, own sequences) that is every sweep oldest first; a model of Argoverse 2 challenge records
(`data.partner=next`) reads the NEXT sweep t+1 as `points_tm1` (and t-1, t-2, ... as `points_tm2`, ...), and its
flow is the motion from t+1 to t0 per second, minus the velocity. The module records that order (`partner`,
`temporal`, read back by `SavedModelPredictor.order`). One trace serves every N0, N1 (0 included):
point counts are padded inside to the buckets of `ff3d_tf.data.pairs.bucket_size`, and the XLA-compiled model runs once
per bucket.

Inputs are checked inside the signature (so every client gets the same rules) and again, with a Python error, by
`SavedModelPredictor`:
- each pose must be a rigid transform: all 16 entries finite, bottom row [0, 0, 0, 1] and a rotation R with
  max |R^T R - I| <= `geometry.POSE_RIGIDITY_TOLERANCE` and det R > 0; else `InvalidArgumentError` (signature) or
  `ValueError` (predictor) naming the pose (`pose_tm1`, `pose_t0`, ...) and the rule broken;
- points with a NaN/Inf coordinate or feature are not errors: they are masked like points outside the grid
  (`point_valid` false, flow 0);
- dtype, rank and width are fixed by the signature ([N,5] float32 clouds, [4,4] float64 poses); N may be 0.
"""
from __future__ import annotations

import os

import tensorflow as tf

from ff3d_tf import geometry, schema
from ff3d_tf.checkpoints import CONFIG_NAME, with_model_partner
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data.pairs import bucket_size_tf
from ff3d_tf.model import plan as plan_lib
from ff3d_tf.model.fastflow3d import FastFlow3D
from ff3d_tf.predictor import ServingPredictor, num_frames_of, serving_names


def _pose_assertions(pose, name: str) -> list:
    """One assertion op per rule of the pose check (`ff3d_tf.geometry`), each failing with that rule's message."""
    held, messages = geometry.pose_rules_hold(pose), geometry.pose_rule_messages(name)
    return [tf.debugging.Assert(held[rule], [messages[rule]]) for rule in geometry.POSE_RULES]


class FlowServingModule(tf.Module):
    def __init__(self, model: FastFlow3D, bucket_base: int, jit_compile: bool = True):
        super().__init__()
        self.model = model
        self.bucket_base = int(bucket_base)
        inline = bool(jit_compile)  # the whole forward in this XLA program: the model's stages inline
        self._infer = tf.function(lambda inputs: model(inputs, training=False, inline_stages=inline),
                                  jit_compile=jit_compile)
        # The order of the sweeps the model reads (`ff3d_tf.inference.predictor.SweepOrder`), saved with it.
        self.partner = tf.Variable(getattr(model, "partner", "previous"), trainable=False, name="partner")
        self.temporal = tf.Variable(model.temporal, trainable=False, name="temporal")
        point_names, pose_names = serving_names(model.num_frames)
        self.serve = tf.function(self._serve, input_signature=(
            [tf.TensorSpec([None, 5], tf.float32, name=n) for n in point_names] +
            [tf.TensorSpec([4, 4], tf.float64, name=n) for n in pose_names]))

    def _pad(self, points, n):
        target = bucket_size_tf(n, self.bucket_base)
        return tf.pad(points, [[0, target - n], [0, 0]])[None], tf.sequence_mask(n, target)[None]

    def _serve(self, *clouds_and_poses):
        """The clouds, oldest first, then their poses (`serving_names`)."""
        num_frames = len(clouds_and_poses) // 2
        clouds, poses = clouds_and_poses[:num_frames][::-1], clouds_and_poses[num_frames:][::-1]  # t0 first
        names = serving_names(num_frames)[1][::-1]
        checks = [a for pose, name in zip(poses, names) for a in _pose_assertions(pose, name)]
        with tf.control_dependencies(checks):  # no flow from a pose that is not rigid
            poses = [tf.identity(pose) for pose in poses]
        inputs = {}
        for k, (cloud, points, pose) in enumerate(zip(schema.sweep_clouds(num_frames), clouds, poses)):
            keys = schema.cloud_keys(cloud)
            if k:
                xyz = geometry.transform_points(points[:, :3], geometry.t0_from_tm1(poses[0], pose))
                points = tf.concat([xyz, points[:, 3:]], -1)
            padded, mask = self._pad(points, tf.shape(points)[0])
            inputs.update({keys["xyz"]: padded[..., :3], keys["features"]: padded[..., 3:], keys["mask"]: mask})
        out = self._infer(inputs)
        n0 = tf.shape(clouds[0])[0]
        return {"flow_mps": out["flow_mps"][0, :n0], "point_valid": out["point_valid"][0, :n0]}


def export_saved_model(model: FastFlow3D, path: str, bucket_base: int, jit_compile: bool = True,
                       cfg: ExperimentConfig | None = None) -> str:
    """Writes `model` as a SavedModel at `path` (signature serving_default) with the execution plan that computes it
    (`path/execution_plan.json`) and, given the config it was restored with, that config with the model's partner
    (`checkpoints.CONFIG_NAME`: the tools given this SavedModel load it)."""
    module = FlowServingModule(model, bucket_base, jit_compile)
    tf.saved_model.save(module, path, signatures={"serving_default": module.serve})
    plan_lib.save(model.plan, path)
    if cfg is not None:
        with_model_partner(cfg, model).save(os.path.join(path, CONFIG_NAME))
    return path



class SavedModelPredictor(ServingPredictor):
    """Calls a SavedModel's serving signature; raises a clear `ValueError` naming the argument on bad input. A
    `ff3d_tf.predictor.Predictor` too: `predict(batch, example)` calls it with the pair's raw clouds.

    Wrong dtype, rank or width, and poses that are not rigid transforms (`geometry.pose_problem_np`), fail here before
    the call. One instance may be called from several threads at once (the loaded function holds no per-call state).
    """

    def __init__(self, path: str):
        self.path = path
        self.loaded = tf.saved_model.load(path)
        self.fn = self.loaded.signatures["serving_default"]
        self.num_frames = num_frames_of(self.fn.structured_input_signature[1])
        # The order of the sweeps the model reads as the module records it (`ff3d_tf.inference.predictor.sweep_order`)
        self.recorded_order = {k: getattr(self.loaded, k).numpy().decode() for k in ("partner", "temporal")
                               if hasattr(self.loaded, k)}
        self.point_names, self.pose_names = serving_names(self.num_frames)
        self._specs = {**{n: (tf.float32, (None, 5)) for n in self.point_names},
                       **{n: (tf.float64, (4, 4)) for n in self.pose_names}}

    def __call__(self, *clouds_and_poses, **by_name) -> dict:
        values = self.arguments(self.path, self.num_frames, clouds_and_poses, by_name)
        tensors = {}
        for name, (dtype, shape) in self._specs.items():
            t = tf.convert_to_tensor(values[name])
            if t.dtype != dtype or t.shape.rank != len(shape):
                raise ValueError(f"{self.path}: input {name} must be {dtype.name} of rank {len(shape)}, got "
                                 f"{t.dtype.name} with shape {t.shape}")
            if any(want is not None and want != got for want, got in zip(shape, t.shape)):
                shape_text = ", ".join("N" if d is None else str(d) for d in shape)
                raise ValueError(f"{self.path}: input {name} must have shape [{shape_text}], got {t.shape}")
            tensors[name] = t
        for name in self.pose_names:
            problem = geometry.pose_problem_np(tensors[name].numpy(), name)
            if problem:
                raise ValueError(f"{self.path}: {problem}")
        return self.fn(**tensors)
