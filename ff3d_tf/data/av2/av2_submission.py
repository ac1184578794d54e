"""Argoverse 2 scene-flow submissions in the three leaderboard layouts, the official point masks, and the check of an
archive against both.

The layouts (`LAYOUTS`; sources below, facts cited, no code copied). "Ego-motion-free" flow d is the point's
displacement over the pair with the ego motion removed, in the first sweep's ego frame (a static point has d = 0);
"ego motion included" flow is f = T (p + d) - p, the point's position at the next sweep in the next sweep's ego frame
less its position p in the first sweep's ego frame, with T = ego1_from_ego0 (`av2_flow_from_ego_free`). Both are
metres over the pair (AV2 sweeps are ~0.1 s apart; nothing is divided by the time).

    v1 (av2-api, the 2023 leaderboard)  <log_id>/<timestamp_ns>.feather per sweep of the official mask archive
        flow_tx_m, flow_ty_m, flow_tz_m   float16, ego motion included          [1] [2] [5]
        is_dynamic                        bool, |d| >= 0.05 m                   [1]
        one row per True value of the sweep's mask, in the sweep's point order; exactly these four columns [2]
    v2 (bucketed_scene_flow_eval, the 2024 leaderboard)  metadata.json ({"Is Supervised?": bool}) and
        <log_id>/<sweep index, 10 digits>.feather for sweep indices 0, 5, 10, ... of each log (the index of the
        first sweep among the log's sweeps; ceil((sweeps - 1) / 5) files a log)          [6] [7] [9]
        is_valid                          bool, True: a prediction for the point [6] [8]
        flow_tx_m, flow_ty_m, flow_tz_m   float16, ego-motion-free              [8] [10]
        one row per point of the sweep (ground included), in point order           [7] [8]
    v3 (OpenSceneFlow's writer, the 2026 leaderboard)  <log_id>/<timestamp_ns>.feather per sweep of the official
        mask archive                                                               [11]
        flow_tx_m, flow_ty_m, flow_tz_m   float16, ego-motion-free, nothing else [8] [10]
        one row per point of the sweep (ground included), in point order           [10]

The official masks (`MaskArchive`): `{val,test}-masks.zip` from Argoverse's scene-flow task files
(`s3://argoverse/tasks/3d_scene_flow/zips/`, no account needed [11]): `<log_id>/<timestamp_ns>.feather`, one per
evaluated sweep, one boolean column (named `mask` [3] [5]) over every point of the sweep in its point order [4]. The
sweeps of v1 and v3 and the rows of v1 are the archive's; av2-api warns never to compute them for a submission [4].
Without it, for local validation only, `av2_api_rule_subset` and `av2_api_rule_mask` reproduce av2-api's rule: every
5th pair of the split ([::5] over the pairs in the data loader's order, logs then time [4] [12]), and the points with
|x|, |y| <= 50 m that are not ground [4]. Argoverse's validator [2] reads each mask and expects that many rows; it
ships the counts as `{val,test}_submission_format.json` ({"<log_id>/<timestamp_ns>.feather": rows},
`expected_counts_from_json`).

Sources:
 [1] argoverse/av2-api src/av2/evaluation/scene_flow/SUBMISSION_FORMAT.md @01e6d9585ab28f701f149b8f66f1ab55a0551486
 [2] argoverse/av2-api src/av2/evaluation/scene_flow/make_submission_archive.py
     @8a211b92311f4e9c06c11b562f5bf5f704af72fb (columns and dtypes, at most 4 columns, rows = the mask's sum)
 [3] argoverse/av2-api src/av2/evaluation/scene_flow/make_mask_files.py @01e6d9585ab28f701f149b8f66f1ab55a0551486
 [4] argoverse/av2-api src/av2/evaluation/scene_flow/utils.py @8a211b92311f4e9c06c11b562f5bf5f704af72fb
     (`get_eval_subset`, `get_eval_point_mask`, `compute_eval_point_mask`)
 [5] kylevedder/BucketedSceneFlowEval scripts/av2_eval.py @672507b3d430335df37ef37ee42439516e7a9883 (reads v1
     against the masks: column `mask`, the flow "uncompensated", added to the first sweep and moved by the second
     sweep's pose)
 [6] kylevedder/BucketedSceneFlowEval docs/AV2_EVAL_FORMAT.md @33450ec296e96e3ad96bb7edcc7d013a41a2d3e2 (every 5th
     frame, files like the supervised labels without `classes`) and scripts/evals/setup_sparse_user_submission.py
     @3442400422cf5e0b86aa5c224f04f9562f27e3de (10-digit names, index % 5 == 0, ceil(n / 5) files per log)
 [7] kylevedder/BucketedSceneFlowEval bucketed_scene_flow_eval/datasets/argoverse2/argoverse_scene_flow.py
     @01e17bbceced5fe192c28a80d701664781aeae25 (reads is_valid and the flow columns over every point, files by order)
 [8] KTH-RPL/OpenSceneFlow src/utils/av2_eval.py @2a9c474f2455672bca5d235cae77a46d2d36c9fa (`write_output_file`:
     the columns and dtypes of versions 1, 2 and 3)
 [9] KTH-RPL/OpenSceneFlow src/utils/mics.py @10f45bd069959afd84ec0d1747727a5f83a46750 (`zip_res`: metadata.json,
     indices 0, 5, 10, ... for version 2; timestamp names for version 3)
[10] KTH-RPL/OpenSceneFlow src/trainer.py @1c8fc5a201c3f030ed854fd627aa937160ed7a74 (version 1: ego motion included
     on the mask's points; versions 2 and 3: the flow less the ego motion's, over every point)
[11] KTH-RPL/OpenSceneFlow dataprocess/extract_av2.py @087691f119048af3bde4b75a771199a81b670204 (where the masks come
     from; the evaluated sweeps are the mask archive's)
[12] argoverse/av2-api src/av2/torch/data_loaders/scene_flow.py @1eb12b94f9c69b0efdf2250602957098c389ebba (a pair per
     sweep that has a next sweep in its log)

Files are written through a temporary name and renamed, so an interrupted job leaves whole files only.
`make_archive` zips a folder and validates its own archive before it replaces the target. A folder of sweeps being
written carries the fingerprint of what writes them (`claim_parts`: the model, the config, the records, the layout
and the masks): a run resumes only the sweeps of its own fingerprint, and refuses a folder of another.
"""
from __future__ import annotations

