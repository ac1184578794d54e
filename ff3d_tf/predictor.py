"""The one contract of a trained model's forward, whatever holds the model: a checkpoint (the Keras model), a
SavedModel, an ONNX file or a portable XLA export.

A `Predictor` gives the flow of one padded pair of `ff3d_tf.data.pairs.padded_singletons`:

  predict(batch, example) -> (flow_mps [N0,3] float32, m/s in the vehicle frame at t0,
                              point_valid [N0] bool, True where the model made a prediction)

for the pair's N0 real t0 points, as NumPy arrays. `batch` is the pair padded to its bucket, batch 1 (the model's six
inputs among its keys); `example` is the same pair unpadded (`num_points_t0`, both clouds, both poses). Evaluation
(`ff3d_tf.training.evaluation`), tools/eval.py, tools/predict.py and tools/av2_submission.py take any predictor;
`ff3d_tf.inference.predictor.load_predictor` makes one from a path.

A runtime that serves raw clouds (`ServingPredictor`: the SavedModel's signature, the ONNX graph) takes each cloud in
its own vehicle frame and the poses, as a client holds them: the clouds oldest first, then their poses in the same
order (`serving_names`: points_tm1, points_t0, pose_tm1, pose_t0 for the pair; a model of more sweeps
(`data.num_frames`) takes points_tm2 before them, and so on); `serving_clouds` turns an example back into those
arguments, so such a runtime follows the contract through `ServingPredictor.predict`.
"""
from __future__ import annotations

import abc
from typing import Protocol, runtime_checkable

import numpy as np

from ff3d_tf import geometry, schema


@runtime_checkable
class Predictor(Protocol):
    """Flow for one padded pair (see the module docstring); implementations differ only in what they run."""

    def predict(self, batch: dict, example: dict) -> tuple[np.ndarray, np.ndarray]:
        """(flow_mps [N0,3], point_valid [N0]) for the pair's real t0 points, as NumPy arrays."""
        ...


def serving_names(num_frames: int = 2) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(cloud argument names, pose argument names) of a serving runtime of `num_frames` sweeps, oldest first:
    (("points_tm1", "points_t0"), ("pose_tm1", "pose_t0")) for the pair."""
    clouds = schema.sweep_clouds(num_frames)[::-1]
    return tuple(f"points_{c}" for c in clouds), tuple(f"pose_{c}" for c in clouds)


def num_frames_of(names) -> int:
    """The number of sweeps of a serving runtime whose argument names are `names` (its "points_*" count)."""
    return sum(1 for n in names if n.startswith("points_"))


def serving_clouds(example: dict) -> tuple[np.ndarray, ...]:
    """The serving arguments of an unpadded example (`serving_names` order: points_tm1 [N1,5], points_t0 [N0,5],
    pose_tm1 [4,4], pose_t0 [4,4] for a pair; older sweeps first): each cloud in its own vehicle frame (x, y, z in
    metres, intensity, elongation; float32) and the vehicle -> world poses (float64). The example holds every past
    cloud in the t0 frame: each goes back with the inverse of its pose's motion relative to t0."""
    ex = {k: np.asarray(v) for k, v in example.items()}
    clouds = [c for c in schema.sweep_clouds(schema.MAX_NUM_FRAMES) if schema.cloud_keys(c)["xyz"] in ex][::-1]
    points, poses = [], []
    for cloud in clouds:
        keys = schema.cloud_keys(cloud)
        xyz = ex[keys["xyz"]]
        if cloud != "t0":
            own_from_t0 = np.linalg.inv(geometry.t0_from_tm1_np(ex["pose_t0"], ex[keys["pose"]]))
            xyz = geometry.transform_points_np(xyz, own_from_t0).astype(np.float32)
        points.append(np.concatenate([xyz, ex[keys["features"]]], -1))
        poses.append(ex[keys["pose"]])
    return (*points, *poses)


class ServingPredictor(Predictor):
    """A runtime of raw clouds and poses, `__call__(*clouds, *poses)` in `serving_names` order (the pair's:
    points_tm1, points_t0, pose_tm1, pose_t0) -> {"flow_mps" [N0,3], "point_valid" [N0]}, that follows the
    `Predictor` contract through `serving_clouds`."""

    @abc.abstractmethod
    def __call__(self, *clouds_and_poses, **by_name) -> dict:
        """The flow of the t0 cloud's points (see the class docstring); arguments by position or by name."""

    @staticmethod
    def arguments(where: str, num_frames: int, positional: tuple, by_name: dict) -> dict:
        """{argument name: value} in `serving_names(num_frames)` order from a call's positional and named arguments;
        a ValueError naming `where` for a missing, repeated or unknown one."""
        names = sum(serving_names(num_frames), ())
        if len(positional) > len(names):
            raise ValueError(f"{where}: takes {len(names)} arguments ({', '.join(names)}), got {len(positional)}")
        values = dict(zip(names, positional))
        for name, value in by_name.items():
            if name not in names or name in values:
                raise ValueError(f"{where}: argument {name!r} " + ("given twice" if name in values else
                                                                   f"unknown; the arguments: {', '.join(names)}"))
            values[name] = value
        missing = [n for n in names if n not in values]
        if missing:
            raise ValueError(f"{where}: takes {len(names)} arguments ({', '.join(names)}); missing {missing}")
        return {n: values[n] for n in names}

    def predict(self, batch: dict, example: dict) -> tuple[np.ndarray, np.ndarray]:
        out = self(*serving_clouds(example))
        return np.asarray(out["flow_mps"]), np.asarray(out["point_valid"])
