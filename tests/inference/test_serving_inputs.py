"""Serving inputs a client may send: hostile poses rejected by name, bad points masked, any count, many threads."""
import concurrent.futures
import time

import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import replace_config
from ff3d_tf.geometry import POSE_RIGIDITY_TOLERANCE as POSE_TOLERANCE, pose_problem_np as pose_problem
from ff3d_tf.inference.saved_model import SavedModelPredictor, export_saved_model
from ff3d_tf.model import build_model


def _pose(yaw, x, y=0.0):
    m = np.eye(4)
    m[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    m[:2, 3] = x, y
    return m


POSE_TM1, POSE_T0 = _pose(0.02, 10.0), _pose(0.05, 10.8, 0.3)


def _cloud(rng, n, extent=30.0):
    pts = rng.uniform(-extent, extent, (n, 5)).astype(np.float32)
    pts[:, 2] = rng.uniform(-2, 2, n)  # within the grid's z range
    pts[:, 3:] = rng.uniform(0, 1, (n, 2))
    return pts


@pytest.fixture(scope="module", params=["paper", "gru"])
def served(request, tiny_config, tmp_path_factory):
    """(SavedModelPredictor, the raw serving_default function) of a tiny model, with each head (`model.head`)."""
    cfg = replace_config(tiny_config, {"model.head": request.param})
    path = export_saved_model(build_model(cfg), str(tmp_path_factory.mktemp("sm") / "sm"), bucket_base=256)
    predictor = SavedModelPredictor(path)
    return predictor, predictor.fn


def _hostile(kind):
    pose = POSE_T0.copy()
    if kind == "nan":
        pose[0, 3] = np.nan
    elif kind == "inf":
        pose[1, 1] = np.inf
    elif kind == "zeros":  # the client never filled it in
        pose = np.zeros((4, 4))
    elif kind == "singular_rotation":
        pose[:3, :3] = 0
    elif kind == "scaled_by_2":
        pose[:3, :3] *= 2
    elif kind == "sheared":
        pose[0, 1] += 0.01
    elif kind == "bottom_row":
        pose[3, 0] = 0.5
    elif kind == "reflection":
        pose[:3, 2] *= -1  # orthonormal, det -1: a mirrored frame
    return pose


RULE = {"nan": "must be finite", "inf": "must be finite", "zeros": "bottom row", "singular_rotation": "must be rigid",
        "scaled_by_2": "must be rigid", "sheared": "must be rigid", "bottom_row": "bottom row",
        "reflection": "not a reflection"}


@pytest.mark.parametrize("kind", sorted(RULE))
@pytest.mark.parametrize("which", ["pose_tm1", "pose_t0"])
def test_hostile_pose_rejected_naming_the_argument(served, kind, which):
    predictor, fn = served
    rng = np.random.default_rng(1)
    poses = {"pose_tm1": POSE_TM1, "pose_t0": POSE_T0, which: _hostile(kind)}
    pts1, pts0 = _cloud(rng, 50), _cloud(rng, 40)
    problem = pose_problem(poses[which], which)
    assert problem.startswith(f"{which} ") and RULE[kind] in problem
    # The signature itself refuses (any client: TF Serving, C++, Python), the message names argument and rule.
    with pytest.raises(tf.errors.InvalidArgumentError, match=f"{which} {RULE[kind]}|{which} must.*{RULE[kind]}"):
        fn(points_tm1=tf.constant(pts1), points_t0=tf.constant(pts0), pose_tm1=tf.constant(poses["pose_tm1"]),
           pose_t0=tf.constant(poses["pose_t0"]))
    with pytest.raises(ValueError, match=f"{which} .*{RULE[kind]}"):
        predictor(pts1, pts0, poses["pose_tm1"], poses["pose_t0"])


def test_pose_tolerance_accepts_float32_rounded_poses(served):
    """A rigid pose that went through float32 (error ~1e-7) is inside POSE_TOLERANCE; 10x the tolerance is not."""
    predictor, _ = served
    rounded = POSE_T0.astype(np.float32).astype(np.float64)
    assert pose_problem(rounded, "pose_t0") is None
    out = predictor(_cloud(np.random.default_rng(2), 30), _cloud(np.random.default_rng(3), 30), POSE_TM1, rounded)
    assert np.isfinite(out["flow_mps"].numpy()).all()
    scaled = POSE_T0.copy()
    scaled[:3, :3] *= 1 + 10 * POSE_TOLERANCE  # R^T R - I ~ 2e-3 on the diagonal
    assert "must be rigid" in pose_problem(scaled, "pose_t0")


def test_non_finite_points_are_masked_not_errors(served):
    predictor, _ = served
    rng = np.random.default_rng(4)
    pts0, pts1 = _cloud(rng, 200), _cloud(rng, 180)
    bad0 = np.array([3, 50, 199])
    pts0[3, 0], pts0[50, 2], pts0[199, 4] = np.nan, np.inf, -np.inf  # a coordinate, z, a feature
    pts1[[7, 9], 1] = np.nan
    out = predictor(pts1, pts0, POSE_TM1, POSE_T0)
    flow, valid = out["flow_mps"].numpy(), out["point_valid"].numpy()
    assert not valid[bad0].any() and (flow[bad0] == 0).all() and np.isfinite(flow).all()
    # The other points get the flow they get without the bad points at all (masked points change nothing).
    keep0 = np.setdiff1d(np.arange(200), bad0)
    clean = predictor(np.delete(pts1, [7, 9], 0), pts0[keep0], POSE_TM1, POSE_T0)
    np.testing.assert_array_equal(valid[keep0], clean["point_valid"].numpy())
    np.testing.assert_allclose(flow[keep0], clean["flow_mps"].numpy(), atol=1e-5)


@pytest.mark.parametrize("case,match", [
    ("points_float64", "points_t0 must be float32 of rank 2"),
    ("points_rank3", "points_t0 must be float32 of rank 2"),
    ("points_width4", r"points_t0 must have shape \[N, 5\]"),
    ("pose_float32", "pose_tm1 must be float64 of rank 2"),
    ("pose_flat", "pose_tm1 must be float64 of rank 2"),
    ("pose_3x4", r"pose_tm1 must have shape \[4, 4\]")])
def test_wrong_dtype_rank_or_width_rejected(served, case, match):
    predictor, fn = served
    args = {"points_tm1": np.zeros((4, 5), np.float32), "points_t0": np.zeros((4, 5), np.float32),
            "pose_tm1": POSE_TM1, "pose_t0": POSE_T0}
    bad = {"points_float64": ("points_t0", np.zeros((4, 5), np.float64)),
           "points_rank3": ("points_t0", np.zeros((1, 4, 5), np.float32)),
           "points_width4": ("points_t0", np.zeros((4, 4), np.float32)),
           "pose_float32": ("pose_tm1", POSE_TM1.astype(np.float32)),
           "pose_flat": ("pose_tm1", POSE_TM1.reshape(16)),
           "pose_3x4": ("pose_tm1", POSE_TM1[:3])}[case]
    args[bad[0]] = bad[1]
    with pytest.raises(ValueError, match=match):
        predictor(**args)
    # The raw signature refuses the same inputs (TF's own error type and wording: only that it refuses is ours).
    with pytest.raises((TypeError, ValueError, tf.errors.InvalidArgumentError)):
        fn(**{k: tf.constant(v) for k, v in args.items()})


@pytest.mark.parametrize("n1,n0", [(0, 0), (0, 37), (37, 0)])
def test_empty_clouds(served, n1, n0):
    predictor, _ = served
    rng = np.random.default_rng(5)
    out = predictor(_cloud(rng, n1), _cloud(rng, n0), POSE_TM1, POSE_T0)
    assert out["flow_mps"].shape == (n0, 3) and out["point_valid"].shape == (n0,)
    assert out["flow_mps"].dtype == tf.float32 and out["point_valid"].dtype == tf.bool
    assert np.isfinite(out["flow_mps"].numpy()).all()
    if n0:
        assert out["point_valid"].numpy().all()  # all inside the grid, finite: valid even with an empty t-1 cloud


def test_two_million_points(served):
    """A 2M-point t0 cloud (a dense merged sweep): one call, right shapes, the out-of-grid points masked."""
    predictor, _ = served
    rng = np.random.default_rng(6)
    n = 2_000_000
    pts0 = _cloud(rng, n, extent=50.0)  # the tiny grid covers [-40, 40] m: some points fall outside
    pts1 = _cloud(rng, 1000)
    t = time.perf_counter()
    out = predictor(pts1, pts0, POSE_TM1, POSE_T0)
    flow, valid = out["flow_mps"].numpy(), out["point_valid"].numpy()
    seconds = time.perf_counter() - t
    inside = (np.abs(pts0[:, :2]) < 40).all(1)
    assert flow.shape == (n, 3) and np.isfinite(flow).all()
    np.testing.assert_array_equal(valid, inside)
    assert (flow[~inside] == 0).all()
    print(f"2M points: {seconds:.1f} s")


def test_eight_threads_share_one_loaded_model(served):
    """8 threads calling one loaded SavedModel at once get exactly what one call at a time gets."""
    predictor, _ = served
    rng = np.random.default_rng(7)
    # Different inputs per thread (and two bucket sizes), so mixed-up results would show.
    inputs = [(_cloud(rng, 100 + 40 * i), _cloud(rng, 300 - 25 * i), _pose(0.01 * i, 10.0), _pose(0.01 * i + 0.03,
                                                                                                 10.7))
              for i in range(8)]
    expected = [predictor(*args) for args in inputs]
    barrier = __import__("threading").Barrier(8)

    def call(i):
        barrier.wait()  # all eight start together
        return [predictor(*inputs[i]) for _ in range(3)]

    with concurrent.futures.ThreadPoolExecutor(8) as pool:
        results = list(pool.map(call, range(8)))
    for want, got_all in zip(expected, results):
        for got in got_all:
            np.testing.assert_array_equal(got["flow_mps"].numpy(), want["flow_mps"].numpy())
            np.testing.assert_array_equal(got["point_valid"].numpy(), want["point_valid"].numpy())