import dataclasses
import json
import os
import re
import zipfile
from typing import Callable, Iterable

import numpy as np

from ff3d_tf import geometry
from ff3d_tf.data.av2 import argoverse2

FLOW_COLUMNS = tuple(argoverse2.FLOW_COLUMNS)  # flow_tx_m, flow_ty_m, flow_tz_m: the names of Argoverse's labels
DYNAMIC_COLUMN = "is_dynamic"
VALID_COLUMN = "is_valid"
SUBMISSION_COLUMNS = FLOW_COLUMNS + (DYNAMIC_COLUMN,)  # v1
FLOAT16_MAX = float(np.finfo(np.float16).max)  # 65504
DYNAMIC_THRESHOLD_M = argoverse2.SCENE_FLOW_DYNAMIC_THRESHOLD_M  # is_dynamic: |ego-motion-free flow| >= 0.05 m
EVERY_KTH = 5  # both evaluated subsets keep every 5th pair
AV2_API_RULE_HALF_WIDTH_M = 50.0  # av2-api's eval mask: |x|, |y| <= 50 m and not ground
METADATA_NAME = "metadata.json"  # v2's archive root file
SUPERVISED_KEY = "Is Supervised?"
MASKS_SOURCE = ("the official masks are Argoverse's {val,test}-masks.zip: s5cmd --no-sign-request cp "
                "\"s3://argoverse/tasks/3d_scene_flow/zips/*\" . (docs/datasets.md, Argoverse 2)")
_LOG_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*$")  # AV2 log ids are UUIDs
_ENTRY = re.compile(r"^([A-Za-z0-9][A-Za-z0-9_-]*)/(0|[1-9][0-9]*)\.feather$")  # no leading zeros: names match exactly
_INDEX_ENTRY = re.compile(r"^([A-Za-z0-9][A-Za-z0-9_-]*)/([0-9]{10})\.feather$")

SweepKey = tuple[str, int]  # (log_id, timestamp_ns)


class SubmissionFormatError(ValueError):
    """A submission or mask file or archive entry that breaks its format, or disagrees with the records: names the
    file (archive:entry), the field and what is wrong."""

    def __init__(self, path: str, field: str, reason: str):
        self.path, self.field, self.reason = path, field, reason
        super().__init__(f"{path}: {field}: {reason}")


@dataclasses.dataclass(frozen=True)
class Layout:
    """What one leaderboard reads (module doc): entry names, columns, flow convention, rows, evaluated sweeps."""

    name: str
    columns: tuple[str, ...]  # exactly these, in this order when written
    flow_includes_ego_motion: bool  # True: f = T (p + d) - p; False: d (ego-motion-free), first sweep's ego frame
    mask_rows: bool  # True: one row per True value of the official mask; False: one row per point of the sweep
    indexed_entries: bool  # True: <log_id>/<sweep index:010d>.feather; False: <log_id>/<timestamp_ns>.feather
    masks_choose_sweeps: bool  # True: the mask archive's sweeps; False: sweep indices 0, 5, 10, ... of each log
    metadata_json: bool  # the archive holds METADATA_NAME
    leaderboard: str
    spec: str  # where the facts come from (module doc)

    def entry(self, log_id: str, timestamp_ns: int, sweep_index: int | None = None) -> str:
        return indexed_entry(log_id, sweep_index) if self.indexed_entries else sweep_entry(log_id, timestamp_ns)


