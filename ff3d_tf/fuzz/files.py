"""Fuzzing of the readers of your own sequences (`ff3d_tf.data.files`): a small clean sequence of every point format
(npy, npz, PCD binary_compressed and ascii, PLY, KITTI .bin, nuScenes .pcd.bin) with poses, timestamps and a box
table; one file damaged per mutant (`KINDS`: headers that lie about counts and sizes, LZF bombs, truncation, NaN,
object arrays, bit flips; damaged pose files, timestamp files and box tables); then everything the records job reads
of the sequence: its sweeps, poses, times, box table, and every point file as a frame.

A named error is a `PointFileError` naming the damaged file and a field (or line, row and column). Besides the
report's defects, a read whose traced allocations peak above `ALLOCATION_BOUND_FACTOR` times the sequence's bytes (plus
`ALLOCATION_SLACK_BYTES`) is a `huge_allocation`: a reader that believed a header.
"""
from __future__ import annotations

import os
import re
import shutil
import struct
import tracemalloc
import zipfile

import numpy as np

from ff3d_tf.data.files import box_table, point_files, sequences
from ff3d_tf.data.files.point_file_errors import PointFileError
from ff3d_tf.fuzz.report import NONFINITE, Report, check_frame, judge, pick

POINT_KINDS = ("npy_shape_lie", "npy_object_array", "npz_size_lie", "npz_shape_lie", "pcd_points_lie",
               "pcd_count_lie", "lzf_bomb", "ply_count_lie", "truncate_points", "nan_point", "bit_flip_points")
OTHER_KINDS = ("pose_damage", "timestamps_damage", "box_table_damage", "bit_flip_any", "truncate_any")
KINDS = POINT_KINDS + OTHER_KINDS
ALLOCATION_BOUND_FACTOR = 64  # a read may hold a few copies of its inputs, never what a header claims
ALLOCATION_SLACK_BYTES = 32 << 20
HUGE_POINTS = 4_000_000_000  # what a lying header claims: 4e9 points (64 GB of float32 x, y, z, intensity)
SWEEP_NAMES = ("000000.npy", "000001.npz", "000002.pcd", "000003.ply", "000004.bin", "000005.pcd.bin", "000006.pcd")


def _literal_lzf(data: bytes) -> bytes:
    """A valid LZF stream of `data` made of literal runs only (32 bytes each at most)."""
    return b"".join(bytes([len(c) - 1]) + c for c in (data[i:i + 32] for i in range(0, len(data), 32)))


