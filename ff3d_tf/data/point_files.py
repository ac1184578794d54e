"""A user's own point clouds and poses, read into the frame dicts of the rest of the project (NumPy and pyarrow).

Point files (by suffix; points in the vehicle frame of their sweep, metres):

| suffix | what it holds |
|---|---|
| `.npy` | an [N,3] (x, y, z) or [N,4] (x, y, z, intensity) numeric array, or a structured array with fields x, y, z |
|        | (and optionally an intensity field) |
| `.npz` | `points` ([N,3] or [N,4] as in `.npy`), or `x`, `y`, `z` ([N] each); optionally `intensity` [N] (with a |
|        | 3-column `points` or with x, y, z); any other array is an error |
| `.bin` | KITTI style: float32 little-endian x, y, z, intensity per point, nothing else (16 bytes a point); a name |
|        | ending `.pcd.bin` is nuScenes' layout, float32 x, y, z, intensity, ring (20 bytes a point) |
| `.pcd` | PCL's PCD v0.7 (and older headers of the same form): DATA ascii, binary or binary_compressed (LZF, |
|        | decoded by `lzf_decompress` below); TYPE F (4, 8 bytes), I and U (1, 2, 4, 8 bytes); little-endian |
| `.ply` | the element `vertex` of a PLY file, format ascii, binary_little_endian or binary_big_endian |

In PCD and PLY files, x, y and z are required (one value each); the first column named as in `INTENSITY_FIELDS`
(any case) is the intensity; every other column (rgb, ring, t, normals, ...) is ignored and listed in
`PointColumns.ignored`. A NaN or Inf in x, y, z or the intensity is an error naming the file, the field and the
first bad point (organized clouds mark missing returns with NaN: drop those points before). A cloud without an
intensity gets intensity 0.

Intensity scale. The model reads WOD-style intensity: the raw range image channel "intensity", unnormalised (no
fixed range: most returns are small, of order 1 or less, with a long tail up to thousands on retroreflectors;
waymo-open-dataset issues #40 and #93; the synthetic segments draw it in [0, 1.5]). Argoverse 2 stores 0..255 as
uint8 and its reader divides by 255. For user files the rule (`intensity_scale_of`) is: a number given as
`intensity_scale` multiplies the stored values (`--intensity_scale 1/255` for 0..255 stored as floats, `0` to switch
intensity off); by default ("auto") a column stored as an unsigned integer type is divided by that type's maximum
(uint8: 255, the Argoverse 2 rule; uint16: 65535), a signed integer by its positive maximum, and a float column is
taken as it is (KITTI's float reflectance in [0, 1]). The rule looks at the stored type only, never at the values,
so every sweep of a log is scaled alike. Intensity depends on the sensor; where a model trained on WOD does worse
with your intensity than without, pass `--intensity_scale 0`.

Poses: a [4,4] vehicle -> world transform (the project's convention, `ff3d_tf.geometry`), as text (16 numbers, a
4x4 matrix row by row; or 12 numbers, its top 3x4 rows; whitespace or commas between numbers, `#` comments) or
`.npy` ([4,4] or [3,4]); checked by `geometry.pose_problem_np` (finite, bottom row, rigid, not a reflection).

A directory of sweeps (`list_sweeps`): every point file in it, sorted by name (zero-pad numbers: 000009.bin before
000010.bin); `*.pose.npy` files are poses, not sweeps. Its poses (`sweep_poses`), optional: either `poses.txt`, one
pose per line in sweep order (12 or 16 numbers, KITTI odometry style; as many lines as sweeps), or one file per
sweep beside it, `<sweep name without suffix>.pose.txt` or `.pose.npy`; both kinds at once is an error.

Errors are `PointFileError`, naming the file, the field (or "file", "header", "pose", "line N") and what is wrong.
"""
from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from ff3d_tf import schema