LAYOUTS = {
    "v1": Layout("v1", columns=SUBMISSION_COLUMNS, flow_includes_ego_motion=True, mask_rows=True,
                 indexed_entries=False, masks_choose_sweeps=True, metadata_json=False,
                 leaderboard="Argoverse 2 scene flow 2023 (av2-api)",
                 spec="av2-api SUBMISSION_FORMAT.md, make_submission_archive.py, utils.py [1] [2] [4]"),
    "v2": Layout("v2", columns=(VALID_COLUMN,) + FLOW_COLUMNS, flow_includes_ego_motion=False, mask_rows=False,
                 indexed_entries=True, masks_choose_sweeps=False, metadata_json=True,
                 leaderboard="Argoverse 2 scene flow 2024 (bucketed_scene_flow_eval)",
                 spec="BucketedSceneFlowEval AV2_EVAL_FORMAT.md, setup_sparse_user_submission.py, "
                      "argoverse_scene_flow.py; OpenSceneFlow write_output_file, zip_res, trainer, version 2 [6]-[10]"),
    "v3": Layout("v3", columns=FLOW_COLUMNS, flow_includes_ego_motion=False, mask_rows=False, indexed_entries=False,
                 masks_choose_sweeps=True, metadata_json=False, leaderboard="scene flow 2026 (OpenSceneFlow's writer)",
                 spec="OpenSceneFlow write_output_file, zip_res, trainer, extract_av2.py, version 3 [8] [9] [10] [11]"),
}


def layout(name: str) -> Layout:
    """The layout of a leaderboard, "v1", "v2" or "v3"."""
    if name not in LAYOUTS:
        raise ValueError(f"leaderboard {name!r}: expected one of {sorted(LAYOUTS)}")
    return LAYOUTS[name]


# --- Flow conventions ------------------------------------------------------------------------------------------------

def av2_flow_from_ego_free(points_xyz_t0, flow_m_ego_free, ego1_from_ego0) -> np.ndarray:
    """[N,3] float64 flow with the ego motion included, f = T (p + d) - p, from the ego-motion-free displacement d
    (metres, sweep-0 ego frame) of the sweep-0 points p [N,3] (sweep-0 ego frame), T = ego1_from_ego0 [4,4]."""
    p = np.asarray(points_xyz_t0, np.float64)
    return geometry.transform_points_np(p + np.asarray(flow_m_ego_free, np.float64), ego1_from_ego0) - p


def ego_free_from_av2_flow(points_xyz_t0, flow_m_av2, ego1_from_ego0) -> np.ndarray:
    """[N,3] float64 ego-motion-free displacement d = T^-1 (p + f) - p (sweep-0 ego frame) of a v1 or Argoverse-label
    flow f; the inverse of `av2_flow_from_ego_free`."""
    p = np.asarray(points_xyz_t0, np.float64)
    ego0_from_ego1 = np.linalg.inv(np.asarray(ego1_from_ego0, np.float64))
    return geometry.transform_points_np(p + np.asarray(flow_m_av2, np.float64), ego0_from_ego1) - p


