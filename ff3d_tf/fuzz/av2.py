"""Fuzzing of the Argoverse 2 reader (`ff3d_tf.data.av2.argoverse2`): a reduced copy of a log, one file damaged per
mutant (bytes, columns, values), then everything a labelled pair reads: the sweep list, both sweeps with their ego
poses and both sweeps' cuboids.

A named error is an `Argoverse2FormatError` naming the damaged file (a deleted file: it or its folder) and a column.
"""
from __future__ import annotations

import os
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather

from ff3d_tf import schema
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.fuzz.report import NONFINITE, Report, check_frame, judge, pick

KINDS = ("bit_flip", "truncate", "not_feather", "missing_file", "drop_column", "wrong_dtype", "nan_value",
         "empty_table", "zero_quaternion")
COLUMNS = {"sweep": tuple(argoverse2.SWEEP_COLUMNS), "annotations.feather": tuple(argoverse2.CUBOID_COLUMNS),
           "city_SE3_egovehicle.feather": tuple(argoverse2.POSE_COLUMNS)}  # the columns the reader reads, per file


def small_copy(src_log: str, dst_log: str, max_points: int = 2000) -> str:
    """A copy of an AV2 log reduced to its first `max_points` points per sweep and the annotations and poses of its
    sweeps (the readers' inputs; fast to fuzz). The source is never written."""
    if os.path.exists(dst_log):
        shutil.rmtree(dst_log)
    os.makedirs(os.path.join(dst_log, "sensors", "lidar"))
    stamps = argoverse2.sweep_timestamps(src_log)
    for ts in stamps:
        table = feather.read_table(os.path.join(src_log, "sensors", "lidar", f"{ts}.feather"))
        feather.write_feather(table.slice(0, max_points), os.path.join(dst_log, "sensors", "lidar", f"{ts}.feather"))
    for name in ("annotations.feather", "city_SE3_egovehicle.feather"):
        table = feather.read_table(os.path.join(src_log, name))
        keep = np.isin(table.column("timestamp_ns").to_numpy(), stamps)
        feather.write_feather(table.filter(keep), os.path.join(dst_log, name))
    return dst_log


