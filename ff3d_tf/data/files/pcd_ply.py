"""The PCD and PLY parsers behind `point_files.read_point_file`: headers, ASCII tables, binary rows and PCL's LZF.

`read_pcd` reads PCL's PCD v0.7 (and older headers of the same form): DATA ascii, binary or binary_compressed (LZF,
decoded by `lzf_decompress`); TYPE F (4, 8 bytes), I and U (1, 2, 4, 8 bytes); little-endian. `read_ply` reads the
element `vertex` of a PLY file, format ascii, binary_little_endian or binary_big_endian. Each returns (the file's
columns by name, in the file's order; remarks for the user); `point_files` picks x, y, z and the intensity out of them
and checks their values. Errors are `PointFileError`, naming the file and the field or part of the file (header, data,
"header line N", "data line N", "vertex line N").
"""
from __future__ import annotations

import numpy as np

from ff3d_tf.data.files.point_file_errors import PointFileError

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
# LZF's densest code is a back reference of 264 bytes in 3 input bytes: a stream never decodes to more than 88 times
# its length, so a binary_compressed header claiming more lies, and its claim is never allocated.
LZF_MAX_RATIO = 88


# --- headers and ASCII tables (PCD and PLY) -----------------------------------------------------------------------

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


def _check_length(path: str, have: int, n: int, row_bytes: int, what: str) -> None:
    need = n * row_bytes
    if have < need:
        raise PointFileError(path, "data", f"truncated: the header says {n} points of {row_bytes} bytes "
                                           f"({need} bytes of {what} data), the file has {have}")
    if have > need:
        raise PointFileError(path, "data", f"{have - need} bytes after the last of the header's {n} points: the "
                                           "header's fields or point count do not match the data")


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


# --- PCD ----------------------------------------------------------------------------------------------------------

def read_pcd(path: str) -> tuple[dict[str, np.ndarray], tuple[str, ...]]:
    """The fields of a PCD file by name (a repeated name is kept apart as `name#i`), and a remark when its VIEWPOINT
    is not the identity (module docstring)."""
    with open(path, "rb") as f:
        data = f.read()
    lines, body = _header_lines(path, data, "DATA")
    fields, kinds, counts, n, data_kind, notes = _pcd_header(path, lines)
    cols = _pcd_data(path, data[body:], fields, kinds, counts, n, data_kind)
    columns = {}
    for (name, values), field, c in zip(cols.items(), fields, counts):
        if field in columns:
            field = name  # a repeated name: kept apart
        columns[field] = values[:, 0] if c == 1 else values
    return columns, tuple(notes)


def _pcd_header(path: str, lines: list[str]):
    """(FIELDS, their NumPy kinds, COUNTs, the number of points, the DATA kind, remarks) of a PCD header, checked."""
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
    return fields, kinds, counts, n, data_kind, notes


def _pcd_data(path: str, raw: bytes, fields: list[str], kinds: list[str], counts: list[int], n: int,
              data_kind: str) -> dict[str, np.ndarray]:
    """[n, COUNT] columns of the data after a PCD header, by unique name `field#i`, in the header's order."""
    names = [f"{name}#{i}" for i, name in enumerate(fields)]  # unique even where a name repeats (PCL's "_" padding)
    if data_kind == "ascii":
        table = _ascii_table(path, raw, sum(counts), n, f"{len(fields)} fields")
        cols, start = {}, 0
        for name, kind, c in zip(names, kinds, counts):
            cols[name] = table[:, start:start + c].astype(np.float64)
            start += c
            cols[name] = cols[name].astype(kind) if np.all(np.isfinite(cols[name])) and kind[0] != "f" else \
                cols[name]
        return cols
    row_bytes = sum(int(kind[1]) * c for kind, c in zip(kinds, counts))
    if data_kind == "binary":  # the header's sizes against the file's before any array is made
        _check_length(path, len(raw), n, row_bytes, "binary PCD")
    else:
        raw = _pcd_decompressed(path, raw, n * row_bytes)
    dtype = np.dtype([(name, "<" + kind, (c,)) for name, kind, c in zip(names, kinds, counts)])
    if data_kind == "binary_compressed":
        cols, start = {}, 0
        for name, kind, c in zip(names, kinds, counts):  # field by field: all x, then all y, ...
            block = n * c * int(kind[1])
            cols[name] = np.frombuffer(raw, "<" + kind, count=n * c, offset=start).reshape(n, c)
            start += block
        return cols
    rows = np.frombuffer(raw, dtype, count=n)
    return {name: rows[name].reshape(n, c) for name, c in zip(names, counts)}


def _pcd_decompressed(path: str, raw: bytes, expected: int) -> bytes:
    if len(raw) < 8:
        raise PointFileError(path, "data", "truncated: binary_compressed data needs its two uint32 sizes")
    compressed, uncompressed = (int(v) for v in np.frombuffer(raw[:8], "<u4"))
    if uncompressed != expected:
        raise PointFileError(path, "data", f"binary_compressed: uncompressed size {uncompressed} bytes, but the "
                                           f"header's points and fields make {expected}")
    if uncompressed > LZF_MAX_RATIO * compressed:
        raise PointFileError(path, "data", f"binary_compressed: {uncompressed} bytes claimed from {compressed} "
                                           f"compressed; LZF expands at most {LZF_MAX_RATIO}:1 (a lying header)")
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


# --- PLY ----------------------------------------------------------------------------------------------------------

def read_ply(path: str) -> tuple[dict[str, np.ndarray], tuple[str, ...]]:
    """The vertex properties of a PLY file by name (module docstring); no remarks."""
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
