"""Argoverse 2 scene-flow submissions: one Feather file per evaluated sweep, zipped, and the check of an archive.

Format (av2-api src/av2/evaluation/scene_flow/SUBMISSION_FORMAT.md @01e6d9585ab28f701f149b8f66f1ab55a0551486, and the
checks of make_submission_archive.py @8a211b92311f4e9c06c11b562f5bf5f704af72fb; facts cited, no code copied):

    <log_id>/<timestamp_ns>.feather      one per evaluated sweep (the first sweep of the pair), nothing else
      flow_tx_m, flow_ty_m, flow_tz_m    float16, metres to the next sweep
      is_dynamic                         bool, the predicted dynamic label (|ego-motion-free flow| >= 0.05 m)

with one row per point of the sweep's eval mask, in the sweep's point order, and exactly these four columns. The
expected row counts come from the challenge's mask files; av2-api ships them per split as
`{val,test}_submission_format.json` ({"<log_id>/<timestamp_ns>.feather": rows}: `expected_counts_from_json`).

The flow of the format includes the ego motion, as Argoverse's labels do (av2-api src/av2/torch/structures/flow.py
@01e6d9585ab28f701f149b8f66f1ab55a0551486; the community evaluator's scripts/av2_eval.py
@672507b3d430335df37ef37ee42439516e7a9883 calls it "uncompensated"): f = (the point's position at the next sweep, in
the next sweep's ego frame) - (its position in the first sweep's ego frame). `av2_flow_from_ego_free` and
`ego_free_from_av2_flow` convert between it and the ego-motion-free displacement d in the first sweep's ego frame
that `ff3d_tf.metrics_av2` and the model use: f = T (p + d) - p, d = T^-1 (p + f) - p, with T = ego1_from_ego0 =
`geometry.t0_from_tm1_np(pose_sweep1, pose_sweep0)` (sweep-0 ego coordinates -> sweep-1 ego coordinates).

This is av2-api's format (the 2023 leaderboard, and what the community evaluator's scripts/av2_eval.py above reads
against the official masks). The 2024 leaderboard's scripts/evals/av2_eval.py reads another layout (every 5th sweep,
files shaped like its supervised labels: docs/AV2_EVAL_FORMAT.md @33450ec296e96e3ad96bb7edcc7d013a41a2d3e2).

Files are written through a temporary name and renamed, so an interrupted job leaves whole files only; rerunning it
rewrites them. `make_archive` zips a folder and validates its own archive before it replaces the target.
"""
from __future__ import annotations

import json
import os
import re
import zipfile
from typing import Callable

import numpy as np

from ff3d_tf import geometry
from ff3d_tf.data.av2 import argoverse2

FLOW_COLUMNS = tuple(argoverse2.FLOW_COLUMNS)  # flow_tx_m, flow_ty_m, flow_tz_m: the names of Argoverse's labels
DYNAMIC_COLUMN = "is_dynamic"
SUBMISSION_COLUMNS = FLOW_COLUMNS + (DYNAMIC_COLUMN,)
FLOAT16_MAX = float(np.finfo(np.float16).max)  # 65504
_LOG_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")  # AV2 log ids are UUIDs
_ENTRY = re.compile(r"^([A-Za-z0-9][A-Za-z0-9_-]*)/(0|[1-9][0-9]*)\.feather$")  # no leading zeros: names match exactly

SweepKey = tuple[str, int]  # (log_id, timestamp_ns)


class SubmissionFormatError(ValueError):
    """A submission file or archive entry that breaks the format: names the file (archive:entry), the field and
    what is wrong."""

    def __init__(self, path: str, field: str, reason: str):
        self.path, self.field, self.reason = path, field, reason
        super().__init__(f"{path}: {field}: {reason}")


def av2_flow_from_ego_free(points_xyz_t0, flow_m_ego_free, ego1_from_ego0) -> np.ndarray:
    """[N,3] float64 submission flow f = T (p + d) - p from the ego-motion-free displacement d (metres, sweep-0 ego
    frame) of the sweep-0 points p [N,3] (sweep-0 ego frame), T = ego1_from_ego0 [4,4]."""
    p = np.asarray(points_xyz_t0, np.float64)
    return geometry.transform_points_np(p + np.asarray(flow_m_ego_free, np.float64), ego1_from_ego0) - p


def ego_free_from_av2_flow(points_xyz_t0, flow_m_av2, ego1_from_ego0) -> np.ndarray:
    """[N,3] float64 ego-motion-free displacement d = T^-1 (p + f) - p (sweep-0 ego frame) of a submission or
    Argoverse-label flow f; the inverse of `av2_flow_from_ego_free`."""
    p = np.asarray(points_xyz_t0, np.float64)
    ego0_from_ego1 = np.linalg.inv(np.asarray(ego1_from_ego0, np.float64))
    return geometry.transform_points_np(p + np.asarray(flow_m_av2, np.float64), ego0_from_ego1) - p


