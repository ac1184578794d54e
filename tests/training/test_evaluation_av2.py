"""The Argoverse 2 challenge protocol of `tools/eval.py --protocol av2` on the real sample log: the ground truth scores
0, zero flow and a model's flow score what the challenge's arithmetic (`ff3d_tf.metrics_av2`, checked against a
straight-line reference of the community evaluator in tests/test_metrics_av2.py) gives on the same points."""
import numpy as np
import pytest

from ff3d_tf import metrics_av2
from ff3d_tf.config import replace_config
from ff3d_tf.data import pairs
from ff3d_tf.labels import av2
from ff3d_tf.training.evaluation import challenge_flow_m, evaluate_av2


class _Fixed:
    """A predictor of flow = scale * label + offset (m/s), valid everywhere but `invalid`."""

    def __init__(self, scale=1.0, offset=(0.0, 0.0, 0.0), invalid=None):
        self.scale, self.offset, self.invalid = scale, np.asarray(offset, np.float32), invalid

    def predict(self, batch, example):
        flow = self.scale * np.asarray(example["flow_mps_t0"]) + self.offset
        valid = np.ones(len(flow), bool)
        if self.invalid is not None:
            valid[self.invalid(np.asarray(example["points_xyz_t0"]))] = False
        return flow, valid


def _records_cfg(cfg):
    return replace_config(cfg, {"data.source": "pair_records"})


def _straight(records, cfg, predictor):
    """The same numbers without the evaluation loop: the records read directly and fed to the accumulator."""
    cfg = replace_config(_records_cfg(cfg), {"data.crop_to_grid": False})
    (ex,) = [{k: v.numpy() for k, v in e.items()} for e in pairs.pair_dataset(
        pairs.list_segment_files(records), cfg, extras=av2.AV2_EXTRAS, metadata=True)]
    flow, valid = predictor.predict(None, ex)
    flow = np.where(valid[:, None], flow, 0.0)
    acc = metrics_av2.AV2FlowAccumulator()
    mask = ~ex["is_ground_t0"] & (np.max(np.abs(ex["points_xyz_t0"][:, :2]), axis=1) < 35.0)
    acc.update(challenge_flow_m(ex["flow_mps_t0"], ex), challenge_flow_m(flow, ex), ex["category_t0"], mask)
    return acc.result(), int(mask.sum())


def _assert_same(got: dict, want: dict):
    assert set(got) == set(want)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-9, err_msg=k)


def test_ground_truth_scores_zero(av2_sample_records, tiny_config):
    r = evaluate_av2(_records_cfg(tiny_config), pairs.list_segment_files(av2_sample_records), _Fixed())
    m = r["model"]
    for k in ("three_way/fg_dynamic_epe_m", "three_way/fg_static_epe_m", "three_way/bg_static_epe_m",
              "three_way/mean_epe_m", "bucketed/mean_static_epe_m", "bucketed/mean_dynamic_norm_epe"):
        assert m[k] == 0.0, k
    assert m["num_sweeps"] == 1 and m["num_points"] > 50_000
    assert r["paper_model"]["all/all/mean_l2_mps"] == 0.0 and r["paper_zero_flow"]["vehicle/moving/mean_l2_mps"] > 3
    # Zero flow is not 0 on the moving points: the sample's vehicles move.
    assert r["zero_flow"]["three_way/fg_dynamic_epe_m"] > 0.3


@pytest.mark.parametrize("predictor", [_Fixed(scale=0.0), _Fixed(scale=0.8, offset=(0.05, -0.02, 0.0)),
                                       _Fixed(scale=1.1, invalid=lambda p: p[:, 0] > 20.0)])
def test_model_and_zero_flow_are_the_challenges_arithmetic_on_the_same_points(av2_sample_records, tiny_config,
                                                                               predictor):
    r = evaluate_av2(_records_cfg(tiny_config), pairs.list_segment_files(av2_sample_records), predictor)
    want, n = _straight(av2_sample_records, tiny_config, predictor)
    _assert_same(r["model"], want)
    _assert_same(r["zero_flow"], _straight(av2_sample_records, tiny_config, _Fixed(scale=0.0))[0])
    assert r["model"]["num_points"] == n


def test_other_records_are_refused(tiny_config, tmp_path):
    from ff3d_tf.data import pair_records
    from ff3d_tf.data.wod import write_records
    pair_records.write_manifest(str(tmp_path), write_records.wod_manifest(tiny_config))
    (tmp_path / "x.pairs.tfrecord").write_bytes(b"")
    with pytest.raises(ValueError, match="next sweep"):
        evaluate_av2(_records_cfg(tiny_config), [str(tmp_path / "x.pairs.tfrecord")], _Fixed())
    with pytest.raises(ValueError, match="pair records"):
        evaluate_av2(tiny_config, [str(tmp_path / "x.pairs.tfrecord")], _Fixed())