def sweep_columns(lay: Layout, points_xyz_t0, flow_m_ego_free, ego1_from_ego0, rows=None) -> dict[str, np.ndarray]:
    """The columns of one sweep's file in layout `lay`, from the ego-motion-free displacement d [N,3] (metres over the
    pair, sweep-0 ego frame) of the sweep's points p [N,3]: for v1, f = T (p + d) - p and is_dynamic (|d| >= 0.05 m)
    on the rows where `rows` [N] bool (the sweep's official mask) is True, in point order; for v2, is_valid (True)
    and d on every point; for v3, d on every point. Flow columns float16."""
    p = np.asarray(points_xyz_t0, np.float64)
    d = np.asarray(flow_m_ego_free, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or d.shape != p.shape:
        raise ValueError(f"points {p.shape} and flow {d.shape}: expected two [N, 3] arrays")
    if lay.mask_rows:
        rows = np.asarray(rows)
        if rows.shape != (len(p),) or rows.dtype != bool:
            raise ValueError(f"rows: shape {rows.shape} dtype {rows.dtype}, expected the sweep's mask, bool [{len(p)}]")
        p, d = p[rows], d[rows]
    flow = av2_flow_from_ego_free(p, d, ego1_from_ego0) if lay.flow_includes_ego_motion else d
    out = {}
    if VALID_COLUMN in lay.columns:
        out[VALID_COLUMN] = np.ones(len(p), bool)
    out.update({c: flow[:, i] for i, c in enumerate(FLOW_COLUMNS)})
    if DYNAMIC_COLUMN in lay.columns:
        out[DYNAMIC_COLUMN] = np.linalg.norm(d, axis=1) >= DYNAMIC_THRESHOLD_M
    return out


# --- Entries and files -----------------------------------------------------------------------------------------------

def _check_log_id(log_id) -> None:
    if not isinstance(log_id, str) or not _LOG_ID.match(log_id):
        raise SubmissionFormatError(str(log_id), "log_id", "must be letters, digits, '-' or '_' (an AV2 log id)")


def sweep_entry(log_id: str, timestamp_ns: int) -> str:
    """The v1 / v3 archive entry (and folder-relative path) of a sweep: "<log_id>/<timestamp_ns>.feather"."""
    _check_log_id(log_id)
    if int(timestamp_ns) < 0:
        raise SubmissionFormatError(log_id, "timestamp_ns", f"{timestamp_ns} is negative")
    return f"{log_id}/{int(timestamp_ns)}.feather"


def indexed_entry(log_id: str, sweep_index: int) -> str:
    """The v2 archive entry of the sweep at `sweep_index` of its log (a multiple of 5): "<log_id>/<index:010d>.feather"."""
    _check_log_id(log_id)
    if sweep_index is None or int(sweep_index) < 0 or int(sweep_index) % EVERY_KTH or int(sweep_index) >= 10 ** 10:
        raise SubmissionFormatError(log_id, "sweep_index", f"{sweep_index} is not a multiple of {EVERY_KTH} in "
                                    "0..9999999999")
    return f"{log_id}/{int(sweep_index):010d}.feather"


def write_sweep(root: str, lay: Layout, entry: str, columns: dict[str, np.ndarray]) -> str:
    """Write one sweep's file `<root>/<entry>` in layout `lay` (`sweep_columns` gives the columns; flows in metres,
    stored float16) through a temporary name; returns its path."""
    import pyarrow as pa
    import pyarrow.feather as feather
    path = os.path.join(root, *entry.split("/"))
    if sorted(columns) != sorted(lay.columns):
        raise SubmissionFormatError(path, "columns", f"{sorted(columns)}, layout {lay.name} has {list(lay.columns)}")
    n = len(columns[lay.columns[0]])
    arrays = {}
    for c in lay.columns:
        v = np.asarray(columns[c])
        if v.shape != (n,):
            raise SubmissionFormatError(path, f"column {c}", f"shape {v.shape}, expected [{n}]")
        if c in FLOW_COLUMNS:
            v = v.astype(np.float64)
            bad = ~np.isfinite(v) | (np.abs(v) > FLOAT16_MAX)
            if np.any(bad):
                row = int(np.argmax(bad))
                raise SubmissionFormatError(path, f"column {c}", f"{v[row]} at row {row} is not a finite float16 "
                                            f"(|v| <= {FLOAT16_MAX:g})")
            arrays[c] = pa.array(v.astype(np.float16))
        else:
            if v.dtype != bool:
                raise SubmissionFormatError(path, f"column {c}", f"dtype {v.dtype}, expected bool")
            arrays[c] = pa.array(v)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    tmp = path + ".tmp"
    feather.write_feather(pa.table(arrays), tmp)
    os.replace(tmp, path)
    return path


def _read_table(data: bytes, where: str):
    import pyarrow as pa
    import pyarrow.feather as feather
    try:
        table = feather.read_table(pa.BufferReader(data))
        table.validate(full=True)
    except (pa.ArrowException, OSError, ValueError) as err:
        raise SubmissionFormatError(where, "file", f"not a readable Feather (Arrow IPC) file ({type(err).__name__})"
                                    ) from None
    return table


def _check_table(data: bytes, where: str, lay: Layout, expected_rows: int | None) -> dict[str, np.ndarray]:
    """The columns of one submission file (bytes), checked against layout `lay`; raises naming `where` and the field."""
    import pyarrow as pa
    table = _read_table(data, where)
    names = table.schema.names
    for c in lay.columns:
        if c not in names:
            raise SubmissionFormatError(where, f"column {c}", f"missing; the file has {names}")
    extra = [n for n in names if n not in lay.columns]
    if extra or len(names) != len(lay.columns):
        raise SubmissionFormatError(where, f"column {extra[0] if extra else names}",
                                    f"not allowed: exactly {list(lay.columns)} (no repeats)")
    out = {}
    for c in lay.columns:
        col = table.column(c)
        want = pa.float16() if c in FLOW_COLUMNS else pa.bool_()
        if col.type != want:
            raise SubmissionFormatError(where, f"column {c}", f"type {col.type}, expected {want}")
        if col.null_count:
            raise SubmissionFormatError(where, f"column {c}", f"{col.null_count} null values")
        values = col.to_numpy(zero_copy_only=False)
        if c in FLOW_COLUMNS and not np.all(np.isfinite(values)):
            raise SubmissionFormatError(where, f"column {c}",
                                        f"non-finite value at row {int(np.argmin(np.isfinite(values)))}")
        out[c] = values
    if expected_rows is not None and table.num_rows != expected_rows:
        what = "the sweep's official mask has" if lay.mask_rows else "the sweep has"
        raise SubmissionFormatError(where, "rows", f"{table.num_rows} rows, {what} {expected_rows} points")
    return out


def _entry_key(lay: Layout, name: str) -> tuple[str, int] | None:
    """(log_id, timestamp_ns or sweep index) of an entry name of the layout; None if the name is not one."""
    m = (_INDEX_ENTRY if lay.indexed_entries else _ENTRY).match(name)
    if not m or (lay.indexed_entries and int(m.group(2)) % EVERY_KTH):
        return None
    return m.group(1), int(m.group(2))


def _check_metadata(data: bytes, where: str) -> bool:
    try:
        meta = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise SubmissionFormatError(where, "file", "not a JSON file") from None
    if not isinstance(meta, dict) or not isinstance(meta.get(SUPERVISED_KEY), bool):
        raise SubmissionFormatError(where, SUPERVISED_KEY, f"expected {{\"{SUPERVISED_KEY}\": true or false}}")
    return meta[SUPERVISED_KEY]


def validate_archive(zip_path: str, lay: Layout, expected_rows: dict[str, int] | None = None,
                     progress: Callable[[int, int], None] | None = None) -> dict[str, int]:
    """Check a submission zip in layout `lay`: only the layout's entries (folders allowed; v2 also its metadata.json),
    no duplicates, each file of the layout; with `expected_rows` ({entry: rows}) also every expected entry present,
    no other, and each file's row count. Returns {"sweeps", "rows", "logs"}; raises SubmissionFormatError naming the
    archive entry ("<zip>:<entry>") and field. `progress(done, total)` is called after each file checked."""
    return _validate(zip_path, lay, expected_rows, zip_path, progress)


def _validate(zip_path: str, lay: Layout, expected_rows: dict[str, int] | None, shown: str,
              progress: Callable[[int, int], None] | None) -> dict[str, int]:
    try:
        zf = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError) as err:
        raise SubmissionFormatError(shown, "file", f"not a readable zip archive ({type(err).__name__})") from None
    kind = "<log_id>/<10-digit sweep index, a multiple of 5>.feather" if lay.indexed_entries else \
        "<log_id>/<timestamp_ns>.feather"
    with zf:
        seen: dict[str, str] = {}
        metadata = None
        for info in zf.infolist():
            name = info.filename
            if name.endswith("/"):
                if _LOG_ID.match(name[:-1]):
                    continue
                raise SubmissionFormatError(f"{shown}:{name}", "file", "unexpected folder: only <log_id>/")
            if lay.metadata_json and name == METADATA_NAME:
                if metadata is not None:
                    raise SubmissionFormatError(f"{shown}:{name}", "file", "duplicate entry")
                metadata = name
                continue
            if _entry_key(lay, name) is None:
                raise SubmissionFormatError(f"{shown}:{name}", "file",
                                            f"unexpected file: layout {lay.name} entries are {kind}")
            if name in seen:
                raise SubmissionFormatError(f"{shown}:{name}", "file", "duplicate entry for this sweep")
            if expected_rows is not None and name not in expected_rows:
                raise SubmissionFormatError(f"{shown}:{name}", "file", "extra file: not an evaluated sweep")
            seen[name] = name
        if lay.metadata_json:
            if metadata is None:
                raise SubmissionFormatError(f"{shown}:{METADATA_NAME}", "file",
                                            f"missing (layout {lay.name} needs {{\"{SUPERVISED_KEY}\": bool}})")
            _check_metadata(_read_entry(zf, metadata, shown), f"{shown}:{metadata}")
        if expected_rows is not None:
            missing = sorted(set(expected_rows) - set(seen))
            if missing:
                raise SubmissionFormatError(f"{shown}:{missing[0]}", "file",
                                            f"missing ({len(missing)} evaluated sweeps missing in all)")
        rows = 0
        for done, name in enumerate(sorted(seen), 1):
            cols = _check_table(_read_entry(zf, name, shown), f"{shown}:{name}", lay,
                                None if expected_rows is None else int(expected_rows[name]))
            rows += len(cols[lay.columns[0]])
            if progress is not None:
                progress(done, len(seen))
    return {"sweeps": len(seen), "rows": rows, "logs": len({n.split("/")[0] for n in seen})}


