"""lab/labels/nsfp_speed.py (lab/tools/benchmark_nsfp_speed.py): the speed-band pairs' truth against the simulator's
geometry and hand calculations, the scores of known predictions, the summary's arithmetic, and a tiny resumable run."""
import json

import numpy as np
import pytest

from ff3d_tf import geometry
from ff3d_tf.data.synthetic import scene as sim
from lab.labels import nsfp_speed


@pytest.fixture(scope="module")
def pairs():
    return {band: nsfp_speed.speed_pair(3, nsfp_speed.BANDS_MPS[band], points=2048, sensor="ideal")
            for band in ("0-5", "10-20")}


def test_lane_speeds_lie_in_the_band_and_the_geometry_is_the_seeds(pairs):
    for band, pair in pairs.items():
        lo, hi = nsfp_speed.BANDS_MPS[band]
        assert set(pair.lane_speeds_mps) == set(nsfp_speed.TRAFFIC_LANES)
        assert all(lo <= v < hi for v in pair.lane_speeds_mps.values())
    # The band's vehicles move at about their lane's speed (a curve stretches offset lanes a little).
    fast = pairs["10-20"]
    speed = np.linalg.norm(fast.motion_m, axis=1) / nsfp_speed.DT_S
    on = fast.band_vehicle_t0
    assert on.any() and speed[on].min() > 0.8 * min(fast.lane_speeds_mps.values())
    assert speed[on].max() < 1.2 * max(fast.lane_speeds_mps.values())
    # Ground and static structure never move; the same seed and band give the same pair.
    assert not np.any(fast.motion_m[fast.ground_t0])
    again = nsfp_speed.speed_pair(3, nsfp_speed.BANDS_MPS["10-20"], points=2048, sensor="ideal")
    np.testing.assert_array_equal(again.points_xyz_t0, fast.points_xyz_t0)


def test_true_motion_is_the_boxes_rigid_motion():
    """Against the project's own box matrices (the WOD generator's label arithmetic) at one time."""
    rng = np.random.default_rng(0)
    road, agents = sim.make_scene(rng, 10.0)
    agent = [a for a in agents if a.speed != 0 and a.class_id == 1][2]
    c0, h0 = agent.pose(road, 4.0)
    c1, h1 = agent.pose(road, 4.0 - nsfp_speed.DT_S)
    back = geometry.box_matrices_np(c1, h1)[0] @ np.linalg.inv(geometry.box_matrices_np(c0, h0)[0])
    points = c0 + rng.normal(size=(6, 3))
    expected = points - (points @ back[:3, :3].T + back[:3, 3])
    np.testing.assert_allclose(nsfp_speed._true_motion(road, agent, points, np.full(6, 4.0)), expected, atol=1e-9)


def test_the_true_motion_moves_the_fast_vehicles_back_onto_the_earlier_sweep(pairs):
    """Moved back by the truth, the fast vehicles' t0 points lie on the t-1 sweep's surfaces; unmoved they do not."""
    pair = pairs["10-20"]
    on = pair.band_vehicle_t0
    moved_back = nsfp_speed._nearest_distance(pair.points_xyz_t0[on] - pair.motion_m[on], pair.points_xyz_tm1_in_t0)
    unmoved = nsfp_speed._nearest_distance(pair.points_xyz_t0[on], pair.points_xyz_tm1_in_t0)
    assert np.median(moved_back) < 0.5 * np.median(unmoved)


def test_nearest_distance_against_hand_calculation():
    cloud = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    points = np.array([[1.0, 0.0, 0.0], [3.0, 4.0, 0.0], [2.0, 0.0, 0.0]])
    np.testing.assert_allclose(nsfp_speed._nearest_distance(points, cloud, chunk=2), [1.0, 4.0, 1.0])


