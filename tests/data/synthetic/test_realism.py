"""The realistic profile's parts alone, each against a hand calculation or an independent computation: the sensor
model (dropped returns, range noise), porous vegetation, the ground's height field, paths that turn, queues that
brake and never overlap, and the city world's variety."""
import dataclasses

import numpy as np
import pytest

from ff3d_tf.data.synthetic import city, lidar, realism, scene, traffic


def test_profiles_and_their_cited_defaults():
    assert realism.profile("ideal") is realism.IDEAL and realism.profile(realism.REALISTIC) is realism.REALISTIC
    with pytest.raises(ValueError, match="ideal"):
        realism.profile("photoreal")
    ideal = realism.IDEAL
    assert not ideal.city and not ideal.motion_distortion and ideal.range_noise_std_m == 0 == ideal.box_margin_m
    assert ideal.dropout_fraction == 0 and ideal.range_at_10pct_m == np.inf
    real = realism.REALISTIC
    # VLP-32C datasheet: +/-3 cm; HDL-64E S2 datasheet: 50 m on ~10 % reflective pavement.
    assert real.range_noise_std_m == 0.03 and real.range_at_10pct_m == 50.0 and real.box_margin_m == pytest.approx(0.09)


def test_dropped_returns_match_the_parameter_on_average():
    rng = np.random.default_rng(0)
    n = 200_000
    only_random = dataclasses.replace(realism.REALISTIC, range_at_10pct_m=np.inf, range_noise_std_m=0.0)
    _, returned = realism.measure(rng, np.full(n, 10.0), np.full(n, 0.5), only_random)
    # Binomial: the kept share is 1 - p within 5 standard deviations sqrt(p (1 - p) / n) = 0.0005.
    assert abs(returned.mean() - (1 - only_random.dropout_fraction)) < 5 * np.sqrt(0.05 * 0.95 / n)
    # No surface, no return; exact ranges when the noise is off.
    measured, returned = realism.measure(rng, np.array([np.inf, 12.5]), np.array([0.5, 0.5]), only_random)
    assert not returned[0] and measured[1] == 12.5
    # Range and reflectivity: half of (1 - p) at R10 * sqrt(reflectivity / 0.1), i.e. 50 m for 10 %, 100 m for 40 %.
    real = realism.REALISTIC
    p = realism.detection_probability(np.array([50.0, 100.0, 5.0]), np.array([0.1, 0.4, 0.1]), real)
    np.testing.assert_allclose(p[:2], (1 - real.dropout_fraction) / 2)
    assert p[2] > 0.94  # a near dark target: almost only the random loss
    far_dark = realism.measure(rng, np.full(n, 60.0), np.full(n, 0.08), real)[1].mean()
    near_bright = realism.measure(rng, np.full(n, 20.0), np.full(n, 0.45), real)[1].mean()
    assert far_dark < 0.3 < 0.9 < near_bright


def test_range_noise_has_the_datasheet_spread():
    rng = np.random.default_rng(1)
    only_noise = dataclasses.replace(realism.IDEAL, range_noise_std_m=0.03)
    measured, returned = realism.measure(rng, np.full(100_000, 30.0), np.full(100_000, 0.3), only_noise)
    assert returned.all()
    error = measured - 30.0
    # Sample mean within 5 standard errors (0.03 / sqrt(1e5)), sample std within 2 % of 3 cm.
    assert abs(error.mean()) < 5 * 0.03 / np.sqrt(1e5) and abs(error.std() / 0.03 - 1) < 0.02


def test_porous_box_returns_as_beer_lambert_says():
    """Rays through a porous cube of side 2 m and extinction 1/m: the share of returns is 1 - exp(-2) = 0.865; given
    a return, the depth into the cube follows the exponential truncated at 2 m, of mean
    1 - 2 e^-2 / (1 - e^-2) = 0.687 m (hand calculation)."""
    road = scene.Road(np.random.default_rng(0))
    bush = scene.Agent(class_id=0, track_id="bush", size=np.array([2.0, 2.0, 2.0]), s0=0.0, d=30.0, speed=0.0,
                       reverse=False, z_bottom=5.0, material="vegetation", labelled=False, extinction_per_m=1.0)
    centre, heading = bush.pose(road, 0.0)
    n = 40_000
    # Rays level with the cube's centre, from 20 m away towards its centre along its local x axis (chord 2 m).
    axis = np.array([np.cos(heading), np.sin(heading), 0.0])
    origins = np.tile(centre - 20.0 * axis, (n, 1))
    dirs = np.tile(axis, (n, 1))
    ranges, hits = lidar.cast(origins, dirs, np.zeros(n), 75.0, [bush], road, np.random.default_rng(2), 0.0,
                              centre[None])
    returned = hits == 0
    assert abs(returned.mean() - (1 - np.exp(-2.0))) < 5 * np.sqrt(0.865 * 0.135 / n)
    depth = ranges[returned] - 19.0
    assert depth.min() >= 0 and depth.max() <= 2.0
    assert abs(depth.mean() - (1 - 2 * np.exp(-2) / (1 - np.exp(-2)))) < 0.02
    # Solid, the same box returns every ray at its face.
    solid = dataclasses.replace(bush, extinction_per_m=0.0, track_id="wall")
    ranges, hits = lidar.cast(origins[:10], dirs[:10], np.zeros(10), 75.0, [solid], road, None, 0.0, centre[None])
    np.testing.assert_allclose(ranges, 19.0)
    np.testing.assert_array_equal(hits, 0)


