"""SavedModel serving: same outputs as the Keras model, any point count, clear errors on bad input."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import HEADS, replace_config
from ff3d_tf.inference.saved_model import SavedModelPredictor, export_saved_model
from ff3d_tf.model import build_model


def _pose(yaw, x):
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[0, 3] = x
    return m


@pytest.mark.parametrize("head", HEADS)
def test_saved_model_round_trip(tiny_config, tmp_path, head):
    model = build_model(replace_config(tiny_config, {"model.head": head}))
    path = export_saved_model(model, str(tmp_path / "sm"), bucket_base=256)
    predictor = SavedModelPredictor(path)
    rng = np.random.default_rng(0)
    pose_tm1, pose_t0 = _pose(0.02, 10.0), _pose(0.05, 10.8)
    for n0, n1 in ((300, 250), (17, 600), (0, 5), (3, 0)):
        pts0 = rng.uniform(-30, 30, (n0, 5)).astype(np.float32)
        pts1 = rng.uniform(-30, 30, (n1, 5)).astype(np.float32)
        pts0[:, 2] = pts0[:, 2] / 15
        pts1[:, 2] = pts1[:, 2] / 15
        out = predictor(pts1, pts0, pose_tm1, pose_t0)
        assert out["flow_mps"].shape == (n0, 3) and out["point_valid"].shape == (n0,)
        t = np.linalg.inv(pose_t0) @ pose_tm1
        xyz1 = (pts1[:, :3].astype(np.float64) @ t[:3, :3].T + t[:3, 3]).astype(np.float32)
        ref = model({"points_xyz_t0": pts0[None, :, :3], "point_features_t0": pts0[None, :, 3:],
                     "point_mask_t0": tf.ones([1, n0], tf.bool), "points_xyz_tm1_in_t0": xyz1[None],
                     "point_features_tm1": pts1[None, :, 3:], "point_mask_tm1": tf.ones([1, n1], tf.bool)})
        np.testing.assert_allclose(out["flow_mps"].numpy(), ref["flow_mps"].numpy()[0], atol=1e-4)
    # One trace serves every N: the signature has a dynamic point dimension.
    sig = predictor.fn.structured_input_signature[1]
    assert sig["points_t0"].shape.as_list() == [None, 5]
    with pytest.raises(ValueError, match="points_t0 must be float32 of rank 2"):
        predictor(np.zeros((4, 5), np.float32), np.zeros((4, 5), np.float64), pose_tm1, pose_t0)
    with pytest.raises(ValueError, match="pose_t0 must be float64 of rank 2"):
        predictor(np.zeros((4, 5), np.float32), np.zeros((4, 5), np.float32), pose_tm1, np.zeros(16))
