"""Argoverse 2 sensor-log reader (sweeps, cuboids, poses) yielding the same frame dicts as the WOD reader.

Layout (Wilson et al., NeurIPS Datasets and Benchmarks 2021; av2-api): `sensors/lidar/<timestamp_ns>.feather` (x, y, z
in the ego-vehicle frame, intensity 0..255, laser_number, offset_ns), `annotations.feather` (tracked cuboids, ego frame
of their timestamp, quaternion rotation), `city_SE3_egovehicle.feather` (ego -> city pose per timestamp).
Cuboids are reduced to yaw-only boxes (their roll and pitch are ~0 by construction of the annotation).

The map's ground raster (`map/<log_id>_ground_height_surface____<CITY>.npy`, float16 ground height in city metres, 30 cm
cells, NaN outside the region of interest; `map/<log_id>___img_Sim2_city.json`, the Sim(2) city -> raster pixel
mapping) is read by `read_ground_raster`, `ground_height_m` and `is_ground`, with av2-api's arithmetic (cited there).
"""
from __future__ import annotations

import dataclasses
import functools
import glob
import json
import os

import numpy as np

from ff3d_tf import geometry, schema

# AV2 categories -> flow classes; categories not listed are other labelled objects: their points move with their
# cuboid but are counted as background (class 0) in the per-class tables.
AV2_CLASS = {
    **{c: schema.CLASS_VEHICLE for c in ("REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "BOX_TRUCK", "TRUCK",
                                         "TRUCK_CAB", "VEHICULAR_TRAILER", "SCHOOL_BUS", "ARTICULATED_BUS",
                                         "RAILED_VEHICLE", "MESSAGE_BOARD_TRAILER")},
    **{c: schema.CLASS_PEDESTRIAN for c in ("PEDESTRIAN", "OFFICIAL_SIGNALER", "WHEELCHAIR", "STROLLER")},
    **{c: schema.CLASS_CYCLIST for c in ("BICYCLIST", "MOTORCYCLIST", "BICYCLE", "MOTORCYCLE", "WHEELED_RIDER")},
    **{c: schema.CLASS_SIGN for c in ("SIGN", "STOP_SIGN")},
}
CUBOID_MARGIN_M = (0.2, 0.2, 0.0)  # Argoverse's scene-flow labels enlarge cuboids by 0.2 m in length and width


class Argoverse2FormatError(ValueError):
    """A log file that cannot be read as Argoverse 2: names the file, the column (or "file") and what is wrong."""

    def __init__(self, path: str, column: str, reason: str):
        self.path, self.column, self.reason = path, column, reason
        super().__init__(f"{path}: column {column}: {reason}")


# Columns each reader needs, with their kind: f = finite number, i = integer, s = string.
SWEEP_COLUMNS = {"x": "f", "y": "f", "z": "f", "intensity": "f", "laser_number": "i"}
POSE_COLUMNS = {"timestamp_ns": "i", "qw": "f", "qx": "f", "qy": "f", "qz": "f", "tx_m": "f", "ty_m": "f", "tz_m": "f"}
CUBOID_COLUMNS = {**POSE_COLUMNS, "category": "s", "track_uuid": "s", "length_m": "f", "width_m": "f",
                  "height_m": "f"}
FLOW_COLUMNS = {"flow_tx_m": "f", "flow_ty_m": "f", "flow_tz_m": "f"}
QUATERNION_NORM_TOLERANCE = 1e-3


def _table(path: str, columns: dict[str, str]) -> dict[str, np.ndarray]:
    """The named columns of a feather file as NumPy, checked: present, of their kind, no nulls, finite numbers."""
    import pyarrow as pa
    import pyarrow.feather as feather
    if not os.path.exists(path):
        raise Argoverse2FormatError(path, "file", "missing from the Argoverse 2 log")
    try:
        t = feather.read_table(path, columns=None)
        t.validate(full=True)
    except (pa.ArrowException, OSError, ValueError) as err:
        raise Argoverse2FormatError(path, "file", f"not a readable feather (Arrow IPC) file ({type(err).__name__})"
                                    ) from None
    out = {}
    for name, kind in columns.items():
        if name not in t.schema.names:
            raise Argoverse2FormatError(path, name, f"missing; the file has {t.schema.names}")
        column = t.column(name)
        dtype = column.type
        ok = {"f": pa.types.is_floating(dtype) or pa.types.is_integer(dtype), "i": pa.types.is_integer(dtype),
              "s": pa.types.is_string(dtype) or pa.types.is_large_string(dtype)}[kind]
        if not ok:
            wanted = {"f": "a number", "i": "an integer", "s": "a string"}[kind]
            raise Argoverse2FormatError(path, name, f"type {dtype}, expected {wanted}")
        if column.null_count:
            raise Argoverse2FormatError(path, name, f"{column.null_count} null values")
        values = column.to_numpy()
        if kind == "f" and not np.all(np.isfinite(values)):
            raise Argoverse2FormatError(path, name, f"non-finite value at row {int(np.argmin(np.isfinite(values)))}")
        out[name] = values
    return out