def _read_entry(zf: zipfile.ZipFile, name: str, shown: str) -> bytes:
    try:
        return zf.read(name)
    except KeyError:
        raise SubmissionFormatError(f"{shown}:{name}", "file", "missing") from None
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:  # CRC mismatch, truncation
        raise SubmissionFormatError(f"{shown}:{name}", "file", f"unreadable entry ({type(err).__name__})") from None


def read_sweep(zip_path: str, lay: Layout, entry: str) -> dict[str, np.ndarray]:
    """One entry of a submission zip, checked against layout `lay`: {column: values}."""
    try:
        zf = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError) as err:
        raise SubmissionFormatError(zip_path, "file", f"not a readable zip archive ({type(err).__name__})") from None
    with zf:
        data = _read_entry(zf, entry, zip_path)
    return _check_table(data, f"{zip_path}:{entry}", lay, None)


def read_sweep_file(path: str, lay: Layout) -> dict[str, np.ndarray]:
    """One sweep's file on disk (as `write_sweep` wrote it), checked against layout `lay`: {column: values}."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as err:
        raise SubmissionFormatError(path, "file", f"unreadable ({type(err).__name__})") from None
    return _check_table(data, path, lay, None)


FINGERPRINT_NAME = "fingerprint.json"  # in a folder of sweeps being written: what writes them (`claim_parts`)


def _differences(there, here, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two JSON trees, each with both values (short)."""
    if isinstance(there, dict) and isinstance(here, dict):
        return [d for k in sorted(set(there) | set(here))
                for d in _differences(there.get(k), here.get(k), f"{prefix}.{k}" if prefix else k)]
    if there == here:
        return []
    return [f"{prefix}: {json.dumps(there)[:80]} there, {json.dumps(here)[:80]} here"]