def write_clean_sequence(directory: str, num_points: int = 300, seed: int = 0) -> str:
    """The clean sequence of the module docstring (`SWEEP_NAMES`), an object moving through it with its boxes."""
    rng = np.random.default_rng(seed)
    if os.path.exists(directory):
        shutil.rmtree(directory)
    os.makedirs(directory)
    stems = []
    for k, name in enumerate(SWEEP_NAMES):
        xyz = rng.uniform([-20, -20, -2], [20, 20, 2], (num_points, 3)).astype(np.float32)
        xyz[:40] = rng.uniform([-2, -1, -0.7], [2, 1, 0.7], (40, 3)) + [5.0 + 0.5 * k, 2.0, 0.0]
        intensity = rng.uniform(0, 1, num_points).astype(np.float32)
        path = os.path.join(directory, name)
        if name.endswith(".npy"):
            a = np.zeros(num_points, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1")])
            a["x"], a["y"], a["z"] = xyz.T
            a["intensity"] = (intensity * 255).astype(np.uint8)
            np.save(path, a)
        elif name.endswith(".npz"):
            np.savez_compressed(path, points=np.concatenate([xyz, intensity[:, None]], 1))
        elif name.endswith(".pcd.bin"):
            ring = np.arange(num_points, dtype=np.float32) % 32
            np.concatenate([xyz, intensity[:, None], ring[:, None]], 1).astype("<f4").tofile(path)
        elif name.endswith(".bin"):
            np.concatenate([xyz, intensity[:, None]], 1).astype("<f4").tofile(path)
        elif name.endswith(".pcd") and k == 2:
            body = b"".join(np.ascontiguousarray(c, "<f4").tobytes() for c in (*xyz.T, intensity))
            packed = _literal_lzf(body)
            head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                    f"WIDTH {num_points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {num_points}\n"
                    "DATA binary_compressed\n").encode()
            with open(path, "wb") as f:
                f.write(head + struct.pack("<II", len(packed), len(body)) + packed)
        elif name.endswith(".pcd"):
            head = (f"VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                    f"WIDTH {num_points}\nHEIGHT 1\nPOINTS {num_points}\nDATA ascii\n")
            with open(path, "w") as f:
                f.write(head + "".join(f"{x!r} {y!r} {z!r} {i!r}\n" for (x, y, z), i in
                                       zip(xyz.tolist(), intensity.tolist())))
        else:
            head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {num_points}\nproperty float x\n"
                    "property float y\nproperty float z\nproperty float intensity\nend_header\n").encode()
            with open(path, "wb") as f:
                f.write(head + np.concatenate([xyz, intensity[:, None]], 1).astype("<f4").tobytes())
        stems.append(os.path.splitext(name)[0])
    poses = [np.eye(4) for _ in stems]
    for k, pose in enumerate(poses):
        pose[0, 3] = 0.8 * k
    with open(os.path.join(directory, point_files.POSES_FILE), "w") as f:
        f.write("".join(" ".join(repr(float(v)) for v in p[:3].reshape(-1)) + "\n" for p in poses))
    with open(os.path.join(directory, sequences.TIMESTAMPS_FILE), "w") as f:
        f.write("".join(f"{1700000000 + k // 10}.{k % 10}00000000\n" for k in range(len(stems))))
    boxes = {stem: {"center": np.array([[5.0 + 0.5 * k, 2.0, 0.0]]), "size": np.array([[4.2, 2.2, 1.6]]),
                    "heading": np.array([0.0]), "track_id": np.array(["car"]), "class_id": np.array([1], np.int32)}
             for k, stem in enumerate(stems)}
    box_table.write_box_table(os.path.join(directory, box_table.BOX_TABLE_NAMES[0]), boxes)
    return directory