def _unit_quaternions(path: str, t: dict[str, np.ndarray]) -> None:
    norm = np.sqrt(t["qw"].astype(np.float64) ** 2 + t["qx"] ** 2 + t["qy"] ** 2 + t["qz"] ** 2)
    bad = np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE
    if np.any(bad):
        raise Argoverse2FormatError(path, "qw..qz", f"quaternion of norm {norm[bad][0]:.4g} at row "
                                    f"{int(np.argmax(bad))}; rotations need unit norm within "
                                    f"{QUATERNION_NORM_TOLERANCE}")


def sweep_timestamps(log_dir: str) -> list[int]:
    lidar_dir = os.path.join(log_dir, "sensors", "lidar")
    if not os.path.isdir(lidar_dir):
        raise Argoverse2FormatError(lidar_dir, "file", "missing: not an Argoverse 2 sensor log")
    names = [n for n in os.listdir(lidar_dir) if n.endswith(".feather")]
    bad = [n for n in names if not n[: -len(".feather")].isdigit()]
    if bad:
        raise Argoverse2FormatError(os.path.join(lidar_dir, bad[0]), "file",
                                    "sweep names must be <timestamp_ns>.feather")
    return sorted(int(n[: -len(".feather")]) for n in names)


def ego_pose(log_dir: str, timestamp_ns: int) -> np.ndarray:
    """4x4 ego -> city (the WOD `pose` convention: vehicle -> world)."""
    path = os.path.join(log_dir, "city_SE3_egovehicle.feather")
    t = _table(path, POSE_COLUMNS)
    hit = np.nonzero(t["timestamp_ns"] == timestamp_ns)[0]
    if hit.size == 0:
        raise Argoverse2FormatError(path, "timestamp_ns", f"no ego pose at sweep timestamp {timestamp_ns}")
    i = hit[0]
    _unit_quaternions(path, {q: t[q][i:i + 1] for q in ("qw", "qx", "qy", "qz")})
    m = np.eye(4)
    m[:3, :3] = geometry.rotation_from_quaternion_np(t["qw"][i], t["qx"][i], t["qy"][i], t["qz"][i])
    m[:3, 3] = (t["tx_m"][i], t["ty_m"][i], t["tz_m"][i])
    return m


def cuboids(log_dir: str, timestamp_ns: int) -> dict:
    """Boxes dict (`ff3d_tf.labels.box_flow` layout, plus `category`: the Argoverse category strings) of the cuboids
    annotated at a sweep, in its ego frame.

    In reverse file order: where the enlarged cuboids overlap (a rider and their bicycle, people in a group),
    Argoverse's labels give a point to the last cuboid of the file and `bootstrap_flow` to the first box, so the
    reversal makes the two conventions agree (sample log, points within 1 cm of Argoverse's flow: pedestrians 92.7%
    -> 97.8%, cyclists 91.6% -> 100%).
    """
    path = os.path.join(log_dir, "annotations.feather")
    t = _table(path, CUBOID_COLUMNS)
    sel = np.flatnonzero(t["timestamp_ns"] == timestamp_ns)[::-1]
    _unit_quaternions(path, {q: t[q][sel] for q in ("qw", "qx", "qy", "qz")})
    cats = t["category"][sel]
    return {
        "center": np.stack([t["tx_m"][sel], t["ty_m"][sel], t["tz_m"][sel]], -1).astype(np.float64),
        "size": np.stack([t["length_m"][sel], t["width_m"][sel], t["height_m"][sel]], -1).astype(np.float64),
        "heading": geometry.yaw_from_quaternion_np(t["qw"][sel], t["qx"][sel], t["qy"][sel], t["qz"][sel]).astype(np.float64),
        "track_id": np.asarray(t["track_uuid"][sel]).astype(str),
        "class_id": np.array([AV2_CLASS.get(str(c), schema.CLASS_BACKGROUND) for c in cats], np.int32),
        "category": np.asarray(cats).astype(str),  # the Argoverse category of each cuboid (same order)
    }