def claim_parts(root: str, fingerprint: dict) -> None:
    """Makes `root`, the folder of a submission's sweeps, for the run `fingerprint` describes (a JSON tree: what made
    the sweeps), or checks that the folder an interrupted run left is that run's: a folder of another fingerprint, or
    of none, is a SubmissionFormatError naming what differs (its sweeps are another model's flows, or flows of other
    records: never kept)."""
    path = os.path.join(root, FINGERPRINT_NAME)
    wanted = json.loads(json.dumps(fingerprint))
    if not os.path.isdir(root):
        os.makedirs(root)
    elif os.path.isfile(path):
        try:
            with open(path, encoding="utf-8") as f:
                found = json.load(f)
        except (OSError, ValueError):
            found = None
        if found != wanted:
            differ = _differences(found, wanted) if isinstance(found, dict) else ["unreadable"]
            raise SubmissionFormatError(path, "fingerprint", "the sweeps here were written by another run ("
                                        + "; ".join(differ[:4]) + (f"; {len(differ) - 4} more" if len(differ) > 4
                                                                    else "")
                                        + f"): remove {root} to write them again, or give another --out")
        return
    elif os.listdir(root):
        raise SubmissionFormatError(root, "fingerprint", f"a folder of sweeps without {FINGERPRINT_NAME}: not "
                                    f"written by this tool's run; remove it, or give another --out")
    with open(path + ".tmp", "w", encoding="utf-8") as f:
        json.dump(wanted, f, indent=1, sort_keys=True)
    os.replace(path + ".tmp", path)


def make_archive(root: str, zip_path: str, lay: Layout, expected_rows: dict[str, int] | None = None,
                 supervised: bool = True, progress: Callable[[int, int], None] | None = None) -> dict[str, int]:
    """Zip the submission folder `root` (every file an entry of layout `lay` written by `write_sweep`; v2 adds
    metadata.json with {"Is Supervised?": supervised}; `FINGERPRINT_NAME` at its top is not archived), validate the
    archive itself (`validate_archive`) and only then move it to `zip_path`. Returns the validation summary; on a
    failure the error names the file and `zip_path` is left as it was."""
    entries = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames.sort()
        for fn in sorted(filenames):
            rel = os.path.relpath(os.path.join(dirpath, fn), root).replace(os.sep, "/")
            if rel == FINGERPRINT_NAME:
                continue
            if _entry_key(lay, rel) is None:
                raise SubmissionFormatError(os.path.join(root, rel), "file", "unexpected file in the submission "
                                            f"folder: not an entry of layout {lay.name}")
            entries.append(rel)
    tmp = zip_path + ".tmp"
    try:
        # Stored, not deflated: the Feather files are compressed already (LZ4, pyarrow's default).
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
            if lay.metadata_json:
                zf.writestr(METADATA_NAME, json.dumps({SUPERVISED_KEY: bool(supervised)}, indent=4))
            for rel in entries:
                zf.write(os.path.join(root, *rel.split("/")), arcname=rel)
        summary = _validate(tmp, lay, expected_rows, zip_path, progress)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    os.replace(tmp, zip_path)
    return summary


