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
|        | decoded by `pcd_ply.lzf_decompress`); TYPE F (4, 8 bytes), I and U (1, 2, 4, 8 bytes); little-endian |
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
The PCD and PLY parsers live in `pcd_ply`; `PointFileError` in `point_file_errors` (both modules raise it).
"""
from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data.files import pcd_ply
from ff3d_tf.data.files.point_file_errors import PointFileError

POINT_SUFFIXES = (".npy", ".npz", ".bin", ".pcd", ".ply")
INTENSITY_FIELDS = ("intensity", "reflectance", "scalar_intensity")  # column names read as intensity (any case)
NPZ_KEYS = ("points", "x", "y", "z", "intensity")
POSES_FILE = "poses.txt"  # in a sweeps directory: one pose per line, in sweep order
SWEEP_POSE_SUFFIXES = (".pose.txt", ".pose.npy")  # per-sweep pose files: <sweep stem><suffix>
BIN_FIELDS = ("x", "y", "z", "intensity")  # KITTI .bin: float32 each
NUSCENES_BIN_SUFFIX = ".pcd.bin"  # nuScenes lidar sweeps: float32 x, y, z, intensity, ring index
NUSCENES_BIN_FIELDS = ("x", "y", "z", "intensity", "ring")


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
    readers = {".npy": _read_npy, ".npz": _read_npz, ".bin": _read_bin, ".pcd": pcd_ply.read_pcd,
               ".ply": pcd_ply.read_ply}
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


# Deflate expands at most ~1032:1 (RFC 1951: a 258-byte match per ~2 bits at best); a zip member claiming more is a
# lie, and its claim is never allocated.
_DEFLATE_MAX_RATIO = 1032
_NPY_MAX_HEADER_BYTES = 10000  # NumPy's own bound on an .npy header


def _npy_header(path: str, stream, where: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran order, dtype) of an .npy header read from `stream`, which is left at the first data byte."""
    from numpy.lib import format as npy_format
    try:
        version = npy_format.read_magic(stream)
        if version == (1, 0):
            shape, fortran, dtype = npy_format.read_array_header_1_0(stream, _NPY_MAX_HEADER_BYTES)
        elif version == (2, 0):
            shape, fortran, dtype = npy_format.read_array_header_2_0(stream, _NPY_MAX_HEADER_BYTES)
        else:
            raise ValueError(f"format version {version[0]}.{version[1]}: versions 1.0 and 2.0 are read (save with "
                             "ASCII field names)")
    except (ValueError, OSError, EOFError, SyntaxError, TypeError) as err:
        raise PointFileError(path, where, f"not a readable .npy array ({err})") from None
    if dtype.hasobject:
        raise PointFileError(path, where, f"type {dtype}: holds Python objects (pickled); point files hold numbers")
    if dtype.itemsize == 0:  # no bytes a value: any shape would fit any file, so the size check below cannot hold
        raise PointFileError(path, where, f"type {dtype!r} has no bytes a value; point files hold numbers")
    shape = tuple(int(d) for d in shape)
    if any(d < 0 for d in shape):
        raise PointFileError(path, where, f"the header says shape {shape}: a negative dimension")
    return shape, bool(fortran), dtype


def _npy_array(path: str, stream, total_bytes: int, where: str) -> np.ndarray:
    """The array of an .npy stream (a file or a zip member, at its start) of `total_bytes` bytes: the header's shape
    and type are checked against the bytes that follow it before anything is allocated (a header that lies about its
    size is an error, never an allocation)."""
    shape, fortran, dtype = _npy_header(path, stream, where)
    have = total_bytes - stream.tell()
    count = 1
    for d in shape:
        count *= d
    need = count * dtype.itemsize
    if need != have:
        why = "truncated" if need > have else "bytes after the data: the header does not match it"
        raise PointFileError(path, where, f"the header says shape {shape} of {dtype} ({need} bytes of data), the "
                                          f"data has {have} bytes ({why})")
    data = stream.read(need)
    if len(data) != need:
        raise PointFileError(path, where, f"truncated: {len(data)} of {need} bytes of data could be read")
    a = np.frombuffer(data, dtype)
    return a.reshape(shape[::-1]).T if fortran else a.reshape(shape)


def load_npy(path: str, where: str = "file") -> np.ndarray:
    """An .npy file's array (no pickled objects), its header checked against the file's size before reading."""
    with open(path, "rb") as f:
        return _npy_array(path, f, os.fstat(f.fileno()).st_size, where)


def load_npz(path: str) -> dict[str, np.ndarray]:
    """The arrays of an .npz archive by name, each member's size checked against what its compressed bytes can hold
    and its header against its size, before anything is allocated."""
    import zipfile
    import zlib
    arrays = {}
    try:
        with zipfile.ZipFile(path) as z:
            for info in z.infolist():
                if not info.filename.endswith(".npy"):
                    raise PointFileError(path, info.filename, "not an .npy member: an .npz holds arrays only")
                key = info.filename[:-4]
                stored = info.compress_type == zipfile.ZIP_STORED
                if (stored and info.file_size != info.compress_size) or \
                        info.file_size > _DEFLATE_MAX_RATIO * info.compress_size + 1024:
                    raise PointFileError(path, key, f"the archive says {info.file_size} bytes from "
                                                    f"{info.compress_size} compressed: more than its compression holds")
                with z.open(info) as member:
                    arrays[key] = _npy_array(path, member, info.file_size, key)
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, NotImplementedError, RuntimeError) as err:
        raise PointFileError(path, "file", f"not a readable .npz archive ({type(err).__name__}: {err})") from None
    return arrays


def _read_npy(path: str):
    return _array_columns(path, load_npy(path), "array"), ()


def _read_npz(path: str):
    arrays = load_npz(path)
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
        a = load_npy(path, "pose")
        if a.shape not in ((4, 4), (3, 4)) or a.dtype.names or not (np.issubdtype(a.dtype, np.integer) or
                                                                     np.issubdtype(a.dtype, np.floating)):
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