def mutate(log_dir: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """Damages one file of a (copied) AV2 log in place: (path of the damaged file, what was done)."""
    stamps = argoverse2.sweep_timestamps(log_dir)
    name = pick(rng, ["sweep", "annotations.feather", "city_SE3_egovehicle.feather"])
    path = (os.path.join(log_dir, "sensors", "lidar", f"{pick(rng, stamps)}.feather") if name == "sweep"
            else os.path.join(log_dir, name))
    if kind in ("bit_flip", "truncate", "not_feather", "missing_file"):
        data = bytearray(open(path, "rb").read())
        if kind == "bit_flip":
            for _ in range(int(rng.integers(1, 17))):
                data[int(rng.integers(len(data)))] ^= 1 << int(rng.integers(8))
        elif kind == "truncate":
            data = data[: int(rng.integers(0, len(data)))]
        elif kind == "not_feather":
            data = bytearray(b"this is not an arrow file " * int(rng.integers(1, 50)))
        if kind == "missing_file":
            os.remove(path)
        else:
            with open(path, "wb") as f:
                f.write(bytes(data))
        return path, f"{kind} of {os.path.basename(path)}"
    table = feather.read_table(path)
    column = pick(rng, list(COLUMNS[name]))
    if kind == "drop_column":
        table = table.drop_columns([column])
    elif kind == "wrong_dtype":
        table = table.set_column(table.schema.get_field_index(column), column,
                                 pa.array(["x"] * table.num_rows, pa.string()))
    elif kind == "nan_value":
        numeric = [c for c in COLUMNS[name] if pa.types.is_floating(table.schema.field(c).type)]
        column = pick(rng, numeric)
        values = table.column(column).to_numpy().astype(np.float64)
        if values.size:
            values[int(rng.integers(values.size))] = float(pick(rng, NONFINITE))
        table = table.set_column(table.schema.get_field_index(column), column,
                                 pa.array(values, table.schema.field(column).type, from_pandas=False)
                                 if not pa.types.is_float16(table.schema.field(column).type)
                                 else pa.array(values.astype(np.float16)))
    elif kind == "empty_table":
        table = table.slice(0, 0)
    elif kind == "zero_quaternion":
        if name == "sweep":
            name, path = "city_SE3_egovehicle.feather", os.path.join(log_dir, "city_SE3_egovehicle.feather")
            table = feather.read_table(path)
        for q in ("qw", "qx", "qy", "qz"):
            table = table.set_column(table.schema.get_field_index(q), q, pa.array(np.zeros(table.num_rows)))
        column = "qw..qz"
    else:
        raise ValueError(f"unknown AV2 mutation kind {kind!r}; one of {KINDS}")
    feather.write_feather(table, path)
    return path, f"{kind} in {os.path.basename(path)} column {column}"


def read_pair(log_dir: str, stamps: list[int]) -> list[tuple[dict, dict]]:
    """(frame, cuboids) of the sweeps `stamps` (t-1, t0) read by the reader alone, after listing the log's sweeps:
    all a labelled pair reads (`read_sweep` reads the sweep's `ego_pose`)."""
    argoverse2.sweep_timestamps(log_dir)
    return [(argoverse2.read_sweep(log_dir, ts), argoverse2.cuboids(log_dir, ts)) for ts in stamps]


def check_cuboids(boxes: dict) -> str | None:
    """None if a cuboids dict is finite and consistent, else what is wrong."""
    n = len(boxes["center"])
    for key in ("center", "size", "heading"):
        if not np.all(np.isfinite(boxes[key])):
            return f"cuboid {key} has non-finite values"
    for key in ("size", "heading", "track_id", "class_id"):
        if len(boxes[key]) != n:
            return f"cuboid {key} has {len(boxes[key])} rows for {n} cuboids"
    if n and (boxes["class_id"].min() < schema.CLASS_BACKGROUND or boxes["class_id"].max() > max(schema.CLASS_NAMES)):
        return "cuboid class_id out of range"
    return None


def classify(call, path: str) -> tuple[str, str]:
    """(outcome, detail) of reading a damaged log: `call()` returns `read_pair`'s sweeps or raises."""
    try:
        sweeps = call()
    except argoverse2.Argoverse2FormatError as err:
        # The damaged file, or (a deleted sweep) the folder that misses it.
        named = (os.path.basename(path) in str(err) or os.path.dirname(path) in str(err)) and bool(err.column)
        return ("named_error" if named else "unnamed_error"), str(err)
    except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
        return "crash", f"{type(err).__name__}: {err}"
    for frame, boxes in sweeps:
        problem = check_frame(frame) or check_cuboids(boxes)
        if problem:
            return "nonfinite", problem
    return "decoded", f"{len(sweeps[-1][0]['points_xyz'])} points, {len(sweeps[-1][1]['center'])} cuboids"


def fuzz_log(sample_log: str, work_dir: str, num_mutants: int, seed: int = 0, max_points: int = 2000,
             report: Report | None = None, hang_s: float | None = None) -> Report:
    """Damages a fresh reduced copy of the AV2 log per mutant and reads its first two sweeps (`read_pair`);
    `hang_s`: the watchdog's bound on one input (None: none)."""
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    clean = small_copy(sample_log, os.path.join(work_dir, "clean"), max_points)
    stamps = argoverse2.sweep_timestamps(clean)[:2]
    for i in range(num_mutants):
        kind = KINDS[i % len(KINDS)]
        log = os.path.join(work_dir, "mutant")
        if os.path.exists(log):
            shutil.rmtree(log)
        shutil.copytree(clean, log)
        path, what = mutate(log, kind, rng)
        judge(report, kind, what, lambda: classify(lambda: read_pair(log, stamps), path), hang_s)
    return report
