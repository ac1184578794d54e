"""Argoverse 2 sensor-log reader (sweeps, cuboids, poses) yielding the same frame dicts as the WOD reader.

Layout (Wilson et al., NeurIPS Datasets and Benchmarks 2021; av2-api): `sensors/lidar/<timestamp_ns>.feather` (x, y, z
in the ego-vehicle frame, intensity 0..255, laser_number, offset_ns), `annotations.feather` (tracked cuboids, ego frame
of their timestamp, quaternion rotation), `city_SE3_egovehicle.feather` (ego -> city pose per timestamp).
Cuboids are reduced to yaw-only boxes (their roll and pitch are ~0 by construction of the annotation).
"""
from __future__ import annotations

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
    """Boxes dict (`ff3d_tf.labels.box_flow` layout) of the cuboids annotated at a sweep, in its ego frame.

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