def sweep_entry(log_id: str, timestamp_ns: int) -> str:
    """The archive entry (and folder-relative path) of a sweep: "<log_id>/<timestamp_ns>.feather"."""
    if not isinstance(log_id, str) or not _LOG_ID.match(log_id):
        raise SubmissionFormatError(str(log_id), "log_id", "must be letters, digits, '-' or '_' (an AV2 log id)")
    if int(timestamp_ns) < 0:
        raise SubmissionFormatError(log_id, "timestamp_ns", f"{timestamp_ns} is negative")
    return f"{log_id}/{int(timestamp_ns)}.feather"


def write_sweep(root: str, log_id: str, timestamp_ns: int, flow_m_av2, is_dynamic) -> str:
    """Write one sweep's file under `root` (flow [N,3] in the submission's convention, metres; is_dynamic [N] bool;
    rows in the order of the sweep's eval-mask points) and return its path."""
    import pyarrow as pa
    import pyarrow.feather as feather
    entry = sweep_entry(log_id, timestamp_ns)
    path = os.path.join(root, *entry.split("/"))
    flow = np.asarray(flow_m_av2, np.float64)
    dyn = np.asarray(is_dynamic)
    if flow.ndim != 2 or flow.shape[1] != 3:
        raise SubmissionFormatError(path, "flow", f"shape {flow.shape}, expected [N, 3]")
    if dyn.shape != (len(flow),) or dyn.dtype != bool:
        raise SubmissionFormatError(path, DYNAMIC_COLUMN, f"shape {dyn.shape} dtype {dyn.dtype}, expected bool "
                                    f"[{len(flow)}]")
    bad = ~np.isfinite(flow) | (np.abs(flow) > FLOAT16_MAX)
    if np.any(bad):
        row, col = np.argwhere(bad)[0]
        raise SubmissionFormatError(path, FLOW_COLUMNS[col], f"{flow[row, col]} at row {row} is not a finite "
                                    f"float16 (|v| <= {FLOAT16_MAX:g})")
    table = pa.table({**{c: pa.array(flow[:, i].astype(np.float16)) for i, c in enumerate(FLOW_COLUMNS)},
                      DYNAMIC_COLUMN: pa.array(dyn)})
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + ".tmp"
    feather.write_feather(table, tmp)
    os.replace(tmp, path)
    return path


def _check_table(data: bytes, where: str, expected_rows: int | None) -> dict[str, np.ndarray]:
    """The columns of one submission file (bytes), checked against the format; raises naming `where` and the field."""
    import pyarrow as pa
    import pyarrow.feather as feather
    try:
        table = feather.read_table(pa.BufferReader(data))
        table.validate(full=True)
    except (pa.ArrowException, OSError, ValueError) as err:
        raise SubmissionFormatError(where, "file", f"not a readable Feather (Arrow IPC) file ({type(err).__name__})"
                                    ) from None
    names = table.schema.names
    for c in SUBMISSION_COLUMNS:
        if c not in names:
            raise SubmissionFormatError(where, f"column {c}", f"missing; the file has {names}")
    extra = [n for n in names if n not in SUBMISSION_COLUMNS]
    if extra or len(names) != len(SUBMISSION_COLUMNS):
        raise SubmissionFormatError(where, f"column {extra[0] if extra else names}",
                                    f"not allowed: exactly {list(SUBMISSION_COLUMNS)} (no repeats)")
    out = {}
    for c in SUBMISSION_COLUMNS:
        col = table.column(c)
        want = pa.bool_() if c == DYNAMIC_COLUMN else pa.float16()
        if col.type != want:
            raise SubmissionFormatError(where, f"column {c}", f"type {col.type}, expected {want}")
        if col.null_count:
            raise SubmissionFormatError(where, f"column {c}", f"{col.null_count} null values")
        values = col.to_numpy(zero_copy_only=False)
        if c != DYNAMIC_COLUMN and not np.all(np.isfinite(values)):
            raise SubmissionFormatError(where, f"column {c}",
                                        f"non-finite value at row {int(np.argmin(np.isfinite(values)))}")
        out[c] = values
    if expected_rows is not None and table.num_rows != expected_rows:
        raise SubmissionFormatError(where, "rows", f"{table.num_rows} rows, the sweep's eval mask has "
                                    f"{expected_rows} points")
    return out


def validate_archive(zip_path: str, expected_counts: dict[SweepKey, int] | None = None,
                     progress: Callable[[int, int], None] | None = None) -> dict[str, int]:
    """Check a submission zip: only "<log_id>/<timestamp_ns>.feather" entries (folders allowed), no duplicates, each
    file of the format; with `expected_counts` ({(log_id, timestamp_ns): eval-mask points}) also every expected sweep
    present, no other sweep, and each file's row count. Returns {"sweeps", "rows", "logs"}; raises
    SubmissionFormatError naming the archive entry ("<zip>:<log_id>/<timestamp_ns>.feather") and field.
    `progress(done, total)` is called after each file checked."""
    return _validate(zip_path, expected_counts, zip_path, progress)