def read_sequence_like_the_job(directory: str) -> list[dict]:
    """Everything the records job reads of a sequence: its sweeps, poses, times and boxes, and each sweep as a frame
    (`point_files.frame_from_columns`); the frames."""
    seq = sequences.read_sequence(directory)
    sequences.read_boxes(seq)
    poses = seq.poses or [None] * len(seq.sweeps)
    return [point_files.frame_from_columns(point_files.read_point_file(s), p, None, t // 1000)
            for s, p, t in zip(seq.sweeps, poses, seq.timestamps_ns)]


def _npy_with_header(header: dict, data: bytes) -> bytes:
    import io
    from numpy.lib import format as npy_format
    buffer = io.BytesIO()
    npy_format.write_array_header_1_0(buffer, header)
    return buffer.getvalue() + data


def _text_lines(path: str) -> list[str]:
    with open(path, encoding="utf-8") as f:
        return f.read().splitlines()


def _write_lines(path: str, lines: list[str]) -> None:
    with open(path, "w", encoding="utf-8") as f:
        f.write("".join(line + "\n" for line in lines))


def _at(directory: str, name: str) -> str:
    return os.path.join(directory, name)


def _npy_header_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """A .npy header whose shape does not match its data."""
    path = _at(directory, "000000.npy")
    data = open(path, "rb").read()
    a = point_files.load_npy(path)
    shape = pick(rng, [(HUGE_POINTS,), (HUGE_POINTS, 4), (len(a) + 1,), (len(a) - 1,), (2 ** 62,)])
    descr = pick(rng, [a.dtype.descr, "<f4", "<f8"])
    offset = len(data) - a.nbytes
    with open(path, "wb") as f:
        f.write(_npy_with_header({"descr": descr, "fortran_order": False, "shape": shape}, data[offset:]))
    return path, f"{kind}: header shape {shape} of {descr}"


def _npy_object_array(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """A .npy of pickled objects."""
    path = _at(directory, "000000.npy")
    np.save(path, np.array([object()] * 5 + [1.5], dtype=object), allow_pickle=True)
    return path, f"{kind}: a pickled object array"


def _npz_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """A .npz whose archive size or member header lies."""
    path = _at(directory, "000001.npz")
    data = bytearray(open(path, "rb").read())
    if kind == "npz_size_lie":  # the central directory's uncompressed size of the member
        where = data.find(b"PK\x01\x02")
        claim = pick(rng, [0xFFFFFFF0, 1 << 31, 12345])
        data[where + 24:where + 28] = struct.pack("<I", claim)
        with open(path, "wb") as f:
            f.write(bytes(data))
        return path, f"{kind}: the archive claims {claim} bytes uncompressed"
    shape = pick(rng, [(HUGE_POINTS, 4), (300, 400000), (299, 4)])
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("points.npy", _npy_with_header({"descr": "<f4", "fortran_order": False, "shape": shape},
                                                  np.zeros((300, 4), "<f4").tobytes()))
    return path, f"{kind}: member header shape {shape}"


def _pcd_header_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """A .pcd whose POINTS, WIDTH or COUNT lies, or an LZF stream claiming far more than it holds."""
    path = _at(directory, "000002.pcd") if kind == "lzf_bomb" or rng.integers(2) else _at(directory, "000006.pcd")
    data = open(path, "rb").read()
    end = data.find(b"DATA")
    head, rest = data[:end].decode(), data[end:]
    if kind == "pcd_points_lie":
        n = pick(rng, [HUGE_POINTS, 301, 10 ** 20])
        head = re.sub(r"POINTS \d+", f"POINTS {n}", re.sub(r"WIDTH \d+", f"WIDTH {n}", head))
        what = f"POINTS and WIDTH {n}"
    elif kind == "pcd_count_lie":
        count = pick(rng, ["1000000000 1 1 1", "1 1 1 99999999999999999999", "2 1 1 1", "1 1 1"])
        head = re.sub(r"COUNT [\d ]+\n", f"COUNT {count}\n", head)
        what = f"COUNT {count}"
    else:  # binary_compressed claiming far more than its stream: points and uncompressed size agree
        n = pick(rng, [200_000_000, 10_000_000, 4_000_000])  # n * 16 bytes within the uint32 size field
        head = re.sub(r"POINTS \d+", f"POINTS {n}", re.sub(r"WIDTH \d+", f"WIDTH {n}", head))
        repeat = bytes([0x00, 0x41]) + bytes([0xE0, 0xFF, 0x00]) * 200  # one literal, then 264-byte copies
        rest = b"DATA binary_compressed\n" + struct.pack("<II", len(repeat), n * 16) + repeat
        what = f"{n} points claimed by an LZF stream of {len(repeat)} bytes"
    with open(path, "wb") as f:
        f.write(head.encode() + rest)
    return path, f"{kind}: {what}"


def _ply_count_lie(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """A .ply whose vertex count lies."""
    path = _at(directory, "000003.ply")
    data = open(path, "rb").read()
    n = pick(rng, [HUGE_POINTS, 301, 299, 10 ** 19])
    with open(path, "wb") as f:
        f.write(re.sub(rb"element vertex \d+", f"element vertex {n}".encode(), data, count=1))
    return path, f"{kind}: element vertex {n}"


def _nonfinite_point(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """One coordinate of one point not finite, in a binary, .npz or text .pcd sweep."""
    name = pick(rng, ["000004.bin", "000005.pcd.bin", "000001.npz", "000006.pcd"])
    path = _at(directory, name)
    value = float(pick(rng, NONFINITE))
    if name.endswith(".npz"):
        with np.load(path) as z:
            points = z["points"].copy()
        points[int(rng.integers(len(points))), int(rng.integers(3))] = value
        np.savez_compressed(path, points=points)
    elif name.endswith(".pcd"):
        lines = _text_lines(path)
        body = [i for i, line in enumerate(lines) if line and line[0] in "-0123456789"]
        i = pick(rng, body)
        values = lines[i].split()
        values[int(rng.integers(3))] = repr(value)
        lines[i] = " ".join(values)
        _write_lines(path, lines)
    else:
        width = 5 if name.endswith(".pcd.bin") else 4
        rows = np.fromfile(path, "<f4").reshape(-1, width)
        rows[int(rng.integers(len(rows))), int(rng.integers(3))] = value
        rows.tofile(path)
    return path, f"{kind}: {value} in {name}"


def _bytes_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """A point file (or any file) truncated or with bits flipped."""
    names = list(SWEEP_NAMES) if kind.endswith("points") else sorted(os.listdir(directory))
    path = _at(directory, pick(rng, names))
    data = bytearray(open(path, "rb").read())
    if kind.startswith("truncate"):
        data = data[: int(rng.integers(0, max(len(data), 1)))]
    else:
        for _ in range(int(rng.integers(1, 17))):
            if data:
                data[int(rng.integers(len(data)))] ^= 1 << int(rng.integers(8))
    with open(path, "wb") as f:
        f.write(bytes(data))
    return path, f"{kind}: {os.path.basename(path)}"


def _pose_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """One line of the poses file damaged or dropped."""
    path = _at(directory, point_files.POSES_FILE)
    lines = _text_lines(path)
    i = int(rng.integers(len(lines)))
    values = lines[i].split()
    how = pick(rng, ["nan", "scale", "drop_number", "text", "drop_line", "reflect"])
    if how == "nan":
        values[int(rng.integers(len(values)))] = str(pick(rng, NONFINITE))
    elif how == "scale":
        values[0] = "1.5"
    elif how == "drop_number":
        values = values[:-1]
    elif how == "text":
        values[int(rng.integers(len(values)))] = "x1"
    elif how == "reflect":
        values[0] = "-1"
    lines[i] = " ".join(values)
    if how == "drop_line":
        del lines[i]
    _write_lines(path, lines)
    return path, f"{kind}: {how} at line {i + 1}"


def _timestamps_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """One line of the timestamps file damaged."""
    path = _at(directory, sequences.TIMESTAMPS_FILE)
    lines = _text_lines(path)
    i = int(rng.integers(1, len(lines)))
    how = pick(rng, ["backwards", "nan", "drop_line", "text", "huge", "two_values"])
    lines[i] = {"backwards": "1.0", "nan": "nan", "text": "soon", "huge": "1e400", "two_values": "1 2",
                "drop_line": ""}[how]
    _write_lines(path, lines)
    return path, f"{kind}: {how} at line {i + 1}"


def _box_table_damage(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """One row or column of the box table damaged."""
    path = _at(directory, box_table.BOX_TABLE_NAMES[0])
    lines = _text_lines(path)
    header = lines[0].split(",")
    i = int(rng.integers(1, len(lines)))
    cells = lines[i].split(",")
    how = pick(rng, ["drop_column", "unknown_class", "negative_size", "track_gap", "nan", "text_number",
                     "duplicate_row", "unknown_sweep", "short_row", "not_utf8"])
    if how == "drop_column":
        j = int(rng.integers(len(header)))
        lines = [",".join(c for k, c in enumerate(line.split(",")) if k != j) for line in lines]
    elif how == "track_gap":
        if len(lines) > 3:
            del lines[2]
    elif how == "duplicate_row":
        lines.insert(i, lines[i])
    elif how == "short_row":
        lines[i] = ",".join(cells[:5])
    elif how == "not_utf8":
        with open(path, "wb") as f:
            f.write("\n".join(lines).encode() + b"\n\xff\xfe,\x80\n")
        return path, f"{kind}: {how}"
    else:
        column = {"unknown_class": "class", "negative_size": pick(rng, ["length", "width", "height"]),
                  "nan": pick(rng, list(box_table.NUMERIC_COLUMNS)),
                  "text_number": pick(rng, list(box_table.NUMERIC_COLUMNS)), "unknown_sweep": "sweep"}[how]
        cells[header.index(column)] = {"unknown_class": "spaceship", "negative_size": "-2", "nan": "nan",
                                       "text_number": "wide", "unknown_sweep": "999999"}[how]
        lines[i] = ",".join(cells)
    _write_lines(path, lines)
    return path, f"{kind}: {how} at row {i}"


# Each kind's mutation: (directory, kind, rng) -> (path of the damaged file, what was done).
_MUTATIONS = {"npy_shape_lie": _npy_header_damage, "npy_object_array": _npy_object_array,
              "npz_size_lie": _npz_damage, "npz_shape_lie": _npz_damage, "pcd_points_lie": _pcd_header_damage,
              "pcd_count_lie": _pcd_header_damage, "lzf_bomb": _pcd_header_damage, "ply_count_lie": _ply_count_lie,
              "nan_point": _nonfinite_point, "truncate_points": _bytes_damage, "bit_flip_points": _bytes_damage,
              "bit_flip_any": _bytes_damage, "truncate_any": _bytes_damage, "pose_damage": _pose_damage,
              "timestamps_damage": _timestamps_damage, "box_table_damage": _box_table_damage}


def mutate(directory: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """Damages one file of a (copied) clean sequence in place: (path of the damaged file, what was done)."""
    if kind not in _MUTATIONS:
        raise ValueError(f"unknown files mutation kind {kind!r}; one of {KINDS}")
    return _MUTATIONS[kind](directory, kind, rng)


def _input_bytes(directory: str) -> int:
    return sum(os.path.getsize(os.path.join(directory, n)) for n in os.listdir(directory))


def classify(call, path: str, input_bytes: int) -> tuple[str, str]:
    """(outcome, detail) of reading a damaged sequence: `call()` returns its frames or raises; traced allocations
    above the bound are a `huge_allocation` whatever the outcome."""
    tracemalloc.start()
    try:
        try:
            frames = call()
        except PointFileError as err:
            named = bool(err.field) and (err.path == path or os.path.basename(path) in str(err))
            outcome, detail = ("named_error" if named else "unnamed_error"), str(err)
        except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
            outcome, detail = "crash", f"{type(err).__name__}: {err}"
        else:
            problem = next((p for p in (check_frame(f) for f in frames) if p), None)
            outcome, detail = ("nonfinite", problem) if problem else ("decoded", f"{len(frames)} sweeps")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    bound = ALLOCATION_BOUND_FACTOR * input_bytes + ALLOCATION_SLACK_BYTES
    if peak > bound:
        return "huge_allocation", f"{peak} bytes allocated reading {input_bytes} bytes ({outcome}: {detail})"
    return outcome, detail


def fuzz_sequence(work_dir: str, num_mutants: int, seed: int = 0, kinds=KINDS, report: Report | None = None,
                  hang_s: float | None = None) -> Report:
    """Damages a fresh copy of the clean sequence per mutant (kinds round-robin) and reads it as the records job does
    (`read_sequence_like_the_job`); `hang_s`: the watchdog's bound on one input (None: none)."""
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    clean = write_clean_sequence(os.path.join(work_dir, "clean"), seed=seed)
    read_sequence_like_the_job(clean)  # the clean copy reads
    for i in range(num_mutants):
        kind = kinds[i % len(kinds)]
        seq = os.path.join(work_dir, "mutant")
        if os.path.exists(seq):
            shutil.rmtree(seq)
        shutil.copytree(clean, seq)
        path, what = mutate(seq, kind, rng)
        size = _input_bytes(seq)
        judge(report, kind, what, lambda: classify(lambda: read_sequence_like_the_job(seq), path, size), hang_s)
    return report
