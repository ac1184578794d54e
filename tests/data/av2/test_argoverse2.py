"""The Argoverse 2 reader on the real sample log (data/av2_sample_log): sweeps, poses, cuboids, and the map's ground
raster, checked against Argoverse's own flow labels and hand-computed raster lookups."""
import json
import os
import shutil

import numpy as np
import pyarrow.feather as feather
import pytest

from ff3d_tf import schema
from ff3d_tf.data.av2 import argoverse2

from conftest import ROOT
AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")
LOG_ID = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
STAMPS = [315966265259836000, 315966265360032000]


def _column(path, name):
    return feather.read_table(path).column(name).to_numpy(zero_copy_only=False)


def _sweep_city(index=0):
    frame = argoverse2.read_sweep(AV2_LOG, STAMPS[index])
    p = frame["points_xyz"].astype(np.float64)
    return frame, p @ frame["pose"][:3, :3].T + frame["pose"][:3, 3]


# --- reader facts ---------------------------------------------------------------------------------------------------

def test_sample_sweeps_poses_and_cuboids():
    assert argoverse2.sweep_timestamps(AV2_LOG) == STAMPS
    lidar = os.path.join(AV2_LOG, "sensors", "lidar", f"{STAMPS[0]}.feather")
    frame = argoverse2.read_sweep(AV2_LOG, STAMPS[0])
    assert frame["points_xyz"].shape == (99229, 3)
    # float16 coordinates come through exactly; the two 32-beam lidars become laser names 1 and 2.
    np.testing.assert_array_equal(frame["points_xyz"][:, 2], _column(lidar, "z").astype(np.float32))
    laser = _column(lidar, "laser_number")
    np.testing.assert_array_equal(frame["laser_name"], np.where(laser >= 32, 2, 1))
    np.testing.assert_allclose(frame["intensity"], _column(lidar, "intensity") / 255.0, rtol=1e-6)
    assert frame["timestamp_micros"] == STAMPS[0] // 1000
    pose = frame["pose"]
    np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
    poses = feather.read_table(os.path.join(AV2_LOG, "city_SE3_egovehicle.feather")).to_pylist()
    row = next(r for r in poses if r["timestamp_ns"] == STAMPS[0])
    np.testing.assert_array_equal(pose[:3, 3], [row["tx_m"], row["ty_m"], row["tz_m"]])
    # Rotation of a vector by the quaternion, by the Hamilton product q v q* (independent of the matrix formula).
    q = np.array([row["qw"], row["qx"], row["qy"], row["qz"]])

    def mul(a, b):
        return np.array([a[0] * b[0] - a[1:] @ b[1:], *(a[0] * b[1:] + b[0] * a[1:] + np.cross(a[1:], b[1:]))])
    v = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(pose[:3, :3] @ v, mul(mul(q, np.r_[0.0, v]), q * [1, -1, -1, -1])[1:], atol=1e-12)
    boxes = argoverse2.cuboids(AV2_LOG, STAMPS[0])
    ann = feather.read_table(os.path.join(AV2_LOG, "annotations.feather"))
    at = ann.filter(np.asarray(ann.column("timestamp_ns").to_numpy() == STAMPS[0]))
    assert len(boxes["center"]) == at.num_rows > 50
    cats = at.column("category").to_pylist()[::-1]  # the reader reverses the file order (see argoverse2.cuboids)
    np.testing.assert_array_equal(boxes["class_id"], [argoverse2.AV2_CLASS.get(c, 0) for c in cats])
    np.testing.assert_array_equal(boxes["category"], cats)
    np.testing.assert_array_equal(boxes["track_id"], at.column("track_uuid").to_pylist()[::-1])
    assert {schema.CLASS_VEHICLE, schema.CLASS_PEDESTRIAN, schema.CLASS_CYCLIST} <= set(boxes["class_id"].tolist())


