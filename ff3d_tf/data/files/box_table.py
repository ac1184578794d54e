"""A user's tracked boxes, one table per sequence of sweeps, read into the boxes dicts of `ff3d_tf.labels.box_flow`.

The table (`boxes.csv`, or `boxes.feather` for Arrow IPC) sits in the sequence's sweeps directory and has one row per
box per sweep, with the columns `BOX_COLUMNS` (any order; other columns are ignored):

| column | what it holds |
|---|---|
| `sweep` | the point file's name without its suffix (`000042` for `000042.pcd`) |
| `track_id` | the object's id, the same in every sweep it is seen in (text) |
| `class` | vehicle, pedestrian, cyclist, sign, or a name the class map maps (see below) |
| `x`, `y`, `z` | the box's centre (m), in the vehicle frame of that sweep (the frame of its points) |
| `length`, `width`, `height` | the box's extent (m, > 0) along its heading, across it, and up |
| `heading` | yaw (rad) about +z of the box's length axis, 0 along +x, counter-clockwise (towards +y) positive |

A class map (`read_class_map`, a YAML mapping of your class names to one of `CLASS_TARGETS`, or to null to drop those
boxes) names other classes: `car: vehicle`, `bicycle: cyclist`, `DontCare: null`. `background` keeps the box (its
points move with it) but labels its points class 0 (background), as Argoverse 2's reader does with categories outside
the four classes (cones, bollards). A name is looked up in the map first, then among the four classes (any case).

Rules, each an error (`PointFileError`) naming the table, the row (data rows counted from 1; a CSV's line is the row
+ 1) and the column: every column present; a finite number in every numeric cell; length, width and height > 0; a
known class; `sweep` one of the sequence's point files; one box per track per sweep; and a track's boxes in consecutive
sweeps (a track that is missing from a sweep and seen again later is an error: give it a new `track_id` after the
gap). A sweep without rows has no boxes.
"""
from __future__ import annotations

import csv
import math
import os

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data.files.point_file_errors import PointFileError

BOX_TABLE_NAMES = ("boxes.csv", "boxes.feather")
BOX_COLUMNS = ("sweep", "track_id", "class", "x", "y", "z", "length", "width", "height", "heading")
NUMERIC_COLUMNS = ("x", "y", "z", "length", "width", "height", "heading")
SIZE_COLUMNS = ("length", "width", "height")
# What a box's class may be (after the class map): the four labelled classes, and background (points move with the
# box, class 0).
CLASS_TARGETS = {"vehicle": schema.CLASS_VEHICLE, "pedestrian": schema.CLASS_PEDESTRIAN,
                 "cyclist": schema.CLASS_CYCLIST, "sign": schema.CLASS_SIGN, "background": schema.CLASS_BACKGROUND}
MAX_CLASS_MAP_BYTES = 1 << 20  # a class map is a short YAML file


def find_box_table(directory: str) -> str | None:
    """The sequence's box table (`BOX_TABLE_NAMES`), None when it has none; both at once is an error."""
    found = [os.path.join(directory, n) for n in BOX_TABLE_NAMES if os.path.isfile(os.path.join(directory, n))]
    if len(found) > 1:
        raise PointFileError(found[1], "file", f"a second box table beside {os.path.basename(found[0])}: keep one")
    return found[0] if found else None