POINT_SUFFIXES = (".npy", ".npz", ".bin", ".pcd", ".ply")
INTENSITY_FIELDS = ("intensity", "reflectance", "scalar_intensity")  # column names read as intensity (any case)
NPZ_KEYS = ("points", "x", "y", "z", "intensity")
POSES_FILE = "poses.txt"  # in a sweeps directory: one pose per line, in sweep order
SWEEP_POSE_SUFFIXES = (".pose.txt", ".pose.npy")  # per-sweep pose files: <sweep stem><suffix>
BIN_FIELDS = ("x", "y", "z", "intensity")  # KITTI .bin: float32 each
NUSCENES_BIN_SUFFIX = ".pcd.bin"  # nuScenes lidar sweeps: float32 x, y, z, intensity, ring index
NUSCENES_BIN_FIELDS = ("x", "y", "z", "intensity", "ring")
# PCD TYPE letter -> {SIZE in bytes: NumPy kind}
PCD_TYPES = {"F": {4: "f4", 8: "f8"}, "I": {1: "i1", 2: "i2", 4: "i4", 8: "i8"},
             "U": {1: "u1", 2: "u2", 4: "u4", 8: "u8"}}
PCD_DATA_KINDS = ("ascii", "binary", "binary_compressed")
PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
MAX_HEADER_BYTES = 1 << 16  # a PCD or PLY header longer than this is not one
IDENTITY_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)  # PCD VIEWPOINT tx ty tz qw qx qy qz


class PointFileError(ValueError):
    """A point or pose file that cannot be used: names the file, the field (or part of the file) and the problem."""

    def __init__(self, path: str, field: str, reason: str):
        self.path, self.field, self.reason = path, field, reason
        super().__init__(f"{path}: {field}: {reason}")


@dataclasses.dataclass(frozen=True)
class PointColumns:
    """What a point file holds, before the intensity scale: x, y, z (float64, finite), the stored intensity
    (float64, finite, or None) with its stored dtype, the columns not read, and remarks for the user."""
    path: str
    xyz: np.ndarray
    intensity: np.ndarray | None
    intensity_dtype: np.dtype | None
    ignored: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()


# --- intensity --------------------------------------------------------------------------------------------------

def parse_intensity_scale(text: str) -> float | None:
    """`--intensity_scale`: "auto" -> None (the stored-type rule), a number ("0.5", "1e-3") or a fraction ("1/255")."""
    text = str(text).strip()
    if text.lower() == "auto":
        return None
    parts = text.split("/")
    try:
        if len(parts) == 1:
            value = float(parts[0])
        elif len(parts) == 2:
            value = float(parts[0]) / float(parts[1])
        else:
            raise ValueError
    except (ValueError, ZeroDivisionError):
        raise ValueError(f"intensity scale {text!r}: expected 'auto', a number or a fraction such as 1/255") from None
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"intensity scale {text!r}: must be finite and >= 0")
    return value


def intensity_scale_of(dtype, scale: float | None) -> float:
    """The factor applied to a stored intensity column of `dtype` (module docstring: "Intensity scale")."""
    if scale is not None:
        return float(scale)
    dtype = np.dtype(dtype)
    if np.issubdtype(dtype, np.integer):
        return 1.0 / float(np.iinfo(dtype).max)
    return 1.0


# --- frames -----------------------------------------------------------------------------------------------------

def frame_from_columns(cols: PointColumns, pose: np.ndarray | None = None, intensity_scale: float | None = None,
                       timestamp_micros: int = 0) -> dict:
    """A frame dict (`schema.FRAME_KEYS`, the shapes of `argoverse2.read_sweep`): no flow labels (flow 0, class -1),
    elongation 0, laser name 1 (one lidar), the pose (identity when None: the cloud is taken as in the reference
    frame) and the intensity scaled by `intensity_scale_of`."""
    n = len(cols.xyz)
    if cols.intensity is None:
        intensity = np.zeros(n, np.float32)
    else:
        intensity = (cols.intensity * intensity_scale_of(cols.intensity_dtype, intensity_scale)).astype(np.float32)
    return {
        "points_xyz": cols.xyz.astype(np.float32),
        "intensity": intensity,
        "elongation": np.zeros(n, np.float32),
        "flow_mps": np.zeros((n, 3), np.float32),
        "class_id": np.full(n, schema.CLASS_NO_LABEL, np.int32),
        "laser_name": np.ones(n, np.int32),
        "pose": np.eye(4) if pose is None else np.asarray(pose, np.float64),
        "timestamp_micros": int(timestamp_micros),
    }


def read_frame(path: str, pose: np.ndarray | None = None, intensity_scale: float | None = None) -> dict:
    """`read_point_file` then `frame_from_columns`."""
    return frame_from_columns(read_point_file(path), pose, intensity_scale)