def test_scene_flow_label_rules_reproduce_the_sample_labels():
    """`dynamic` and `classes` of Argoverse's labels follow SCENE_FLOW_DYNAMIC_THRESHOLD_M and ANNOTATION_CATEGORIES."""
    frame0, _ = _sweep_city(0)
    p = frame0["points_xyz"].astype(np.float64)
    labels = os.path.join(AV2_LOG, "flow_labels.feather")
    flow = np.stack([_column(labels, c) for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m")], -1).astype(np.float64)
    ego1_from_ego0 = np.linalg.inv(argoverse2.ego_pose(AV2_LOG, STAMPS[1])) @ frame0["pose"]
    rigid = p @ ego1_from_ego0[:3, :3].T + ego1_from_ego0[:3, 3] - p
    dynamic = np.linalg.norm(flow - rigid, axis=1) >= argoverse2.SCENE_FLOW_DYNAMIC_THRESHOLD_M
    np.testing.assert_array_equal(dynamic, _column(labels, "dynamic"))
    # Points inside exactly one cuboid (enlarged by 0.2 m in length and width, as Argoverse labels) carry that
    # cuboid's category index. Inside test in the cuboid frame, by hand.
    ann = feather.read_table(os.path.join(AV2_LOG, "annotations.feather")).to_pylist()
    rows = [r for r in ann if r["timestamp_ns"] == STAMPS[0]]
    inside = np.zeros((len(p), len(rows)), bool)
    for j, r in enumerate(rows):
        yaw = 2 * np.arctan2(r["qz"], r["qw"])  # the cuboids have qx = qy = 0
        d = p - [r["tx_m"], r["ty_m"], r["tz_m"]]
        local = np.stack([np.cos(yaw) * d[:, 0] + np.sin(yaw) * d[:, 1], -np.sin(yaw) * d[:, 0] + np.cos(yaw) * d[:, 1],
                          d[:, 2]], -1)
        half = np.array([r["length_m"] + 0.2, r["width_m"] + 0.2, r["height_m"]]) / 2
        inside[:, j] = np.all(np.abs(local) <= half, axis=1)
    one = inside.sum(1) == 1
    expected = np.array([argoverse2.scene_flow_category_index(rows[j]["category"]) for j in inside[one].argmax(1)])
    classes = _column(labels, "classes")[one]
    assert one.sum() > 5000 and np.mean(classes == expected) > 0.99
    assert np.all(_column(labels, "classes")[inside.sum(1) == 0] == 0)
    assert argoverse2.scene_flow_category_index("REGULAR_VEHICLE") == 19
    assert argoverse2.scene_flow_category_index("not a category") == 0


# --- ground raster --------------------------------------------------------------------------------------------------

def test_sample_raster_and_sim2():
    raster = argoverse2.read_ground_raster(AV2_LOG)
    assert raster.height_m.shape == (785, 880) and raster.height_m.dtype == np.float32
    assert os.path.basename(raster.path) == f"{LOG_ID}_ground_height_surface____PIT.npy"
    with open(os.path.join(AV2_LOG, "map", f"{LOG_ID}___img_Sim2_city.json")) as f:
        sim2 = json.load(f)
    np.testing.assert_array_equal(raster.rotation, np.reshape(sim2["R"], (2, 2)))
    np.testing.assert_array_equal(raster.translation, sim2["t"])
    assert raster.scale == pytest.approx(1 / 0.3)  # 30 cm cells
    assert np.isnan(raster.height_m).any() and np.isfinite(raster.height_m).mean() > 0.5
    assert argoverse2.read_ground_raster(AV2_LOG) is raster  # cached


def test_ground_height_by_hand_on_the_sample():
    raster = argoverse2.read_ground_raster(AV2_LOG)
    stored = np.load(raster.path)
    rows, cols = np.nonzero(np.isfinite(stored))
    pick = np.linspace(0, len(rows) - 1, 50).astype(int)
    r, c = rows[pick], cols[pick]
    t, s = raster.translation, raster.scale  # R is the identity in this log: city x = pixel x / s - t
    # Inside a cell at 10%, 50% and 90% of its width: the cell's own value (no interpolation, no rounding).
    for frac in (0.1, 0.5, 0.9):
        xy = np.stack([(c + frac) / s - t[0], (r + (1 - frac)) / s - t[1]], -1)
        np.testing.assert_array_equal(argoverse2.ground_height_m(AV2_LOG, xy), stored[r, c].astype(np.float64))
    # Off the raster (either side, both axes) and on unmapped cells: NaN.
    h, w = stored.shape
    off = np.array([[-1.5 / s - t[0], 10 / s - t[1]], [(w + 0.5) / s - t[0], 10 / s - t[1]],
                    [10 / s - t[0], -1.5 / s - t[1]], [10 / s - t[0], (h + 0.5) / s - t[1]]])
    assert np.all(np.isnan(argoverse2.ground_height_m(AV2_LOG, np.c_[off, np.zeros(4)])))
    nr, nc = np.argwhere(np.isnan(stored))[0]
    assert np.isnan(argoverse2.ground_height_m(AV2_LOG, [[(nc + 0.5) / s - t[0], (nr + 0.5) / s - t[1]]]))[0]
    assert np.isnan(argoverse2.ground_height_m(AV2_LOG, [[np.nan, 0.0], [np.inf, 1.0]])).all()
    with pytest.raises(ValueError, match="shape"):
        argoverse2.ground_height_m(AV2_LOG, np.zeros((3, 4)))


def test_is_ground_reproduces_argoverse_labels_on_the_sample():
    frame, city = _sweep_city(0)
    ours = argoverse2.is_ground(AV2_LOG, frame["points_xyz"], frame["pose"])
    theirs = _column(os.path.join(AV2_LOG, "flow_labels.feather"), "is_ground_0")
    # 99,228 of 99,229 points (99.9990%). The other point lies 0.4 mm before a cell border (city x 5242.49998 in
    # float64, border 5242.50039); float32 steps there are 0.49 mm (5242.5, 5242.50049), and the labels' float32 city
    # transform landed on the far side, in the neighbouring cell (0.0625 m higher, which makes the point ground).
    assert np.mean(ours == theirs) > 0.999 and np.sum(ours != theirs) == 1 and ours.sum() > 15000
    (i,) = np.flatnonzero(ours != theirs)
    raster = argoverse2.read_ground_raster(AV2_LOG)
    px = raster.pixel_xy(city[i:i + 1, :2])[0]
    assert abs(px[0] - round(px[0])) / raster.scale < 1e-3  # metres from the border
    # The rule is |dz| <= 0.3 m OR below the ground: without "below" the labels disagree on more points.
    height = argoverse2.ground_height_m(AV2_LOG, city)
    with np.errstate(invalid="ignore"):
        near_only = np.abs(city[:, 2] - height) <= argoverse2.GROUND_HEIGHT_THRESHOLD_M
    assert np.sum(near_only != theirs) > np.sum(ours != theirs)
    # The threshold argument: 0 keeps only points below the ground.
    strict = argoverse2.is_ground(AV2_LOG, frame["points_xyz"], frame["pose"], threshold_m=0.0)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(strict, city[:, 2] <= height)


def _map_dir(tmp_path, array, sim2, name="L"):
    log = tmp_path / name
    (log / "map").mkdir(parents=True)
    np.save(log / "map" / f"{name}_ground_height_surface____XYZ.npy", array)
    with open(log / "map" / f"{name}___img_Sim2_city.json", "w") as f:
        json.dump(sim2, f)
    return str(log)


def test_rotated_sim2_by_hand(tmp_path):
    """pixel = s * (R @ xy + t): a raster whose cell (row, col) holds 1000 row + col, queried at city points built by
    inverting the mapping by hand, xy = R^T (pixel / s - t)."""
    rows, cols = 40, 60
    # float32 (the reader takes any float dtype): float16 cannot hold 1000 row + col exactly.
    values = (np.arange(rows)[:, None] * 1000.0 + np.arange(cols)[None]).astype(np.float32)
    a = np.deg2rad(30.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t, s = np.array([12.5, -7.25]), 2.0
    log = _map_dir(tmp_path, values, {"R": rot.reshape(-1).tolist(), "t": t.tolist(), "s": s})
    rng = np.random.default_rng(0)
    pix = np.c_[rng.uniform(0.01, cols - 0.01, 500), rng.uniform(0.01, rows - 0.01, 500)]
    xy = (pix / s - t) @ rot  # row vectors: R^T p == p @ R
    expected = np.floor(pix[:, 1]) * 1000 + np.floor(pix[:, 0])
    np.testing.assert_array_equal(argoverse2.ground_height_m(log, xy), expected)
    # Truncation toward zero, as av2 casts: a pixel coordinate in (-1, 0) still reads cell 0; <= -1 is off.
    edge = (np.array([[-0.5, 3.5], [-1.5, 3.5], [5.5, -0.5], [cols + 0.2, 3.5]]) / s - t) @ rot
    got = argoverse2.ground_height_m(log, edge)
    assert got[0] == 3000 and np.isnan(got[1]) and got[2] == 5 and np.isnan(got[3])
    # is_ground takes ego points and the ego -> city pose.
    pose = np.eye(4)
    pose[:3, 3] = (1.0, 2.0, 3.0)
    city = np.c_[xy[:3], expected[:3] + [0.29, 0.31, -5.0]]
    np.testing.assert_array_equal(argoverse2.is_ground(log, city - pose[:3, 3], pose), [True, False, True])


@pytest.mark.parametrize("damage, column, message", [
    ("no_map_dir", "file", "no map folder"),
    ("no_npy", "file", "found none"),
    ("two_npy", "file", "exactly one"),
    ("no_json", "file", "found none"),
    ("garbage_npy", "file", "not a readable .npy"),
    ("pickled_npy", "file", "not a readable .npy"),
    ("one_d", "array", "2-D"),
    ("int_array", "array", "dtype int16"),
    ("inf_height", "array", "infinite"),
    ("bad_json", "file", "not a readable JSON"),
    ("json_list", "file", "JSON object"),
    ("missing_s", "s", "missing"),
    ("short_t", "t", "2 numbers"),
    ("string_R", "R", "4 numbers"),
    ("nan_t", "t", "non-finite"),
    ("zero_s", "s", "positive"),
    ("scaled_R", "R", "not a rotation"),
])
def test_damaged_raster_is_named(tmp_path, damage, column, message):
    good = {"R": [1.0, 0.0, 0.0, 1.0], "t": [0.0, 0.0], "s": 1 / 0.3}
    array = np.zeros((4, 5), np.float16)
    log = _map_dir(tmp_path, array, good)
    map_dir = os.path.join(log, "map")
    npy = os.path.join(map_dir, "L_ground_height_surface____XYZ.npy")
    js = os.path.join(map_dir, "L___img_Sim2_city.json")

    def write_json(value):
        with open(js, "w") as f:
            f.write(value if isinstance(value, str) else json.dumps(value))
    if damage == "no_map_dir":
        shutil.rmtree(map_dir)
    elif damage == "no_npy":
        os.remove(npy)
    elif damage == "two_npy":
        shutil.copy(npy, os.path.join(map_dir, "M_ground_height_surface____XYZ.npy"))
    elif damage == "no_json":
        os.remove(js)
    elif damage == "garbage_npy":
        with open(npy, "wb") as f:
            f.write(b"\x93NUMPY garbage" * 3)
    elif damage == "pickled_npy":
        np.save(npy, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    elif damage == "one_d":
        np.save(npy, np.zeros(7, np.float16))
    elif damage == "int_array":
        np.save(npy, np.zeros((3, 3), np.int16))
    elif damage == "inf_height":
        np.save(npy, np.array([[0.0, np.inf]], np.float16))
    elif damage == "bad_json":
        write_json('{"R": [1, 0, 0, 1], "t": [0')
    elif damage == "json_list":
        write_json([1, 2, 3])
    elif damage == "missing_s":
        write_json({"R": good["R"], "t": good["t"]})
    elif damage == "short_t":
        write_json(dict(good, t=[1.0]))
    elif damage == "string_R":
        write_json(dict(good, R=["1", 0, 0, 1]))
    elif damage == "nan_t":
        write_json('{"R": [1, 0, 0, 1], "t": [NaN, 0], "s": 3.3}')
    elif damage == "zero_s":
        write_json(dict(good, s=0))
    elif damage == "scaled_R":
        write_json(dict(good, R=[2.0, 0.0, 0.0, 2.0]))
    with pytest.raises(argoverse2.Argoverse2FormatError) as err:
        argoverse2.ground_height_m(log, np.zeros((2, 3)))
    assert err.value.column == column and message in err.value.reason, str(err.value)
    assert err.value.path.startswith(map_dir)