def expected_counts_from_json(path: str) -> dict[str, int]:
    """{"<log_id>/<timestamp_ns>.feather": rows} of av2-api's `{val,test}_submission_format.json`, checked."""
    try:
        with open(path, encoding="utf-8") as f:
            raw = json.load(f)
    except OSError as err:
        raise SubmissionFormatError(path, "file", f"unreadable ({type(err).__name__})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SubmissionFormatError(path, "file", f"not JSON ({getattr(err, 'msg', err)})") from None
    if not isinstance(raw, dict):
        raise SubmissionFormatError(path, "file", "expected an object {\"<log_id>/<timestamp_ns>.feather\": rows}")
    for name, rows in raw.items():
        if not _ENTRY.match(name):
            raise SubmissionFormatError(path, f"key {name!r}", "expected <log_id>/<timestamp_ns>.feather")
        if not isinstance(rows, int) or isinstance(rows, bool) or rows < 0:
            raise SubmissionFormatError(path, f"key {name!r}", f"row count {rows!r} is not an integer >= 0")
    return dict(raw)


def check_against_format_json(lay: Layout, planned_rows: dict[str, int | None], format_rows: dict[str, int],
                              format_path: str) -> None:
    """The planned entries ({entry: rows, None where not known yet}) against av2-api's format JSON, as its validator
    compares an archive: the same entries and, for v1, the same row counts (v3 has a row per point: names only)."""
    if lay.indexed_entries:
        raise SubmissionFormatError(format_path, "file", f"layout {lay.name} names sweeps by index; the format JSON "
                                    "describes the <log_id>/<timestamp_ns>.feather layouts (v1, v3)")
    for name in sorted(format_rows):
        if name not in planned_rows:
            raise SubmissionFormatError(f"{format_path}:{name}", "entry", "an evaluated sweep the submission does "
                                        "not plan (no such sweep among the mask archive's or the records')")
        rows = planned_rows[name]
        if lay.mask_rows and rows is not None and rows != format_rows[name]:
            raise SubmissionFormatError(f"{format_path}:{name}", "rows", f"{format_rows[name]} rows expected, the "
                                        f"official mask selects {rows}")
    extra = sorted(set(planned_rows) - set(format_rows))
    if extra:
        raise SubmissionFormatError(f"{format_path}:{extra[0]}", "entry", f"planned but not in the format JSON "
                                    f"({len(extra)} such sweeps)")


# --- The official masks ----------------------------------------------------------------------------------------------

class MaskArchive:
    """The official point masks (`{val,test}-masks.zip`, module doc): `<log_id>/<timestamp_ns>.feather` entries of one
    boolean column over every point of the sweep. Other files (not .feather) and folders are ignored, as Argoverse's
    validator ignores them; a .feather entry with another name is an error naming it."""

    def __init__(self, path: str):
        self.path = path
        try:
            self._zip = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError) as err:
            raise SubmissionFormatError(path, "file", f"not a readable zip archive of masks "
                                        f"({type(err).__name__}); {MASKS_SOURCE}") from None
        self.entries: dict[SweepKey, str] = {}
        for info in self._zip.infolist():
            name = info.filename
            if name.endswith("/") or not name.endswith(".feather"):
                continue
            m = _ENTRY.match(name)
            if not m:
                raise SubmissionFormatError(f"{path}:{name}", "file", "a mask entry must be "
                                            "<log_id>/<timestamp_ns>.feather")
            key = (m.group(1), int(m.group(2)))
            if key in self.entries:
                raise SubmissionFormatError(f"{path}:{name}", "file", "duplicate entry for this sweep")
            self.entries[key] = name
        if not self.entries:
            raise SubmissionFormatError(path, "file", f"no <log_id>/<timestamp_ns>.feather masks in it; {MASKS_SOURCE}")

    def __enter__(self) -> "MaskArchive":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._zip.close()

    def keys(self) -> list[SweepKey]:
        return sorted(self.entries)

    def where(self, key: SweepKey) -> str:
        return f"{self.path}:{self.entries[key]}"

    def mask(self, key: SweepKey) -> np.ndarray:
        """[N] bool, the sweep's official mask, checked: one column, boolean, no nulls."""
        import pyarrow as pa
        where = self.where(key)
        table = _read_table(_read_entry(self._zip, self.entries[key], self.path), where)
        names = table.schema.names
        if len(names) != 1:
            raise SubmissionFormatError(where, "columns", f"{names}: a mask has exactly one boolean column")
        col = table.column(0)
        if col.type != pa.bool_():
            raise SubmissionFormatError(where, f"column {names[0]}", f"type {col.type}, a mask column is bool")
        if col.null_count:
            raise SubmissionFormatError(where, f"column {names[0]}", f"{col.null_count} null values")
        return col.to_numpy(zero_copy_only=False).astype(bool)

    def checked_mask(self, key: SweepKey, num_points: int, record_where: str) -> np.ndarray:
        """`mask(key)`, which must hold one value per point of the sweep's record (error naming both otherwise)."""
        m = self.mask(key)
        if len(m) != num_points:
            raise SubmissionFormatError(self.where(key), "mask length", f"{len(m)} values, but the sweep's pair "
                                        f"record in {record_where} has {num_points} points")
        return m


# --- Which sweeps, which rows ----------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class RecordSweep:
    """A pair record's first sweep: its log, timestamp, the next sweep's timestamp, its point count, its file."""

    log_id: str
    timestamp_ns: int
    next_timestamp_ns: int
    num_points: int
    where: str  # the records file holding it

    @property
    def key(self) -> SweepKey:
        return self.log_id, self.timestamp_ns


@dataclasses.dataclass(frozen=True)
class PlannedSweep:
    """A sweep the submission holds: its archive entry and its row count (None: set by av2-api's rule when written,
    without official masks)."""

    log_id: str
    timestamp_ns: int
    entry: str
    num_points: int
    rows: int | None
    where: str  # the records file holding it