# --- point files ------------------------------------------------------------------------------------------------

def read_point_file(path: str) -> PointColumns:
    """The columns of a `.npy`, `.npz`, `.bin`, `.pcd` or `.ply` point file (module docstring), checked."""
    suffix = os.path.splitext(path)[1].lower()
    readers = {".npy": _read_npy, ".npz": _read_npz, ".bin": _read_bin, ".pcd": _read_pcd, ".ply": _read_ply}
    if suffix not in readers:
        raise PointFileError(path, "file", f"unknown point file suffix {suffix!r}; one of {POINT_SUFFIXES}")
    if not os.path.isfile(path):
        raise PointFileError(path, "file", "missing (not a file)")
    columns, notes = readers[suffix](path)
    return _cloud_of_columns(path, columns, notes)


def _cloud_of_columns(path: str, columns: dict[str, np.ndarray], notes=()) -> PointColumns:
    """x, y, z and the intensity of named 1-D columns (the dict's order is the file's), checked finite."""
    for axis in ("x", "y", "z"):
        if axis not in columns:
            raise PointFileError(path, axis, f"missing; the file has the fields {list(columns)}")
    by_lower = {}
    for name in columns:
        by_lower.setdefault(name.lower(), name)
    intensity_name = next((by_lower[n] for n in INTENSITY_FIELDS if n in by_lower), None)
    used = ("x", "y", "z") + ((intensity_name,) if intensity_name else ())
    out = {}
    for name in used:
        values = np.asarray(columns[name])
        if values.ndim != 1:
            raise PointFileError(path, name, f"needs one value per point, has shape {values.shape}")
        if not (np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)):
            raise PointFileError(path, name, f"type {values.dtype}: not a real number")
        finite = np.isfinite(values)
        if not np.all(finite):
            row = int(np.argmin(finite))
            raise PointFileError(path, name, f"non-finite value {values[row]} at point {row} (NaN or Inf; remove "
                                             "such points before predicting)")
        out[name] = values
    n = len(out["x"])
    for name in used[1:]:
        if len(out[name]) != n:
            raise PointFileError(path, name, f"{len(out[name])} values, but x has {n}")
    xyz = np.stack([out["x"], out["y"], out["z"]], -1).astype(np.float64)
    return PointColumns(path=path, xyz=xyz,
                        intensity=None if intensity_name is None else out[intensity_name].astype(np.float64),
                        intensity_dtype=None if intensity_name is None else out[intensity_name].dtype,
                        ignored=tuple(c for c in columns if c not in used), notes=tuple(notes))


def _array_columns(path: str, a: np.ndarray, what: str) -> dict[str, np.ndarray]:
    """Columns of an [N,3]/[N,4] numeric array or a structured array of fields."""
    if a.dtype.names:
        if a.ndim != 1:
            raise PointFileError(path, what, f"a structured array of shape {a.shape}; expected one row per point")
        cols = {}
        for name in a.dtype.names:
            if a.dtype[name].shape:
                cols[name] = a[name].reshape(len(a), -1)  # a sub-array field: only an error if it is x, y or z
                if cols[name].shape[1] == 1:
                    cols[name] = cols[name][:, 0]
            else:
                cols[name] = a[name]
        return cols
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise PointFileError(path, what, f"type {a.dtype}: expected real numbers")
    if a.ndim != 2 or a.shape[1] not in (3, 4):
        raise PointFileError(path, what, f"shape {a.shape}: expected [N, 3] (x, y, z) or [N, 4] "
                                         "(x, y, z, intensity)")
    return dict(zip(BIN_FIELDS, a.T))


def _read_npy(path: str):
    try:
        a = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise PointFileError(path, "file", f"not a readable .npy array without pickled objects ({err})") from None
    return _array_columns(path, a, "array"), ()


def _read_npz(path: str):
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError) as err:
        raise PointFileError(path, "file", f"not a readable .npz archive without pickled objects ({err})") from None
    for key in arrays:
        if key not in NPZ_KEYS:
            raise PointFileError(path, key, "unknown array; an .npz point file holds 'points' ([N,3] or [N,4]) or "
                                            "'x', 'y', 'z' ([N] each), and optionally 'intensity' [N]")
    if "points" in arrays:
        if any(k in arrays for k in ("x", "y", "z")):
            raise PointFileError(path, "points", "given together with x/y/z arrays: give one or the other")
        cols = _array_columns(path, arrays["points"], "points")
        if "intensity" in arrays:
            if "intensity" in cols:
                raise PointFileError(path, "intensity", "given twice: as the 4th column of 'points' and as an array")
            cols["intensity"] = arrays["intensity"]
        return cols, ()
    return arrays, ()