def read_class_map(path: str) -> dict[str, int | None]:
    """{your class name: flow class id, or None (boxes dropped)} of a class map YAML (module docstring)."""
    import yaml
    if not os.path.isfile(path):
        raise PointFileError(path, "file", "missing (not a file)")
    if os.path.getsize(path) > MAX_CLASS_MAP_BYTES:
        raise PointFileError(path, "file", f"over {MAX_CLASS_MAP_BYTES} bytes: not a class map")
    with open(path, "rb") as f:
        try:
            tree = yaml.safe_load(f.read().decode("utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as err:
            raise PointFileError(path, "file", f"not YAML text ({str(err).splitlines()[0]})") from None
    if not isinstance(tree, dict):
        raise PointFileError(path, "file", "expected a mapping of class names to one of "
                                           f"{sorted(CLASS_TARGETS)} or null, e.g. 'car: vehicle'")
    out = {}
    for name, target in tree.items():
        if not isinstance(name, (str, int)) or isinstance(name, bool):
            raise PointFileError(path, repr(name), "a class name must be text")
        if target is None:
            out[str(name)] = None
            continue
        if not isinstance(target, str) or target.lower() not in CLASS_TARGETS:
            raise PointFileError(path, str(name), f"maps to {target!r}; expected one of {sorted(CLASS_TARGETS)} or "
                                                  "null (boxes of this class dropped)")
        out[str(name)] = CLASS_TARGETS[target.lower()]
    return out


def _class_id(name: str, class_map: dict[str, int | None]) -> int | None:
    if name in class_map:
        return class_map[name]
    if name.lower() in CLASS_TARGETS:
        return CLASS_TARGETS[name.lower()]
    raise KeyError(name)


def _csv_rows(path: str) -> tuple[list[str], list[list[str]], int]:
    """(header, data rows, the line number of data row 1) of a CSV table."""
    try:
        with open(path, encoding="utf-8", newline="") as f:
            rows = list(csv.reader(f))
    except UnicodeDecodeError as err:
        raise PointFileError(path, "file", f"not UTF-8 text ({err.reason} at byte {err.start})") from None
    except csv.Error as err:
        raise PointFileError(path, "file", f"not a CSV table ({err})") from None
    rows = [r for r in rows if any(cell.strip() for cell in r)]
    if not rows:
        raise PointFileError(path, "header", f"empty: a box table starts with a header line naming {BOX_COLUMNS}")
    return [c.strip() for c in rows[0]], rows[1:], 2


def _feather_columns(path: str) -> dict[str, list]:
    import pyarrow as pa
    import pyarrow.feather as feather
    try:
        table = feather.read_table(path)
        table.validate(full=True)
    except (pa.ArrowException, OSError, ValueError) as err:
        raise PointFileError(path, "file", f"not a readable feather (Arrow IPC) file ({type(err).__name__})") from None
    out = {}
    for name in table.schema.names:
        if name not in BOX_COLUMNS:
            continue
        column, dtype = table.column(name), table.schema.field(name).type
        text = pa.types.is_string(dtype) or pa.types.is_large_string(dtype)
        number = pa.types.is_floating(dtype) or pa.types.is_integer(dtype)
        if name in NUMERIC_COLUMNS and not number:
            raise PointFileError(path, f"column {name}", f"type {dtype}, expected numbers")
        if name == "track_id" and not (text or pa.types.is_integer(dtype)):
            raise PointFileError(path, f"column {name}", f"type {dtype}, expected text (or integers)")
        if name in ("sweep", "class") and not text:
            raise PointFileError(path, f"column {name}", f"type {dtype}, expected text (a sweep name keeps its zeros "
                                                         "only as text)")
        out[name] = column.to_pylist()
    return out


def read_box_table(path: str, sweep_stems: list[str], class_map: dict[str, int | None] | None = None
                   ) -> dict[str, dict]:
    """{sweep stem: boxes dict (`box_flow` layout: center [K,3], size [K,3], heading [K], track_id [K] str,
    class_id [K] int32)} for every stem of `sweep_stems` (in sweep order), checked by the module docstring's rules.
    Boxes keep the table's row order within a sweep."""
    class_map = class_map or {}
    if path.lower().endswith(".feather"):
        columns = _feather_columns(path)
        missing = [c for c in BOX_COLUMNS if c not in columns]
        if missing:
            raise PointFileError(path, f"column {missing[0]}", f"missing; a box table has the columns {BOX_COLUMNS}")
        num_rows = len(columns["sweep"])
        cells = [{c: columns[c][i] for c in BOX_COLUMNS} for i in range(num_rows)]
        where = lambda i: f"row {i + 1}"  # noqa: E731
    else:
        header, rows, first_line = _csv_rows(path)
        missing = [c for c in BOX_COLUMNS if c not in header]
        if missing:
            raise PointFileError(path, f"column {missing[0]}", f"missing from the header line {header}; a box table "
                                                               f"has the columns {BOX_COLUMNS}")
        index = {c: header.index(c) for c in BOX_COLUMNS}
        cells = []
        for i, row in enumerate(rows):
            if len(row) != len(header):
                raise PointFileError(path, f"row {i + 1} (line {i + first_line})",
                                     f"{len(row)} cells for the header's {len(header)} columns")
            cells.append({c: row[j] for c, j in index.items()})
        where = lambda i: f"row {i + 1} (line {i + first_line})"  # noqa: E731
    order = {stem: k for k, stem in enumerate(sweep_stems)}
    per_sweep: dict[str, list] = {stem: [] for stem in sweep_stems}
    seen: dict[tuple[str, str], int] = {}
    track_sweeps: dict[str, list[tuple[int, int]]] = {}
    for i, row in enumerate(cells):
        def bad(column, why, i=i):
            return PointFileError(path, f"{where(i)}, column {column}", why)
        sweep = "" if row["sweep"] is None else str(row["sweep"]).strip()
        if sweep not in order:
            raise bad("sweep", f"{sweep!r} is not the name (without suffix) of a point file of the sequence "
                               f"({len(sweep_stems)} sweeps: {sweep_stems[0]} .. {sweep_stems[-1]})")
        track = "" if row["track_id"] is None else str(row["track_id"]).strip()
        if not track:
            raise bad("track_id", "empty")
        name = "" if row["class"] is None else str(row["class"]).strip()
        try:
            class_id = _class_id(name, class_map)
        except KeyError:
            raise bad("class", f"{name!r} is not one of {sorted(CLASS_TARGETS)}; map your class names with "
                               "--class_map (a YAML file: 'car: vehicle')") from None
        values = {}
        for column in NUMERIC_COLUMNS:
            cell = row[column]
            try:
                value = float(cell) if not isinstance(cell, bool) and cell is not None else float("nan")
            except (TypeError, ValueError):
                raise bad(column, f"{cell!r} is not a number") from None
            if not math.isfinite(value):
                raise bad(column, f"{cell!r}: not a finite number")
            values[column] = value
        for column in SIZE_COLUMNS:
            if values[column] <= 0:
                raise bad(column, f"{values[column]!r}: a box's {column} must be > 0 m")
        key = (sweep, track)
        if key in seen:
            raise bad("track_id", f"track {track!r} has a second box in sweep {sweep} (the first: {where(seen[key])})")
        seen[key] = i
        track_sweeps.setdefault(track, []).append((order[sweep], i))
        if class_id is not None:
            per_sweep[sweep].append((values, track, class_id))
    for track, where_seen in track_sweeps.items():
        where_seen.sort()
        for (k0, i0), (k1, i1) in zip(where_seen, where_seen[1:]):
            if k1 != k0 + 1:
                raise PointFileError(path, f"{where(i1)}, column track_id",
                                     f"track {track!r} is in sweeps {sweep_stems[k0]} ({where(i0)}) and "
                                     f"{sweep_stems[k1]}, not in the {k1 - k0 - 1} sweep(s) between: a track's boxes "
                                     "are in consecutive sweeps (give the object a new track_id after a gap)")
    return {stem: _boxes(rows) for stem, rows in per_sweep.items()}


def _boxes(rows: list) -> dict:
    if not rows:
        return {"center": np.zeros((0, 3)), "size": np.zeros((0, 3)), "heading": np.zeros(0),
                "track_id": np.zeros(0, dtype=str), "class_id": np.zeros(0, np.int32)}
    return {"center": np.array([[v["x"], v["y"], v["z"]] for v, _, _ in rows], np.float64),
            "size": np.array([[v["length"], v["width"], v["height"]] for v, _, _ in rows], np.float64),
            "heading": np.array([v["heading"] for v, _, _ in rows], np.float64),
            "track_id": np.array([t for _, t, _ in rows]),
            "class_id": np.array([c for _, _, c in rows], np.int32)}


def write_box_table(path: str, boxes_by_sweep: dict[str, dict], class_names: dict[int, str] | None = None) -> str:
    """Writes a `boxes.csv` of boxes dicts by sweep stem (in the dict's order); the class column is the box's
    `category` where the dict has one, else its class name (`class_names`, default `schema.CLASS_NAMES`). Numbers
    are written with every digit of their float64 (read back bit for bit)."""
    class_names = class_names or schema.CLASS_NAMES
    tmp = path + ".partial"
    with open(tmp, "w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(BOX_COLUMNS)
        for stem, boxes in boxes_by_sweep.items():
            for k in range(len(boxes["heading"])):
                name = str(boxes["category"][k]) if "category" in boxes else class_names[int(boxes["class_id"][k])]
                c, s = boxes["center"][k], boxes["size"][k]
                writer.writerow([stem, str(boxes["track_id"][k]), name, *(repr(float(v)) for v in c),
                                 *(repr(float(v)) for v in s), repr(float(boxes["heading"][k]))])
    os.replace(tmp, path)
    return path