def test_chamfer_profile_is_lowest_near_the_truth_for_fast_vehicles(pairs):
    """Ideal lidars: the fast vehicles' points moved back by their true motion land on the earlier sweep, so the
    objective along the truth is lower there than at zero motion, and lowest within a step or two of 1x."""
    found = nsfp_speed.chamfer_profile(pairs["10-20"], scales=(0.0, 0.5, 0.9, 1.0, 1.1))
    assert found["scales"] == [0.0, 0.5, 0.9, 1.0, 1.1] and len(found["chamfer_m2"]) == 5
    assert found["argmin_scale"] in (0.9, 1.0, 1.1)
    assert found["at_truth_over_at_zero"] < 0.75  # 2048 points a sweep: sparse, so far from 0


def test_scores_of_zero_and_true_flow(pairs):
    pair = pairs["10-20"]
    perfect = nsfp_speed.score(pair, pair.motion_m)
    assert perfect["moving_vehicle_epe_m"] == 0.0 and perfect["mean_epe_m"] == 0.0
    zero = nsfp_speed.score(pair, np.zeros_like(pair.motion_m))
    assert zero["moving_vehicle_epe_m"] == pytest.approx(zero["moving_vehicle_zero_flow_epe_m"])
    # Zero flow's error on a moving vehicle point is its displacement: the band's speeds x 0.1 s.
    assert zero["moving_vehicle_epe_m"] == pytest.approx(zero["moving_vehicle_mean_speed_mps"] * nsfp_speed.DT_S,
                                                         rel=1e-5)
    assert zero["bg_static_epe_m"] == 0.0


def test_summary_against_hand_calculation():
    def fit(moving, fit_s):
        return {"moving_vehicle_epe_m": moving, "fg_dynamic_epe_m": 1.0, "fg_static_epe_m": 0.0,
                "bg_static_epe_m": 0.5, "mean_epe_m": 0.5, "iterations": 100, "fit_s": fit_s}
    fits = {"a/0-5/1": fit(0.1, 10.0), "a/0-5/2": fit(0.3, 20.0), "a/10-20/1": fit(0.5, 30.0)}
    found = nsfp_speed.summarize(fits, "a", ["0-5", "10-20"], [1, 2])
    assert found["0-5"]["moving_vehicle_epe_m"] == pytest.approx(0.2) and found["0-5"]["fit_s"] == 15.0
    assert found["10-20"]["seeds"] == [1]  # seed 2 not fitted yet
    assert found["fast_over_slow"] == pytest.approx(0.5 / 0.2)


def test_a_tiny_run_writes_every_fit_and_resumes(tmp_path):
    out = str(tmp_path / "speed.json")
    candidates = {"baseline": {"max_iterations": 3, "segment_iterations": 3}}
    lines = []
    args = (candidates, [1], [2], ["baseline"], ["0-5", "10-20"], 1024, "ideal", None, [])
    result = nsfp_speed.run(out, *args, log=lines.append)
    assert set(result["fits"]) == {"baseline/0-5/1", "baseline/10-20/1", "baseline/0-5/2", "baseline/10-20/2"}
    assert result["fits"]["baseline/0-5/1"]["iterations"] == 3
    assert result["held_out"]["baseline"]["10-20"]["seeds"] == [2]
    assert result["machine"]["model_name"] and len(lines) == 8  # 4 fits, 4 Chamfer profiles
    assert set(result["chamfer_profile"]) == {"0-5/1", "10-20/1", "0-5/2", "10-20/2"}
    with open(out) as f:
        assert json.load(f)["fits"] == json.loads(json.dumps(result["fits"]))
    nsfp_speed.run(out, *args, log=lines.append)
    assert len(lines) == 8  # nothing refitted
    changed = {"baseline": {"max_iterations": 2, "segment_iterations": 2}}
    result = nsfp_speed.run(out, changed, *args[1:], log=lines.append)
    assert len(lines) == 12 and result["fits"]["baseline/0-5/1"]["iterations"] == 2