def test_terrain_crossing_matches_a_fine_march():
    terrain = city.Terrain(np.random.default_rng(4))
    rng = np.random.default_rng(5)
    n = 300
    origins = np.column_stack([rng.uniform(-200, 200, n), rng.uniform(-200, 200, n), np.zeros(n)])
    origins[:, 2] = terrain.height(origins[:, 0], origins[:, 1]) + rng.uniform(0.3, 2.5, n)
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2]) * rng.uniform(0.0, 0.3, n)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = terrain.intersect(origins, dirs, 75.0)
    steps = np.arange(0.0, 75.0, 0.005)
    for i in range(n):
        p = origins[i] + steps[:, None] * dirs[i]
        below = p[:, 2] < terrain.height(p[:, 0], p[:, 1])
        if below.any():
            assert abs(t[i] - steps[np.argmax(below)]) <= 0.005
        else:
            assert not np.isfinite(t[i])
    # Gentle slopes: the steepest grade bounds every finite difference.
    x = np.linspace(-500, 500, 20001)
    assert np.abs(np.diff(terrain.height(x, 0.3 * x)) / np.diff(x * np.sqrt(1.09))).max() <= terrain.max_grade


def test_a_right_turn_is_a_quarter_circle():
    # From s = 10 at d = -5.25 heading +s, a right turn of radius 6 at s = 20: 10 m straight, 3 pi m of arc ending at
    # (26, -11.25) heading -d, then straight on in -d (hand calculation).
    lane = traffic.LaneGeometry(-5.25, 1, turn_s=20.0, turn_radius_m=6.0, turn_sign=-1)
    path = traffic.lane_path(10.0, lane)
    s, d, h = path.at(np.array([0.0, 10.0, 10 + 3 * np.pi / 2, 10 + 3 * np.pi, 10 + 3 * np.pi + 4.0, -2.0]))
    np.testing.assert_allclose(s, [10, 20, 20 + 6 * np.sin(np.pi / 4), 26, 26, 8], atol=1e-9)
    np.testing.assert_allclose(d, [-5.25, -5.25, -5.25 - 6 * (1 - np.cos(np.pi / 4)), -11.25, -15.25, -5.25],
                               atol=1e-9)
    np.testing.assert_allclose(h, [0, 0, -np.pi / 4, -np.pi / 2, -np.pi / 2, 0], atol=1e-12)


def test_queue_brakes_for_a_stop_and_never_overlaps():
    """A leader braking to a stop at 2 m/s^2 (a free-speed event) and two followers: the leader's speed falls from
    8 m/s to 0 over about 4 s (v / b), the followers brake behind it and no bumper gap closes below the clamp's."""
    times = np.arange(0.0, 20.0 + 1e-9, traffic.SIM_STEP_S)
    leader_free = np.where(times < 5.0, 8.0, np.where(times < 9.0, 8.0 - 2.0 * (times - 5.0), 0.0))
    free = np.full(len(times), 8.0)
    lane = traffic.LaneGeometry(-1.75, 1)
    movers = [traffic.Mover(lane, 60.0, 4.5, 1.9, 8.0, leader_free), traffic.Mover(lane, 40.0, 4.5, 1.9, 8.0, free),
              traffic.Mover(lane, 20.0, 10.0, 2.5, 8.0, free)]
    (u,) = traffic.simulate([traffic.Queue(1, movers, [], traffic.VEHICLE_IDM)], times)
    speed = [np.diff(p) / traffic.SIM_STEP_S for p in u]
    assert speed[0][times[:-1] < 4.5].min() > 7.5 and speed[0][times[:-1] > 10.0].max() < 1e-6
    braking = (times[:-1] > 5.5) & (times[:-1] < 8.5)
    assert np.all(np.diff(speed[0][braking]) < 0)  # the box speeds decrease while it brakes
    assert -np.diff(speed[0][braking]).max() / traffic.SIM_STEP_S <= traffic.MAX_DECEL_MPS2 + 1e-9
    for front, back, half in ((0, 1, 4.5), (1, 2, 7.25)):
        gap = (60.0 - 20.0 * front + u[front]) - (60.0 - 20.0 * back + u[back]) - half
        assert gap.min() >= traffic.CLAMP_GAP_M - 1e-9
    assert speed[1][times[:-1] > 15.0].max() < 0.05 and speed[2][times[:-1] > 15.0].max() < 0.05


