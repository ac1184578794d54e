"""The map-free ground rule (ff3d_tf.labels.ground) on hand-made scenes: a road with a slope, cars, a wall, a
column with only a few points, returns below the road."""
import numpy as np
import pytest

from ff3d_tf.labels.ground import (GROUND_ABOVE_M, GROUND_CELL_M, has_neighbour_within, height_ground_mask,
                                   pair_ground_masks)


def _scene(seed=0):
    """A road over x in [-30, 30] m, y in [-10, 10] m rising 1 m per 10 m beyond x = 10 (z = 0.1 * max(x - 10, 0)), a
    car (a 4 x 2 x 1.5 m box of points 0.3-1.5 m above the road) at x = 0 and one on the slope at x = 20, a wall from
    0.4 to 3 m above the road at y = 8. Returns points and whether each is ground."""
    rng = np.random.default_rng(seed)

    def road_z(x):
        return 0.1 * np.maximum(x - 10.0, 0.0)
    xy = rng.uniform([-30, -10], [30, 10], (10000, 2))
    road = np.c_[xy, road_z(xy[:, 0]) + rng.normal(0, 0.03, len(xy))]
    cars = []
    for cx in (0.0, 20.0):
        p = rng.uniform([-2, -1, 0.3], [2, 1, 1.5], (400, 3)) + [cx, 0, 0]
        p[:, 2] += road_z(p[:, 0])
        cars.append(p)
    wall = np.c_[rng.uniform(-30, 30, 800), np.full(800, 8.0), rng.uniform(0.4, 3.0, 800)]
    wall[:, 2] += road_z(wall[:, 0])
    points = np.concatenate([road] + cars + [wall])
    return points, np.r_[np.ones(len(road), bool), np.zeros(len(points) - len(road), bool)]


def test_road_and_slope_are_ground_objects_are_not():
    points, truth = _scene()
    got = height_ground_mask(points)
    assert got[truth].mean() > 0.99  # the road, flat and sloped
    assert not got[~truth].any()  # car bodies (0.3 m and more above the road) and the wall
    # A global height threshold would call the slope beyond x = 13 (z > 0.3 m) not ground; the local rule does not.
    slope = truth & (points[:, 0] > 15)
    assert got[slope].mean() > 0.99 and (points[slope, 2] >= GROUND_ABOVE_M).mean() > 0.8


def test_a_few_points_below_the_road_do_not_lift_or_sink_its_column():
    points, truth = _scene(1)
    below = np.array([[0.5, 3.0, -2.0], [0.7, 3.2, -1.5]])  # multipath returns under the road
    got = height_ground_mask(np.concatenate([points, below]))
    assert got[: len(points)][truth].mean() > 0.99 and not got[: len(points)][~truth].any()


def test_a_sparse_column_takes_its_neighbours_ground():
    points, truth = _scene(2)
    # a lone point 1 m above the road, alone in a column outside the road's: its neighbours' ground says not ground
    lone = np.array([[31.0, 0.0, 0.1 * 21 + 1.0]])
    got = height_ground_mask(np.concatenate([points, lone]))
    assert not got[-1]


def test_shapes_and_bad_input():
    assert height_ground_mask(np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match=r"points must be \[N, 3\]"):
        height_ground_mask(np.zeros((4, 2)))


def _verge_pair(seed=3):
    """Two sweeps of `_scene`'s street (independent samples of the same static surfaces) with a verge 0.35 m above
    the road (a strip at y in [-10, -9], x in [-10, 10]: ground the map would call ground, above the 0.3 m band) and
    the car at x = 0 driving 1 m along x between them (10 m/s over 0.1 s). Returns (t0 points, t-1 points, t0 labels:
    0 road, 1 verge, 2 moving car, 3 other)."""
    rng = np.random.default_rng(seed)
    clouds, labels = [], []
    for shift in (0.0, -1.0):  # t0, then t-1 with the car 1 m behind
        points, truth = _scene(int(rng.integers(1 << 30)))
        car = (~truth) & (np.abs(points[:, 0]) < 2.5) & (np.abs(points[:, 1]) < 1.5)
        points[car, 0] += shift
        verge = np.c_[rng.uniform(-10, 10, 2000), rng.uniform(-10, -9, 2000), 0.35 + rng.normal(0, 0.01, 2000)]
        clouds.append(np.concatenate([points, verge]))
        labels.append(np.r_[np.where(truth, 0, np.where(car, 2, 3)), np.ones(len(verge), int)])
    return clouds[0], clouds[1], labels[0]


def test_pair_rule_takes_raised_ground_that_stayed_and_leaves_what_moved():
    t0, tm1, label = _verge_pair()
    # The scene's 10% slope wants the default 4 m columns: a column of the pair rule's default 8 m spans 0.8 m of
    # height there, and its low percentile lies below the column's upper half by more than the band.
    ground_t0, ground_tm1 = pair_ground_masks(t0, tm1, cell_m=GROUND_CELL_M)
    alone = height_ground_mask(np.concatenate([t0, tm1]))[: len(t0)]  # the height rule alone, one surface
    assert alone[label == 1].mean() < 0.2  # the verge lies above its band
    # ... and stayed put between the sweeps. Two independent samplings of 100 points/m^2: a t0 verge point has no
    # t-1 point within STATIC_MATCH_M = 0.1 m with probability exp(-100 * pi * 0.1^2) = 4.3%, so about 96% match.
    assert ground_t0[label == 1].mean() > 0.9
    assert ground_t0[label == 0].mean() > 0.99  # the road
    # The moving car's low points (0.3-0.4 m above the road) moved 1 m; where the 4 m car overlaps its own earlier
    # place, a point can still find one of the other sweep's within 0.1 m by chance (the rule's known miss).
    moving_low = (label == 2) & (t0[:, 2] < 0.4)
    assert ground_t0[label == 2].sum() <= 0.1 * moving_low.sum()
    assert not ground_t0[label == 3].any()  # the parked car and the wall start 0.4 m above the road or more
    assert (ground_t0 >= alone).all() and ground_tm1.shape == (len(tm1),)


def test_has_neighbour_within_equals_brute_force():
    rng = np.random.default_rng(4)
    query, target = rng.uniform(-2, 2, (500, 3)), rng.uniform(-2, 2, (400, 3))
    distance = np.sqrt(((query[:, None] - target[None]) ** 2).sum(-1)).min(1)
    for radius in (0.05, 0.2, 0.5):
        np.testing.assert_array_equal(has_neighbour_within(query, target, radius), distance <= radius)
    assert has_neighbour_within(np.zeros((0, 3)), target, 0.1).shape == (0,)
    assert not has_neighbour_within(query, np.zeros((0, 3)), 0.1).any()