def _read_bin(path: str):
    size = os.path.getsize(path)
    nuscenes = path.lower().endswith(NUSCENES_BIN_SUFFIX)
    fields = NUSCENES_BIN_FIELDS if nuscenes else BIN_FIELDS
    row = 4 * len(fields)
    if size % row:
        layout = "a nuScenes .pcd.bin holds float32 x, y, z, intensity, ring" if nuscenes else \
            "a KITTI-style .bin holds float32 x, y, z, intensity"
        raise PointFileError(path, "file", f"size {size} bytes is not a multiple of {row}: {layout} per point and "
                                           "nothing else (truncated, or another layout)")
    a = np.fromfile(path, dtype="<f4").reshape(-1, len(fields))
    return dict(zip(fields, a.T)), ()


# --- PCD ----------------------------------------------------------------------------------------------------------

def _header_lines(path: str, data: bytes, last_key: str):
    """(lines of the header as text, offset of the first byte after it): lines up to the one starting `last_key`."""
    lines, offset = [], 0
    while True:
        end = data.find(b"\n", offset)
        if end < 0 and offset < len(data):  # a last line without a newline (an empty cloud's header)
            end = len(data)
        if end < 0 or end > MAX_HEADER_BYTES:
            raise PointFileError(path, "header", f"no '{last_key}' line in the first {MAX_HEADER_BYTES} bytes")
        try:
            line = data[offset:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointFileError(path, "header", f"line {len(lines) + 1} is not ASCII text") from None
        lines.append(line)
        offset = end + 1
        if line.split(maxsplit=1)[:1] == [last_key]:
            return lines, offset


def _ints(path: str, key: str, values: list[str]) -> list[int]:
    try:
        out = [int(v) for v in values]
    except ValueError:
        raise PointFileError(path, key, f"{' '.join(values)!r}: expected integers") from None
    if any(v < 0 for v in out):
        raise PointFileError(path, key, f"{' '.join(values)!r}: negative")
    return out


def _read_pcd(path: str):
    with open(path, "rb") as f:
        data = f.read()
    lines, body = _header_lines(path, data, "DATA")
    header = {}
    for line in lines:
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in header:
            raise PointFileError(path, key, "missing from the PCD header")
    fields = header["FIELDS"]
    sizes = _ints(path, "SIZE", header["SIZE"])
    types = [t.upper() for t in header["TYPE"]]
    counts = _ints(path, "COUNT", header.get("COUNT", ["1"] * len(fields)))
    for key, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != len(fields):
            raise PointFileError(path, key, f"{len(values)} entries for {len(fields)} FIELDS")
    kinds = []
    for name, t, s, c in zip(fields, types, sizes, counts):
        kind = PCD_TYPES.get(t, {}).get(s)
        if kind is None:
            raise PointFileError(path, name, f"TYPE {t} SIZE {s}: unknown PCD field type (known: F with SIZE 4 or 8, "
                                             "I and U with SIZE 1, 2, 4 or 8)")
        if c < 1:
            raise PointFileError(path, name, f"COUNT {c}: must be at least 1")
        kinds.append(kind)
    width = _ints(path, "WIDTH", header.get("WIDTH", []))
    height = _ints(path, "HEIGHT", header.get("HEIGHT", ["1"]))
    points = _ints(path, "POINTS", header["POINTS"]) if "POINTS" in header else None
    if points is None and len(width) != 1:
        raise PointFileError(path, "POINTS", "missing, and no WIDTH to count the points by")
    n = points[0] if points is not None else width[0] * height[0]
    if len(width) == 1 and len(height) == 1 and width[0] * height[0] != n:
        raise PointFileError(path, "POINTS", f"{n}, but WIDTH x HEIGHT = {width[0]} x {height[0]}")
    data_kind = (header["DATA"] or [""])[0].lower()
    if data_kind not in PCD_DATA_KINDS:
        raise PointFileError(path, "DATA", f"{data_kind!r}: one of {PCD_DATA_KINDS}")
    notes = []
    if "VIEWPOINT" in header:
        try:
            viewpoint = tuple(float(v) for v in header["VIEWPOINT"])
        except ValueError:
            raise PointFileError(path, "VIEWPOINT", f"{header['VIEWPOINT']}: expected 7 numbers") from None
        if viewpoint != IDENTITY_VIEWPOINT:
            notes.append(f"VIEWPOINT {' '.join(header['VIEWPOINT'])} ignored: points are read as stored (they must "
                         "be in the vehicle frame)")
    names = [f"{name}#{i}" for i, name in enumerate(fields)]  # unique even where a name repeats (PCL's "_" padding)
    if data_kind == "ascii":
        table = _ascii_table(path, data[body:], sum(counts), n, f"{len(fields)} fields")
        cols, start = {}, 0
        for name, kind, c in zip(names, kinds, counts):
            cols[name] = table[:, start:start + c].astype(np.float64)
            start += c
            cols[name] = cols[name].astype(kind) if np.all(np.isfinite(cols[name])) and kind[0] != "f" else \
                cols[name]
    else:
        dtype = np.dtype([(name, "<" + kind, (c,)) for name, kind, c in zip(names, kinds, counts)])
        raw = data[body:]
        if data_kind == "binary_compressed":
            raw = _pcd_decompressed(path, raw, n * dtype.itemsize)
            cols, start = {}, 0
            for name, kind, c in zip(names, kinds, counts):  # field by field: all x, then all y, ...
                block = n * c * int(kind[1])
                cols[name] = np.frombuffer(raw, "<" + kind, count=n * c, offset=start).reshape(n, c)
                start += block
        else:
            _check_length(path, len(raw), n, dtype.itemsize, "binary PCD")
            rows = np.frombuffer(raw, dtype, count=n)
            cols = {name: rows[name].reshape(n, c) for name, c in zip(names, counts)}
    columns = {}
    for (name, values), field, c in zip(cols.items(), fields, counts):
        if field in columns:
            field = name  # a repeated name: kept apart
        columns[field] = values[:, 0] if c == 1 else values
    return columns, tuple(notes)


def _check_length(path: str, have: int, n: int, row_bytes: int, what: str) -> None:
    need = n * row_bytes
    if have < need:
        raise PointFileError(path, "data", f"truncated: the header says {n} points of {row_bytes} bytes "
                                           f"({need} bytes of {what} data), the file has {have}")
    if have > need:
        raise PointFileError(path, "data", f"{have - need} bytes after the last of the header's {n} points: the "
                                           "header's fields or point count do not match the data")


def _pcd_decompressed(path: str, raw: bytes, expected: int) -> bytes:
    if len(raw) < 8:
        raise PointFileError(path, "data", "truncated: binary_compressed data needs its two uint32 sizes")
    compressed, uncompressed = (int(v) for v in np.frombuffer(raw[:8], "<u4"))
    if uncompressed != expected:
        raise PointFileError(path, "data", f"binary_compressed: uncompressed size {uncompressed} bytes, but the "
                                           f"header's points and fields make {expected}")
    if len(raw) - 8 < compressed:
        raise PointFileError(path, "data", f"truncated: binary_compressed data of {compressed} bytes, the file has "
                                           f"{len(raw) - 8} after the sizes")
    try:
        return lzf_decompress(raw[8:8 + compressed], uncompressed)
    except ValueError as err:
        raise PointFileError(path, "data", f"binary_compressed: {err}") from None


def lzf_decompress(data: bytes, out_size: int) -> bytes:
    """LZF (liblzf's format, which PCL's binary_compressed uses), decoded to exactly `out_size` bytes.

    The stream is a sequence of runs, each starting with a control byte c: c < 32 is a literal run, the next c + 1
    bytes copied as they are; otherwise a back reference of length (c >> 5) + 2, where a length field of 7 is
    extended by the next byte, copying from distance ((c & 31) << 8) + (next byte) + 1 back in the output (the copy
    may overlap what it writes). ValueError when the stream is cut short, points before its start or does not
    decode to `out_size` bytes.
    """
    out = bytearray(out_size)
    ip, op, n = 0, 0, len(data)
    while ip < n:
        ctrl = data[ip]
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n:
                raise ValueError(f"LZF literal run of {length} bytes at input byte {ip - 1} runs past the input")
            if op + length > out_size:
                raise ValueError(f"LZF data decodes to more than {out_size} bytes")
            out[op:op + length] = data[ip:ip + length]
            ip += length
            op += length
            continue
        length = ctrl >> 5
        if length == 7:
            if ip >= n:
                raise ValueError("LZF back reference cut short")
            length += data[ip]
            ip += 1
        if ip >= n:
            raise ValueError("LZF back reference cut short")
        ref = op - ((ctrl & 0x1F) << 8) - data[ip] - 1
        ip += 1
        length += 2
        if ref < 0:
            raise ValueError(f"LZF back reference at input byte {ip - 2} points {op - ref} bytes back, before the "
                             "start of the output")
        if op + length > out_size:
            raise ValueError(f"LZF data decodes to more than {out_size} bytes")
        if ref + length <= op:  # no overlap: one slice
            out[op:op + length] = out[ref:ref + length]
        else:  # overlapping: a byte-by-byte copy repeats the last op - ref bytes
            period = bytes(out[ref:op])
            out[op:op + length] = (period * (length // len(period) + 1))[:length]
        op += length
    if op != out_size:
        raise ValueError(f"LZF data decodes to {op} bytes, expected {out_size}")
    return bytes(out)


def _ascii_table(path: str, text: bytes, width: int, n: int, what: str, more_ok: bool = False,
                 label: str = "data line") -> np.ndarray:
    """[n, width] float64 of whitespace-separated numbers, one point a line (blank lines skipped); lines after the
    n-th are an error unless `more_ok` (a PLY's later elements). Errors name the line as `label` N, counted from 1
    at the first line of `text`."""
    try:
        lines = text.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise PointFileError(path, "data", "ASCII data holds bytes that are not ASCII") from None
    rows = [(i, line.split()) for i, line in enumerate(lines) if line.strip()]
    if len(rows) < n:
        raise PointFileError(path, "data", f"truncated: the header says {n} points, the data has {len(rows)} lines")
    if len(rows) > n and not more_ok:
        raise PointFileError(path, f"{label} {rows[n][0] + 1}", f"a line after the header's {n} points")
    rows = rows[:n]
    for i, values in rows:
        if len(values) != width:
            raise PointFileError(path, f"{label} {i + 1}", f"{len(values)} values; the header's {what} take "
                                                             f"{width}")
    try:
        return np.array([values for _, values in rows], dtype=np.float64).reshape(n, width)
    except ValueError:
        for i, values in rows:
            for v in values:
                try:
                    float(v)
                except ValueError:
                    raise PointFileError(path, f"{label} {i + 1}", f"{v!r} is not a number") from None
        raise


# --- PLY ----------------------------------------------------------------------------------------------------------

def _read_ply(path: str):
    with open(path, "rb") as f:
        data = f.read()
    if not data.startswith(b"ply"):
        raise PointFileError(path, "header", "does not start with 'ply'")
    lines, body = _header_lines(path, data, "end_header")
    fmt, elements = None, []  # elements: [name, count, [(property, type)]]
    for i, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in PLY_FORMATS:
                raise PointFileError(path, "format", f"{line!r}: one of {tuple(PLY_FORMATS)}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3:
                raise PointFileError(path, f"header line {i}", f"{line!r}: expected 'element NAME COUNT'")
            elements.append([words[1], _ints(path, f"element {words[1]}", [words[2]])[0], []])
        elif words[0] == "property":
            if not elements:
                raise PointFileError(path, f"header line {i}", "a property before any element")
            if len(words) == 5 and words[1] == "list":
                elements[-1][2].append((words[4], "list"))
            elif len(words) == 3:
                if words[1] not in PLY_TYPES:
                    raise PointFileError(path, words[2], f"property type {words[1]!r} unknown; PLY types are "
                                                         f"{sorted(set(PLY_TYPES))}")
                elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
            else:
                raise PointFileError(path, f"header line {i}", f"{line!r}: expected 'property TYPE NAME'")
        else:
            raise PointFileError(path, f"header line {i}", f"{line!r}: unknown PLY header keyword")
    if fmt is None:
        raise PointFileError(path, "format", "missing from the PLY header")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise PointFileError(path, "vertex", f"no element 'vertex'; the file has {names}")
    vi = names.index("vertex")
    _, n, props = elements[vi]
    for name, kind in props:
        if kind == "list":
            raise PointFileError(path, name, "a list property of vertex: points need one value per property")
    if len({p for p, _ in props}) != len(props):
        raise PointFileError(path, "vertex", "a property name repeats")
    if fmt == "ascii":
        lines_before = sum(e[1] for e in elements[:vi])
        text = data[body:]
        skip = 0
        for _ in range(lines_before):  # the lines of the elements before vertex (one item a line)
            end = text.find(b"\n", skip)
            if end < 0:
                raise PointFileError(path, "data", f"truncated before the vertex element ({lines_before} lines of "
                                                   "earlier elements expected)")
            skip = end + 1
        table = _ascii_table(path, text[skip:], len(props), n, f"{len(props)} vertex properties", more_ok=True,
                             label="vertex line")
        columns = {}
        for j, (name, kind) in enumerate(props):
            values = table[:, j]
            columns[name] = values.astype(kind) if kind[0] != "f" and np.all(np.isfinite(values)) else values
        return columns, ()
    order = PLY_FORMATS[fmt]
    offset = body
    for name, count, eprops in elements[:vi]:
        if any(kind == "list" for _, kind in eprops):
            raise PointFileError(path, name, "an element with a list property before 'vertex' in a binary PLY is "
                                             "not supported: write the vertex element first")
        offset += count * sum(int(kind[1]) for _, kind in eprops)
    dtype = np.dtype([(name, order + kind) for name, kind in props])
    have = len(data) - offset
    if have < n * dtype.itemsize:
        _check_length(path, have, n, dtype.itemsize, "binary PLY vertex")
    rows = np.frombuffer(data, dtype, count=n, offset=offset)  # later elements (faces, ...) are not read
    return {name: rows[name].astype(rows[name].dtype.newbyteorder("=")) for name, _ in props}, ()


# --- poses --------------------------------------------------------------------------------------------------------

def _numbers(path: str, where: str, text: str) -> list[float]:
    tokens = [t for t in re.split(r"[\s,]+", text.split("#", 1)[0]) if t]
    try:
        return [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_number(t))
        raise PointFileError(path, where, f"{bad!r} is not a number") from None


def _is_number(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _pose_of_numbers(path: str, where: str, values) -> np.ndarray:
    values = np.asarray(values, np.float64).reshape(-1)
    if values.size == 12:
        values = np.concatenate([values, [0.0, 0.0, 0.0, 1.0]])
    if values.size != 16:
        raise PointFileError(path, where, f"{values.size} numbers; a pose is a 4x4 (16 numbers) or 3x4 (12 numbers) "
                                          "vehicle -> world matrix, row by row")
    pose = values.reshape(4, 4)
    from ff3d_tf import geometry  # the project's one pose check
    problem = geometry.pose_problem_np(pose, "the pose")
    if problem is not None:
        raise PointFileError(path, where, problem)
    return pose


def read_pose(path: str) -> np.ndarray:
    """A [4,4] float64 vehicle -> world pose from a text file or `.npy` (module docstring), checked rigid."""
    if not os.path.isfile(path):
        raise PointFileError(path, "pose", "missing (not a file)")
    if path.lower().endswith(".npy"):
        try:
            a = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as err:
            raise PointFileError(path, "pose", f"not a readable .npy array ({err})") from None
        if a.shape not in ((4, 4), (3, 4)) or not np.issubdtype(a.dtype, np.number):
            raise PointFileError(path, "pose", f"array of shape {a.shape} and type {a.dtype}: expected a [4,4] or "
                                               "[3,4] numeric matrix")
        return _pose_of_numbers(path, "pose", a)
    with open(path, encoding="utf-8", errors="replace") as f:
        text = f.read()
    values = []
    for i, line in enumerate(text.splitlines(), start=1):
        values += _numbers(path, f"line {i}", line)
    return _pose_of_numbers(path, "pose", values)


def read_pose_list(path: str) -> list[np.ndarray]:
    """Poses of a `poses.txt`: one per non-blank, non-comment line, 12 or 16 numbers (row-major 3x4 or 4x4)."""
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = f.read().splitlines()
    poses = []
    for i, line in enumerate(lines, start=1):
        values = _numbers(path, f"line {i}", line)
        if values:
            poses.append(_pose_of_numbers(path, f"line {i}", values))
    return poses


# --- directories of sweeps ------------------------------------------------------------------------------------------

def _is_sweep_name(name: str) -> bool:
    lower = name.lower()
    return lower.endswith(POINT_SUFFIXES) and not lower.endswith(SWEEP_POSE_SUFFIXES)


def list_sweeps(directory: str) -> list[str]:
    """The point files of a directory, sorted by name; at least two (one pair)."""
    if not os.path.isdir(directory):
        raise PointFileError(directory, "file", "not a directory of sweeps")
    sweeps = sorted(os.path.join(directory, n) for n in os.listdir(directory)
                    if _is_sweep_name(n) and os.path.isfile(os.path.join(directory, n)))
    if len(sweeps) < 2:
        raise PointFileError(directory, "file", f"{len(sweeps)} point files ({', '.join(POINT_SUFFIXES)}); a pair "
                                                "needs two consecutive sweeps")
    by_stem: dict[str, str] = {}
    for sweep in sweeps:
        other = by_stem.setdefault(os.path.splitext(sweep)[0], sweep)
        if other != sweep:
            raise PointFileError(sweep, "file", f"the same name as {os.path.basename(other)} but another suffix: "
                                                "outputs and pose files are named after the sweep, keep one of them")
    return sweeps


def sweep_pose_files(sweep: str) -> list[str]:
    """The per-sweep pose files that exist beside a sweep (`<stem>.pose.txt`, `<stem>.pose.npy`)."""
    stem = os.path.splitext(sweep)[0]
    return [stem + s for s in SWEEP_POSE_SUFFIXES if os.path.isfile(stem + s)]


def sweep_poses(directory: str, sweeps: list[str]) -> list[np.ndarray] | None:
    """The pose of each sweep (`poses.txt` or one file per sweep), or None when the directory has no poses."""
    listing = os.path.join(directory, POSES_FILE)
    per_sweep = [sweep_pose_files(s) for s in sweeps]
    if os.path.isfile(listing):
        if any(per_sweep):
            first = next(f for f in per_sweep if f)[0]
            raise PointFileError(first, "pose", f"a per-sweep pose beside {listing}: give the poses one way only")
        poses = read_pose_list(listing)
        if len(poses) != len(sweeps):
            raise PointFileError(listing, "file", f"{len(poses)} poses for {len(sweeps)} sweeps (one line per sweep, "
                                                  "in the sweeps' name order)")
        return poses
    if not any(per_sweep):
        return None
    for sweep, found in zip(sweeps, per_sweep):
        stem = os.path.splitext(sweep)[0]
        if not found:
            raise PointFileError(stem + SWEEP_POSE_SUFFIXES[0], "pose", f"missing: other sweeps of {directory} have "
                                                                       "a pose file, so every sweep needs one")
        if len(found) > 1:
            raise PointFileError(found[1], "pose", f"a second pose file of {os.path.basename(sweep)} "
                                                   f"(also {os.path.basename(found[0])}): keep one")
    return [read_pose(f[0]) for f in per_sweep]


# --- outputs ------------------------------------------------------------------------------------------------------

FLOW_FEATHER_COLUMNS = ("x_m", "y_m", "z_m", "flow_x_mps", "flow_y_mps", "flow_z_mps", "point_valid")


def write_predictions(stem: str, points_xyz_t0: np.ndarray, flow_mps: np.ndarray, point_valid: np.ndarray,
                      ) -> tuple[str, str]:
    """`<stem>.npz` (flow_mps [N,3] float32 m/s in the t0 vehicle frame, point_valid [N] bool, points_xyz_t0 [N,3])
    and `<stem>.feather` (one row per t0 point, in the file's order: `FLOW_FEATHER_COLUMNS`); both paths."""
    import pyarrow as pa
    import pyarrow.feather as feather
    xyz = np.asarray(points_xyz_t0, np.float32)
    flow = np.asarray(flow_mps, np.float32)
    valid = np.asarray(point_valid, bool)
    npz = stem + ".npz"
    np.savez_compressed(npz, flow_mps=flow, point_valid=valid, points_xyz_t0=xyz)
    table = pa.table(dict(zip(FLOW_FEATHER_COLUMNS, [*xyz.T, *flow.T, valid])))
    path = stem + ".feather"
    feather.write_feather(table, path)
    return npz, path