def av2_api_rule_subset(keys: Iterable[SweepKey]) -> list[SweepKey]:
    """Every 5th pair of a split, from the first, in av2-api's data loader order (logs, then time): av2-api's
    `get_eval_subset` over the first sweeps of the pairs `keys` (every sweep of a log but its last). For local
    validation only: a submission's sweeps are the official mask archive's."""
    return sorted(keys)[::EVERY_KTH]


def av2_api_rule_mask(points_xyz, is_ground) -> np.ndarray:
    """[N] bool, av2-api's `compute_eval_point_mask`: |x| <= 50 m and |y| <= 50 m (sweep ego frame) and not ground
    (`is_ground`: the map's ground by av2-api's rule, as `argoverse2.is_ground`). For local validation only."""
    p = np.asarray(points_xyz, np.float64)
    g = np.asarray(is_ground)
    if p.ndim != 2 or p.shape[1] != 3 or g.shape != (len(p),) or g.dtype != bool:
        raise ValueError(f"points {p.shape}, is_ground {g.shape} {g.dtype}: expected [N, 3] and bool [N]")
    return (np.abs(p[:, 0]) <= AV2_API_RULE_HALF_WIDTH_M) & (np.abs(p[:, 1]) <= AV2_API_RULE_HALF_WIDTH_M) & ~g


def _index_in_logs(records: list[RecordSweep]) -> dict[SweepKey, int]:
    """The index of each record's sweep among its log's sweeps: its rank among the log's records, which must chain
    (each record's next sweep is the next record's sweep); a break is an error naming the log and the records."""
    by_log: dict[str, list[RecordSweep]] = {}
    for r in records:
        by_log.setdefault(r.log_id, []).append(r)
    index = {}
    for log_id, rs in by_log.items():
        rs.sort(key=lambda r: r.timestamp_ns)
        for k, r in enumerate(rs):
            if k + 1 < len(rs) and r.next_timestamp_ns != rs[k + 1].timestamp_ns:
                raise SubmissionFormatError(r.where, f"log {log_id}", f"the record of sweep {r.timestamp_ns} pairs it "
                                            f"with {r.next_timestamp_ns}, but the next record starts at "
                                            f"{rs[k + 1].timestamp_ns}: the layout numbers sweeps by their position "
                                            "in the log, so the records must hold every pair of the log")
            index[r.key] = k
    return index


def plan_submission(lay: Layout, records: list[RecordSweep], masks: MaskArchive | None) -> list[PlannedSweep]:
    """The sweeps of a submission in layout `lay`, in (log, time) order, with their entries and row counts.

    Every sweep of `masks` must have a record whose point count is its mask's length (errors name both). v1, v3: the
    mask archive's sweeps; v1's rows are each mask's True values, v3's every point. Without masks (local validation):
    `av2_api_rule_subset` of the records, v1's rows set by `av2_api_rule_mask` when written. v2: sweep indices 0, 5,
    10, ... of each log (of the masks' logs, when given), every point."""
    by_key: dict[SweepKey, RecordSweep] = {}
    for r in records:
        if r.key in by_key:
            raise SubmissionFormatError(r.where, f"sweep {r.log_id}/{r.timestamp_ns}", "a second record of this "
                                        f"sweep (the first is in {by_key[r.key].where})")
        by_key[r.key] = r
    mask_rows: dict[SweepKey, int] = {}
    if masks is not None:
        record_logs = {r.log_id for r in records}
        for key in masks.keys():
            if key not in by_key:
                have = sum(1 for r in records if r.log_id == key[0]) if key[0] in record_logs else 0
                raise SubmissionFormatError(masks.where(key), "sweep", f"no pair record of this sweep in "
                                            f"{_records_where(records)} (they hold {have} sweeps of log {key[0]})")
            r = by_key[key]
            mask_rows[key] = int(masks.checked_mask(key, r.num_points, r.where).sum())
    if lay.masks_choose_sweeps:
        keys = masks.keys() if masks is not None else av2_api_rule_subset(by_key)
        index = {}
    else:
        index = _index_in_logs(list(by_key.values()))
        logs = {k[0] for k in masks.keys()} if masks is not None else None
        keys = sorted(k for k, i in index.items() if i % EVERY_KTH == 0 and (logs is None or k[0] in logs))
    out = []
    for key in keys:
        r = by_key[key]
        rows = mask_rows.get(key) if lay.mask_rows else r.num_points
        out.append(PlannedSweep(r.log_id, r.timestamp_ns, lay.entry(r.log_id, r.timestamp_ns, index.get(key)),
                                r.num_points, rows, r.where))
    return out


def _records_where(records: list[RecordSweep]) -> str:
    folders = sorted({os.path.dirname(r.where) or "." for r in records})
    return folders[0] if len(folders) == 1 else f"{len(folders)} folders ({folders[0]}, ...)" if folders else \
        "the records (none given)"
