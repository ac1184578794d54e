"""SceneFlowMetrics against a NumPy reference, over batches, and under a two-device MirroredStrategy."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.metrics import SceneFlowMetrics, format_paper_table

NAMES = ["background", "vehicle", "pedestrian", "sign", "cyclist"]


def _data(seed=0, n=3000):
    rng = np.random.default_rng(seed)
    cls = rng.integers(-1, 5, n)
    true = rng.normal(0, 1, (n, 3)) * (cls[:, None] > 0) * rng.uniform(0, 3, (n, 1))
    pred = true + rng.normal(0, 0.4, (n, 3))
    cls[:5] = 2  # make sure every class has points
    return true.astype(np.float32), pred.astype(np.float32), cls.astype(np.int32)


def _reference(true, pred, cls, thr=0.5):
    keep = cls >= 0
    err = np.linalg.norm(pred - true, axis=1)
    speed = np.linalg.norm(true, axis=1)
    sp_pred = np.linalg.norm(pred, axis=1)
    out = {}
    for name, sel in [(n, keep & (cls == i)) for i, n in enumerate(NAMES)] + [("all", keep)]:
        for sub, ss in (("all", sel), ("moving", sel & (speed >= thr)), ("stationary", sel & (speed < thr))):
            e = err[ss]
            out[f"{name}/{sub}/mean_l2_mps"] = e.mean() if e.size else np.nan
            out[f"{name}/{sub}/frac_l2_le_0.1"] = (e <= 0.1).mean() if e.size else np.nan
            out[f"{name}/{sub}/count"] = e.size
        tm, pm = speed[sel] >= thr, sp_pred[sel] >= thr
        out[f"{name}/moving_precision"] = (tm & pm).sum() / pm.sum() if pm.sum() else np.nan
        out[f"{name}/moving_recall"] = (tm & pm).sum() / tm.sum() if tm.sum() else np.nan
    fg = keep & (cls > 0)
    out["three_way/fg_dynamic_epe_m"] = 0.1 * err[fg & (speed >= thr)].mean()
    out["three_way/bg_static_epe_m"] = 0.1 * err[keep & (cls == 0) & (speed < thr)].mean()
    # Bucketed, vehicle: speed in m per 0.1 s.
    sel = keep & (cls == 1)
    sm, em = 0.1 * speed[sel], 0.1 * err[sel]
    b = np.minimum(np.floor(sm / 0.04 + 1e-9).astype(int), 50)
    ratios = [em[b == k].mean() / sm[b == k].mean() for k in range(1, 51) if np.any(b == k)]
    out["bucketed/vehicle/dynamic_norm_epe"] = np.mean(ratios)
    out["bucketed/vehicle/static_epe_m"] = em[b == 0].mean() if np.any(b == 0) else np.nan
    return out


def _check(result, ref):
    for k, v in ref.items():
        if np.isnan(v):
            assert np.isnan(result[k]), k
        else:
            np.testing.assert_allclose(result[k], v, rtol=1e-6, atol=1e-9, err_msg=k)


def test_against_numpy_in_batches():
    true, pred, cls = _data()
    m = SceneFlowMetrics()
    for s in (slice(0, 1000), slice(1000, 3000)):
        m.update_state(true[s], pred[s], cls[s])
    result = m.result()
    _check(result, _reference(true, pred, cls))
    assert np.isnan(result["background/moving/mean_l2_mps"])  # empty cell: NaN, never 0
    assert "vehicle" in format_paper_table(result)


def test_point_valid_mask_and_reset():
    true, pred, cls = _data(1, 500)
    valid = np.arange(500) % 2 == 0
    m = SceneFlowMetrics()
    m.update_state(true, pred, cls, point_valid=valid)
    _check(m.result(), _reference(true[valid], pred[valid], cls[valid]))
    m.reset_state()
    assert m.result()["all/all/count"] == 0


def test_two_replica_mirrored_strategy():
    true, pred, cls = _data(2, 2000)
    strategy = tf.distribute.MirroredStrategy(["/cpu:0", "/cpu:1"])
    with strategy.scope():
        m = SceneFlowMetrics()
    halves = [(true[:1000], pred[:1000], cls[:1000]), (true[1000:], pred[1000:], cls[1000:])]

    args = tuple(strategy.experimental_distribute_values_from_function(
        lambda ctx, i=i: tf.constant(halves[ctx.replica_id_in_sync_group][i])) for i in range(3))

    @tf.function
    def step(t, p, c):
        strategy.run(lambda a, b, d: m.update_state(a, b, d), args=(t, p, c))

    step(*args)
    _check(m.result(), _reference(true, pred, cls))


def test_max_distance_crop_against_numpy():
    # The AV2 evaluator's crop keeps points with max(|x|, |y|) < 35 m: (34.9, -34.9) in, (35.0, 0) and (0, -36) out.
    true, pred, cls = _data(3, 1500)
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-60, 60, (1500, 3)).astype(np.float32)
    xyz[:3, :2] = [[34.9, -34.9], [35.0, 0.0], [0.0, -36.0]]
    inside = np.max(np.abs(xyz[:, :2]), axis=1) < 35.0
    assert inside[0] and not inside[1] and not inside[2]
    m = SceneFlowMetrics(max_distance_m=35.0)
    m.update_state(true[:700], pred[:700], cls[:700], points_xyz=xyz[:700])
    m.update_state(true[700:], pred[700:], cls[700:], points_xyz=xyz[700:])
    _check(m.result(), _reference(true[inside], pred[inside], cls[inside]))
    with pytest.raises(ValueError, match="needs the t0 points"):
        m.update_state(true, pred, cls)


def test_evaluation_reports_crop(tiny_segment, tiny_config):
    from ff3d_tf.data import pairs
    from ff3d_tf.predictor import Predictor
    from ff3d_tf.training.evaluation import evaluate
    from ff3d_tf.metrics import CROP_PREFIX, format_extra_tables

    class HalfFlow(Predictor):  # predicts half the true flow for every point
        def predict(self, batch, example):
            n = int(example["num_points_t0"])
            return 0.5 * example["flow_mps_t0"].numpy(), np.ones(n, bool)

    result, _ = evaluate(tiny_config, [tiny_segment], HalfFlow(), log_fn=lambda s: None)
    # Reference: three-way fg_dynamic EPE within 35 m, in m per 0.1 s, over the same pairs.
    errs = []
    for ex in pairs.pair_dataset([tiny_segment], tiny_config):
        xyz, cls, flow = ex["points_xyz_t0"].numpy(), ex["class_id_t0"].numpy(), ex["flow_mps_t0"].numpy()
        speed = np.linalg.norm(flow, axis=1)
        sel = (np.max(np.abs(xyz[:, :2]), 1) < 35.0) & (cls > 0) & (speed >= 0.5)
        errs.append(0.5 * speed[sel])
    errs = np.concatenate(errs)
    assert errs.size > 0
    np.testing.assert_allclose(result[CROP_PREFIX + "three_way/fg_dynamic_epe_m"], 0.1 * errs.mean(), rtol=1e-6)
    assert "within" not in "".join(k for k in result if k.startswith("all/"))
    assert "< 35 m" in format_extra_tables(result)