def read_sweep(log_dir: str, timestamp_ns: int) -> dict:
    """One sweep as a WOD-reader frame dict (no flow labels: flow 0, class -1; elongation 0; intensity / 255)."""
    t = _table(os.path.join(log_dir, "sensors", "lidar", f"{timestamp_ns}.feather"), SWEEP_COLUMNS)
    xyz = np.stack([t["x"], t["y"], t["z"]], -1).astype(np.float32)
    n = len(xyz)
    return {
        "points_xyz": xyz,
        "intensity": (t["intensity"].astype(np.float32) / 255.0),
        "elongation": np.zeros(n, np.float32),
        "flow_mps": np.zeros((n, 3), np.float32),
        "class_id": np.full(n, schema.CLASS_NO_LABEL, np.int32),
        # The two stacked 32-beam sensors map to laser names 1 (upper, lasers 0-31) and 2 (lower).
        "laser_name": (1 + (t["laser_number"].astype(np.int32) >= 32)).astype(np.int32),
        "pose": ego_pose(log_dir, timestamp_ns),
        "timestamp_micros": int(timestamp_ns // 1000),
    }


def argoverse_flow_in_paper_convention(log_dir: str) -> tuple[np.ndarray, np.ndarray]:
    """Argoverse's own labels of sweep 0 converted to the paper's convention, (displacement_m [N,3] in the sweep-0
    ego frame with ego motion removed, over sweep 0 -> sweep 1; the `dynamic`/class columns are not used).

    Argoverse stores f = X1 - p: the point's position at sweep 1 in the sweep-1 ego frame minus its sweep-0 position
    (ego motion included, forward-looking). In the sweep-0 frame the point moved by inv(ego1_SE3_ego0) (p + f) - p.
    """
    stamps = sweep_timestamps(log_dir)
    p = read_sweep(log_dir, stamps[0])["points_xyz"].astype(np.float64)
    lab = _table(os.path.join(log_dir, "flow_labels.feather"), FLOW_COLUMNS)
    f = np.stack([lab["flow_tx_m"], lab["flow_ty_m"], lab["flow_tz_m"]], -1).astype(np.float64)
    ego0_from_ego1 = geometry.t0_from_tm1_np(ego_pose(log_dir, stamps[0]), ego_pose(log_dir, stamps[1]))
    return geometry.transform_points_np(p + f, ego0_from_ego1) - p, p


# --- Scene-flow label facts (av2-api, src/av2/evaluation/scene_flow/constants.py and
# src/av2/datasets/sensor/constants.py `AnnotationCategories`): the `classes` column of Argoverse's flow labels holds
# 1 + the index of the cuboid's category in this order (0: no cuboid); a point is `dynamic` when its flow less the
# ego-motion flow is at least 5 cm over the sweep pair (`SCENE_FLOW_DYNAMIC_THRESHOLD`; checked on the sample log:
# both columns agree on every point).
ANNOTATION_CATEGORIES = (
    "ANIMAL", "ARTICULATED_BUS", "BICYCLE", "BICYCLIST", "BOLLARD", "BOX_TRUCK", "BUS", "CONSTRUCTION_BARREL",
    "CONSTRUCTION_CONE", "DOG", "LARGE_VEHICLE", "MESSAGE_BOARD_TRAILER", "MOBILE_PEDESTRIAN_CROSSING_SIGN",
    "MOTORCYCLE", "MOTORCYCLIST", "OFFICIAL_SIGNALER", "PEDESTRIAN", "RAILED_VEHICLE", "REGULAR_VEHICLE", "SCHOOL_BUS",
    "SIGN", "STOP_SIGN", "STROLLER", "TRAFFIC_LIGHT_TRAILER", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER", "WHEELCHAIR",
    "WHEELED_DEVICE", "WHEELED_RIDER")
SCENE_FLOW_DYNAMIC_THRESHOLD_M = 0.05


def scene_flow_category_index(category: str) -> int:
    """The `classes` value of Argoverse's flow labels for a point inside a cuboid of `category` (0: no cuboid)."""
    return ANNOTATION_CATEGORIES.index(category) + 1 if category in ANNOTATION_CATEGORIES else 0


# --- Ground raster. Facts from av2-api (argoverse/av2-api):
# - src/av2/geometry/sim2.py `Sim2.from_json` / `transform_from`: the json holds R (2x2, row-major, 4 values), t (2)
#   and s; a city point maps to raster pixel coordinates as s * (R @ xy_city + t) (pixel x = column, y = row).
# - src/av2/map/map_api.py `RasterMapLayer.get_raster_values_at_coords`: pixel coordinates are cast to int64 (truncated
#   toward zero, no rounding, no interpolation: the cell whose [i, i+1) span holds the point), the value is
#   array[row = pixel y, col = pixel x], and queries off the array get the fill value, NaN for the ground height
#   (`GroundHeightLayer.get_ground_height_at_xy`); cells outside the region of interest hold NaN themselves.
# - same file, `GroundHeightLayer.get_ground_points_boolean`: a point is ground when |z - ground height| <=
#   GROUND_HEIGHT_THRESHOLD_M = 0.3 m or it lies below the ground height (z < height); a NaN height is never ground.
#   Argoverse's scene-flow labels (`is_ground_0`) come from this rule with the sweep's points in city coordinates.
# - same file, `GroundHeightLayer.from_file`: the files are the one `*_ground_height_surface____*.npy` and the one
#   `*___img_Sim2_city.json` of the log's map folder.
GROUND_HEIGHT_THRESHOLD_M = 0.3
GROUND_RASTER_PATTERN = "*_ground_height_surface____*.npy"
SIM2_PATTERN = "*___img_Sim2_city.json"
SIM2_ROTATION_TOLERANCE = 1e-3  # |R^T R - I| entries: R must be a rotation (the scale is s)


@dataclasses.dataclass(frozen=True)
class GroundRaster:
    """A log's ground-height raster and its city -> pixel Sim(2):
    pixel_xy = scale * (rotation @ xy_city + translation)."""

    height_m: np.ndarray  # [H, W] float32 (stored float16), ground height in city metres, NaN where unmapped
    rotation: np.ndarray  # [2, 2]
    translation: np.ndarray  # [2]
    scale: float  # pixels per metre (1 / 0.3 in Argoverse 2)
    path: str  # the .npy file

    def pixel_xy(self, xy_city: np.ndarray) -> np.ndarray:
        """[N, 2] float64 raster pixel coordinates (x = column, y = row) of [N, 2] city points."""
        xy = np.asarray(xy_city, np.float64)
        with np.errstate(invalid="ignore", over="ignore"):  # non-finite queries give non-finite pixels
            return (xy @ self.rotation.T + self.translation) * self.scale

    def height_at(self, points_xyz_city: np.ndarray) -> np.ndarray:
        """[N] float64 ground height under each city point ([N, 2] or [N, 3]; only x, y are used), NaN off the raster
        or on an unmapped cell."""
        pts = np.asarray(points_xyz_city, np.float64)
        if pts.ndim != 2 or pts.shape[1] not in (2, 3):
            raise ValueError(f"ground height: points must be [N, 2] or [N, 3], got shape {pts.shape}")
        pix = self.pixel_xy(pts[:, :2])
        rows, cols = self.height_m.shape
        # Truncation toward zero as av2 casts (so a pixel coordinate in (-1, 0) reads cell 0, as it does there); the
        # bounds test is on the cast values. Non-finite queries stay NaN (their cast would be undefined).
        finite = np.all(np.isfinite(pix), axis=1) & np.all(np.abs(pix) < 2.0 ** 62, axis=1)
        ij = np.zeros(pix.shape, np.int64)
        ij[finite] = pix[finite].astype(np.int64)
        ok = finite & (ij[:, 0] >= 0) & (ij[:, 0] < cols) & (ij[:, 1] >= 0) & (ij[:, 1] < rows)
        out = np.full(len(pts), np.nan)
        out[ok] = self.height_m[ij[ok, 1], ij[ok, 0]]
        return out


def _one_map_file(map_dir: str, pattern: str, what: str) -> str:
    if not os.path.isdir(map_dir):
        raise Argoverse2FormatError(map_dir, "file", f"missing: the log has no map folder (needed for the {what})")
    found = sorted(glob.glob(os.path.join(glob.escape(map_dir), pattern)))
    if len(found) != 1:
        have = "none" if not found else ", ".join(os.path.basename(f) for f in found)
        raise Argoverse2FormatError(os.path.join(map_dir, pattern), "file",
                                    f"the {what} must be exactly one file matching {pattern}; found {have}")
    return found[0]


def _read_sim2(path: str) -> tuple[np.ndarray, np.ndarray, float]:
    try:
        with open(path, "rb") as f:
            data = json.loads(f.read().decode("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as err:
        raise Argoverse2FormatError(path, "file", f"not a readable JSON file ({type(err).__name__})") from None
    if not isinstance(data, dict):
        raise Argoverse2FormatError(path, "file", f"a JSON object with R, t and s expected, got {type(data).__name__}")
    fields = {}
    for key, count in (("R", 4), ("t", 2), ("s", 1)):
        if key not in data:
            raise Argoverse2FormatError(path, key, f"missing; the file has {sorted(data)}")
        value = data[key] if key != "s" else [data[key]]
        if (not isinstance(value, list) or len(value) != count
                or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise Argoverse2FormatError(path, key, f"{count} number{'s' if count > 1 else ''} expected, got "
                                        f"{json.dumps(data[key])[:60]}")
        arr = np.asarray(value, np.float64)
        if not np.all(np.isfinite(arr)):
            raise Argoverse2FormatError(path, key, "non-finite value")
        fields[key] = arr
    rotation, scale = fields["R"].reshape(2, 2), float(fields["s"][0])
    if not scale > 0.0:
        raise Argoverse2FormatError(path, "s", f"scale {scale} must be positive")
    if np.abs(rotation.T @ rotation - np.eye(2)).max() > SIM2_ROTATION_TOLERANCE:
        raise Argoverse2FormatError(path, "R", f"not a rotation matrix: {fields['R'].tolist()} (R^T R must be I "
                                    f"within {SIM2_ROTATION_TOLERANCE})")
    return rotation, fields["t"], scale


@functools.lru_cache(maxsize=8)
def _cached_raster(npy_path: str, json_path: str, _stamp: tuple) -> GroundRaster:
    try:
        array = np.load(npy_path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise Argoverse2FormatError(npy_path, "file", f"not a readable .npy array ({type(err).__name__})") from None
    if not isinstance(array, np.ndarray) or array.ndim != 2 or min(array.shape) == 0:
        raise Argoverse2FormatError(npy_path, "array", f"a non-empty 2-D ground height array expected, got shape "
                                    f"{getattr(array, 'shape', None)}")
    if not np.issubdtype(array.dtype, np.floating):
        raise Argoverse2FormatError(npy_path, "array", f"dtype {array.dtype}, expected float16 ground heights")
    height = array.astype(np.float32)
    if np.isinf(height).any():
        r, c = np.argwhere(np.isinf(height))[0]
        raise Argoverse2FormatError(npy_path, "array", f"infinite ground height at row {r}, column {c} (unmapped "
                                    "cells are NaN)")
    height.setflags(write=False)
    rotation, translation, scale = _read_sim2(json_path)
    return GroundRaster(height, rotation, translation, scale, npy_path)


def read_ground_raster(log_dir: str) -> GroundRaster:
    """The log's ground raster and its Sim(2), checked (Argoverse2FormatError naming the file and field otherwise).

    Cached per file (path, size, modification time): a log's sweeps share one read."""
    map_dir = os.path.join(log_dir, "map")
    npy_path = _one_map_file(map_dir, GROUND_RASTER_PATTERN, "ground height raster")
    json_path = _one_map_file(map_dir, SIM2_PATTERN, "raster's Sim(2) (img_Sim2_city)")
    stamp = tuple((os.stat(p).st_size, os.stat(p).st_mtime_ns) for p in (npy_path, json_path))
    return _cached_raster(npy_path, json_path, stamp)


def ground_height_m(log_dir: str, points_xyz_city: np.ndarray) -> np.ndarray:
    """[N] float64 map ground height (city metres) under each city point ([N, 2] or [N, 3]), NaN off the raster or
    where the map has no ground height (outside Argoverse's region of interest), as av2-api's
    `get_ground_height_at_xy`."""
    return read_ground_raster(log_dir).height_at(points_xyz_city)


def is_ground(log_dir: str, points_xyz_ego: np.ndarray, pose_ego_to_city: np.ndarray,
              threshold_m: float = GROUND_HEIGHT_THRESHOLD_M) -> np.ndarray:
    """[N] bool: ego-frame points (a sweep's `points_xyz`) that are ground by Argoverse's rule (av2-api
    `get_ground_points_boolean`): in city coordinates (float64), within `threshold_m` of the map's ground height or
    below it. Points without a ground height (NaN: off the raster or unmapped) are not ground.

    On the sample log this reproduces the `is_ground_0` column of Argoverse's flow labels on 99,228 of 99,229 points;
    the other point lies 0.4 mm before a cell border, which the labels' float32 city transform (0.49 mm steps there)
    put on the far side, in the neighbouring cell."""
    pts = np.asarray(points_xyz_ego)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"is_ground: points must be [N, 3], got shape {pts.shape}")
    city = geometry.transform_points_np(pts, pose_ego_to_city)
    height = ground_height_m(log_dir, city)
    z = city[:, 2]
    with np.errstate(invalid="ignore"):
        return (np.abs(z - height) <= threshold_m) | (z < height)
