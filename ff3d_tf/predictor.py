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
its own vehicle frame and the two poses, as a client holds them; `serving_clouds` turns a pair back into those
arguments, so such a runtime follows the contract through `ServingPredictor.predict`.
"""
from __future__ import annotations

import abc
from typing import Protocol, runtime_checkable

import numpy as np

from ff3d_tf import geometry


@runtime_checkable
class Predictor(Protocol):
    """Flow for one padded pair (see the module docstring); implementations differ only in what they run."""

    def predict(self, batch: dict, example: dict) -> tuple[np.ndarray, np.ndarray]:
        """(flow_mps [N0,3], point_valid [N0]) for the pair's real t0 points, as NumPy arrays."""
        ...


def serving_clouds(example: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points_tm1 [N1,5], points_t0 [N0,5], pose_tm1 [4,4], pose_t0 [4,4]) of an unpadded pair: each cloud in its own
    vehicle frame (x, y, z in metres, intensity, elongation; float32) and the vehicle -> world poses (float64). The
    pair holds the t-1 cloud in the t0 frame: it goes back with the inverse of the poses' relative motion."""
    ex = {k: np.asarray(v) for k, v in example.items()}
    tm1_from_t0 = np.linalg.inv(geometry.t0_from_tm1_np(ex["pose_t0"], ex["pose_tm1"]))
    xyz_tm1 = geometry.transform_points_np(ex["points_xyz_tm1_in_t0"], tm1_from_t0)
    points_tm1 = np.concatenate([xyz_tm1.astype(np.float32), ex["point_features_tm1"]], -1)
    points_t0 = np.concatenate([ex["points_xyz_t0"], ex["point_features_t0"]], -1)
    return points_tm1, points_t0, ex["pose_tm1"], ex["pose_t0"]


class ServingPredictor(Predictor):
    """A runtime of raw clouds and poses, `__call__(points_tm1, points_t0, pose_tm1, pose_t0)` -> {"flow_mps" [N0,3],
    "point_valid" [N0]}, that follows the `Predictor` contract through `serving_clouds`."""

    @abc.abstractmethod
    def __call__(self, points_tm1, points_t0, pose_tm1, pose_t0) -> dict:
        """The flow of the t0 cloud's points (see the class docstring)."""

    def predict(self, batch: dict, example: dict) -> tuple[np.ndarray, np.ndarray]:
        out = self(*serving_clouds(example))
        return np.asarray(out["flow_mps"]), np.asarray(out["point_valid"])