def _validate(zip_path: str, expected_counts: dict[SweepKey, int] | None, shown: str,
              progress: Callable[[int, int], None] | None) -> dict[str, int]:
    try:
        zf = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError) as err:
        raise SubmissionFormatError(shown, "file", f"not a readable zip archive ({type(err).__name__})") from None
    with zf:
        seen: dict[SweepKey, str] = {}
        for info in zf.infolist():
            name = info.filename
            if name.endswith("/"):
                if _LOG_ID.match(name[:-1]):
                    continue
                raise SubmissionFormatError(f"{shown}:{name}", "file", "unexpected folder: only <log_id>/")
            m = _ENTRY.match(name)
            if not m:
                raise SubmissionFormatError(f"{shown}:{name}", "file",
                                            "unexpected file: entries must be <log_id>/<timestamp_ns>.feather")
            key = (m.group(1), int(m.group(2)))
            if key in seen:
                raise SubmissionFormatError(f"{shown}:{name}", "file", "duplicate entry for this sweep")
            if expected_counts is not None and key not in expected_counts:
                raise SubmissionFormatError(f"{shown}:{name}", "file", "extra file: not an evaluated sweep")
            seen[key] = name
        if expected_counts is not None:
            missing = sorted(set(expected_counts) - set(seen))
            if missing:
                raise SubmissionFormatError(f"{shown}:{sweep_entry(*missing[0])}", "file",
                                            f"missing ({len(missing)} evaluated sweeps missing in all)")
        rows = 0
        for done, (key, name) in enumerate(sorted(seen.items()), 1):
            where = f"{shown}:{name}"
            try:
                data = zf.read(name)
            except (zipfile.BadZipFile, OSError, ValueError) as err:  # CRC mismatch, truncation
                raise SubmissionFormatError(where, "file", f"unreadable entry ({type(err).__name__})") from None
            cols = _check_table(data, where, None if expected_counts is None else int(expected_counts[key]))
            rows += len(cols[DYNAMIC_COLUMN])
            if progress is not None:
                progress(done, len(seen))
    return {"sweeps": len(seen), "rows": rows, "logs": len({k[0] for k in seen})}


def read_sweep(zip_path: str, log_id: str, timestamp_ns: int) -> dict[str, np.ndarray]:
    """One sweep of a submission zip, checked: {"flow_m_av2": [N,3] float16, "is_dynamic": [N] bool}."""
    entry = sweep_entry(log_id, timestamp_ns)
    with zipfile.ZipFile(zip_path) as zf:
        try:
            data = zf.read(entry)
        except KeyError:
            raise SubmissionFormatError(f"{zip_path}:{entry}", "file", "missing") from None
    cols = _check_table(data, f"{zip_path}:{entry}", None)
    return {"flow_m_av2": np.stack([cols[c] for c in FLOW_COLUMNS], -1), "is_dynamic": cols[DYNAMIC_COLUMN]}


def make_archive(root: str, zip_path: str, expected_counts: dict[SweepKey, int] | None = None,
                 progress: Callable[[int, int], None] | None = None) -> dict[str, int]:
    """Zip the submission folder `root` (every file must be a <log_id>/<timestamp_ns>.feather written by
    `write_sweep`), validate the archive itself (`validate_archive`) and only then move it to `zip_path`. Returns the
    validation summary; on a failure the error names the file and `zip_path` is left as it was. `progress(done,
    total)` follows the validation."""
    entries = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for fn in sorted(filenames):
            rel = os.path.relpath(os.path.join(dirpath, fn), root).replace(os.sep, "/")
            if not _ENTRY.match(rel):
                raise SubmissionFormatError(os.path.join(root, rel), "file",
                                            "unexpected file in the submission folder: only <log_id>/<timestamp_ns>"
                                            ".feather")
            entries.append(rel)
    tmp = zip_path + ".tmp"
    try:
        # Stored, not deflated: the Feather files are compressed already (LZ4, pyarrow's default).
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
            for rel in entries:
                zf.write(os.path.join(root, *rel.split("/")), arcname=rel)
        summary = _validate(tmp, expected_counts, zip_path, progress)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, zip_path)
    return summary


def expected_counts_from_json(path: str) -> dict[SweepKey, int]:
    """{(log_id, timestamp_ns): rows} from av2-api's {"<log_id>/<timestamp_ns>.feather": rows} JSON."""
    with open(path, encoding="utf-8") as f:
        try:
            raw = json.load(f)
        except json.JSONDecodeError as err:
            raise SubmissionFormatError(path, "file", f"not JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(raw, dict):
        raise SubmissionFormatError(path, "file", "expected an object {\"<log_id>/<timestamp_ns>.feather\": rows}")
    out = {}
    for name, rows in raw.items():
        m = _ENTRY.match(name)
        if not m:
            raise SubmissionFormatError(path, f"key {name!r}", "expected <log_id>/<timestamp_ns>.feather")
        if not isinstance(rows, int) or isinstance(rows, bool) or rows < 0:
            raise SubmissionFormatError(path, f"key {name!r}", f"row count {rows!r} is not an integer >= 0")
        out[(m.group(1), int(m.group(2)))] = rows
    return out