def test_red_light_stops_the_queue_and_green_releases_it():
    times = np.arange(0.0, 30.0 + 1e-9, traffic.SIM_STEP_S)
    red = (times > 2.0) & (times < 15.0)
    lane = traffic.LaneGeometry(1.75, -1)  # driving towards -s
    movers = [traffic.Mover(lane, 100.0, 4.5, 1.9, 6.0, np.full(len(times), 6.0))]
    (u,) = traffic.simulate([traffic.Queue(-1, movers, [traffic.StopLine(40.0, red)], traffic.VEHICLE_IDM)], times)
    front = 100.0 - u[0] - 2.25  # s of its front bumper
    waiting = (times > 13.0) & (times < 15.0)
    assert np.all(front[waiting] > 40.0) and np.all(front[waiting] < 40.0 + 3.0)  # stopped just before the line
    assert front[-1] < 0.0  # green: it drove on


@pytest.fixture(scope="module")
def world():
    return city.make_world(np.random.default_rng(7), 12.0)


def test_city_world_variety(world):
    """Within 80 m of the ego's road stretch: moving vehicles, pedestrians and cyclists, some of them braking by more
    than 1 m/s; vehicles and pedestrians that turn off the road's direction by more than 45 degrees; trees with
    porous crowns, poles and signs standing."""
    times = np.arange(0.0, 12.0, 0.1)
    ego = world.ego_poses(times)[:, :2, 3]
    kinds = {1: set(), 2: set(), 4: set()}
    braking, turning = set(), set()
    for a in world.agents:
        if a.track is None:
            continue
        path_heading = a.track.path.at(a.track.u)[2]  # relative to the road: turns, not curves
        if np.ptp(path_heading) > np.pi / 4:
            turning.add(a.class_id)  # anywhere, any time: intersections are 90-200 m apart
        centres, _ = a.poses(world.road, times)
        if np.min(np.linalg.norm(centres[:, :2] - ego, axis=1)) > 80.0:
            continue
        v = np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1) / 0.1
        if v.max() > 0.5:
            kinds[a.class_id].add(a.track_id)
        if np.max(np.maximum.accumulate(v) - v) > 1.0:
            braking.add(a.class_id)
    assert all(len(v) >= 2 for v in kinds.values()), {k: len(v) for k, v in kinds.items()}
    assert {1, 2} <= braking and {1, 2} <= turning, (braking, turning)
    materials = {a.material for a in world.agents}
    assert {"vegetation", "trunk", "pole", "sign", "building"} <= materials
    assert any(a.extinction_per_m > 0 for a in world.agents) and world.intersections


def test_city_world_boxes_never_overlap(world):
    """No two solid boxes (buildings aside) overlap in any frame near the ego (separating axes in the plane, then
    height)."""
    def corners(centre, heading, size):
        c, s = np.cos(heading), np.sin(heading)
        return np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * size[:2] / 2 @ np.array([[c, s], [-s, c]]) + centre[:2]

    def apart(a, b):
        for poly in (a, b):
            for i in range(4):
                edge = poly[(i + 1) % 4] - poly[i]
                normal = np.array([-edge[1], edge[0]])
                if (a @ normal).max() <= (b @ normal).min() + 1e-9 or (b @ normal).max() <= (a @ normal).min() + 1e-9:
                    return True
        return False

    for t in np.arange(0.0, 12.0, 1.5):
        frame = world.frame_scene(0, t)
        boxes = [(a, *frame.poses_t[a.track_id]) for a in frame.near
                 if a.extinction_per_m == 0 and a.material != "building"]
        centres = np.array([c for _, c, _ in boxes])
        reach = np.array([np.hypot(*a.size[:2]) / 2 for a, _, _ in boxes])
        heights = np.array([a.size[2] / 2 for a, _, _ in boxes])
        # Pairs whose bounding circles meet and whose heights overlap (not a sign above its pole).
        close = ((np.linalg.norm(centres[:, None, :2] - centres[None, :, :2], axis=-1) < reach[:, None] + reach[None])
                 & (np.abs(centres[:, None, 2] - centres[None, :, 2]) < heights[:, None] + heights[None]))
        for i, j in zip(*np.nonzero(np.triu(close, 1))):
            (ai, ci, hi), (aj, cj, hj) = boxes[i], boxes[j]
            assert apart(corners(ci, hi, ai.size), corners(cj, hj, aj.size)), (t, ai.track_id, aj.track_id)
