"""Evaluation: a checkpoint and its SavedModel score the same; the zero-flow baseline matches NumPy."""
import numpy as np

from ff3d_tf.data import pairs
from ff3d_tf.training.evaluation import evaluate
from ff3d_tf.model.forward import ModelPredictor
from ff3d_tf.inference.saved_model import SavedModelPredictor, export_saved_model
from ff3d_tf.model import build_model


def test_model_and_saved_model_agree_and_zero_baseline(tiny_segment, tiny_config, tmp_path):
    model = build_model(tiny_config)
    result, zero = evaluate(tiny_config, [tiny_segment], ModelPredictor(model), log_fn=lambda s: None)
    saved = SavedModelPredictor(export_saved_model(model, str(tmp_path / "sm"), tiny_config.data.point_bucket_base))
    result_sm, zero_sm = evaluate(tiny_config, [tiny_segment], saved, log_fn=lambda s: None)
    for key in ("all/all/count", "vehicle/moving/count", "all/all/mean_l2_mps", "all/moving/frac_l2_le_1.0"):
        np.testing.assert_allclose(result_sm[key], result[key], rtol=1e-4, err_msg=key)
    assert zero_sm.keys() == zero.keys()
    np.testing.assert_array_equal([zero_sm[k] for k in sorted(zero)], [zero[k] for k in sorted(zero)])  # NaN = NaN
    # Zero flow: the mean L2 error is the mean speed of the labelled points with a prediction (valid = in the grid).
    speeds, n = 0.0, 0
    for ex in pairs.pair_dataset([tiny_segment], tiny_config):
        cls, flow = ex["class_id_t0"].numpy(), ex["flow_mps_t0"].numpy()
        speeds += np.linalg.norm(flow[cls >= 0], axis=1).sum()
        n += int((cls >= 0).sum())
    assert zero["all/all/count"] == n
    np.testing.assert_allclose(zero["all/all/mean_l2_mps"], speeds / n, rtol=1e-6)
