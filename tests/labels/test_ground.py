"""The map-free ground rule (ff3d_tf.labels.ground) on hand-made scenes: a road with a slope, cars, a wall, a
column with only a few points, returns below the road."""
import numpy as np
import pytest

from ff3d_tf.labels.ground import GROUND_ABOVE_M, height_ground_mask


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
