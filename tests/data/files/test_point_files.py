"""Readers of a user's own point files: every format written here by hand (text, or bytes with struct/NumPy) and
read back equal to the arrays it was written from; bad files raise PointFileError naming the file and field."""
import os
import struct

import numpy as np
import pytest

from ff3d_tf import geometry, schema
from ff3d_tf.data.files import pcd_ply
from ff3d_tf.data.files import point_files as pf
from ff3d_tf.data.files.point_file_errors import PointFileError

RNG = np.random.default_rng(3)
XYZ = RNG.uniform(-30, 30, (7, 3)).astype(np.float32)
INTENSITY_U8 = np.array([0, 17, 255, 128, 3, 90, 200], np.uint8)
INTENSITY_F = RNG.uniform(0, 1, 7).astype(np.float32)


def _write(path, data):
    mode = "w" if isinstance(data, str) else "wb"
    with open(path, mode) as f:
        f.write(data)
    return str(path)


def _raises(path, field, fn, *args):
    """Calls fn(*args) expecting a PointFileError that names `path` and `field`; returns its message."""
    with pytest.raises(PointFileError) as err:
        fn(*args)
    message = str(err.value)
    assert str(path) in message and err.value.field == field, message
    return message


# --- an LZF compressor written independently of the reader's decoder (greedy, 3-byte hash of last positions) ---------

def lzf_compress(data: bytes) -> bytes:
    out, literal, last, i, n = bytearray(), bytearray(), {}, 0, len(data)

    def flush():
        nonlocal literal
        while literal:
            run, literal = literal[:32], literal[32:]
            out.append(len(run) - 1)
            out.extend(run)

    while i < n:
        key = data[i:i + 3]
        ref = last.get(key) if len(key) == 3 else None
        if len(key) == 3:
            last[key] = i
        if ref is not None and i - ref - 1 < 8192:
            length = 3
            while i + length < n and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            flush()
            offset, code = i - ref - 1, length - 2
            if code < 7:
                out.append((code << 5) | (offset >> 8))
            else:
                out += bytes([(7 << 5) | (offset >> 8), code - 7])
            out.append(offset & 0xFF)
            i += length
        else:
            literal.append(data[i])
            i += 1
    flush()
    return bytes(out)


def test_lzf_decompress_hand_made_streams():
    # "abc" as a literal run (control 2), then a back reference of length 5 from 3 bytes back, overlapping what it
    # writes: control (5 - 2) << 5 = 96, offset byte 3 - 1 = 2 -> "abc" + "abcab".
    assert pcd_ply.lzf_decompress(bytes([2]) + b"abc" + bytes([96, 2]), 8) == b"abcabcab"
    # A long reference: length 20 = 7 + 11 + 2 (control 7 << 5 = 224, extra byte 11), 1 byte back: 21 x "z".
    assert pcd_ply.lzf_decompress(bytes([0]) + b"z" + bytes([224, 11, 0]), 21) == b"z" * 21
    # A distance above 255: (offset >> 8) in the control byte. 300 literal bytes, then 4 bytes from 300 back.
    lit = bytes(range(256)) + bytes(range(44))
    stream = b"".join(bytes([len(c) - 1]) + c for c in (lit[k:k + 32] for k in range(0, 300, 32)))
    offset = 300 - 1
    stream += bytes([(2 << 5) | (offset >> 8), offset & 0xFF])
    assert pcd_ply.lzf_decompress(stream, 304) == lit + lit[:4]
    with pytest.raises(ValueError, match="before the start"):
        pcd_ply.lzf_decompress(bytes([0]) + b"a" + bytes([96, 5]), 6)
    with pytest.raises(ValueError, match="runs past the input"):
        pcd_ply.lzf_decompress(bytes([5]) + b"ab", 6)
    with pytest.raises(ValueError, match="decodes to 3 bytes, expected 4"):
        pcd_ply.lzf_decompress(bytes([2]) + b"abc", 4)


def test_lzf_round_trip_of_an_independent_compressor():
    data = b"".join([XYZ.tobytes(), bytes(200), b"ab" * 300, np.arange(500, dtype="<f4").tobytes(), XYZ.tobytes()])
    packed = lzf_compress(data)
    assert len(packed) < len(data)  # it did use back references
    assert pcd_ply.lzf_decompress(packed, len(data)) == data


# --- .npy, .npz, .bin ----------------------------------------------------------------------------------------------

def test_npy_npz_bin_as_written(tmp_path):
    xyzi = np.concatenate([XYZ, INTENSITY_F[:, None]], 1)
    np.save(tmp_path / "a.npy", XYZ)
    np.save(tmp_path / "b.npy", xyzi.astype(np.float64))
    structured = np.zeros(7, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("Intensity", "u1"), ("ring", "<u2")])
    for k, name in enumerate("xyz"):
        structured[name] = XYZ[:, k]
    structured["Intensity"] = INTENSITY_U8
    np.save(tmp_path / "c.npy", structured)
    np.savez(tmp_path / "d.npz", points=xyzi)
    np.savez(tmp_path / "e.npz", x=XYZ[:, 0], y=XYZ[:, 1], z=XYZ[:, 2], intensity=INTENSITY_U8)
    np.savez(tmp_path / "f.npz", points=XYZ, intensity=INTENSITY_F)
    _write(tmp_path / "g.bin", b"".join(struct.pack("<4f", *row) for row in xyzi))
    # nuScenes: x, y, z, intensity (0..255 as float), ring; 4 points of 20 bytes = 80 bytes, a multiple of 16 too
    _write(tmp_path / "n.pcd.bin", b"".join(struct.pack("<5f", *XYZ[i], float(INTENSITY_U8[i]), i % 32)
                                            for i in range(4)))
    cases = {"a.npy": None, "b.npy": INTENSITY_F, "c.npy": INTENSITY_U8, "d.npz": INTENSITY_F, "e.npz": INTENSITY_U8,
             "f.npz": INTENSITY_F, "g.bin": INTENSITY_F}
    for name, intensity in cases.items():
        cols = pf.read_point_file(str(tmp_path / name))
        np.testing.assert_array_equal(cols.xyz, XYZ.astype(np.float64), err_msg=name)
        if intensity is None:
            assert cols.intensity is None
        else:
            np.testing.assert_allclose(cols.intensity, intensity.astype(np.float64), rtol=1e-7, err_msg=name)
    assert pf.read_point_file(str(tmp_path / "c.npy")).ignored == ("ring",)
    cols = pf.read_point_file(str(tmp_path / "n.pcd.bin"))
    np.testing.assert_array_equal(cols.xyz, XYZ[:4].astype(np.float64))
    np.testing.assert_array_equal(cols.intensity, INTENSITY_U8[:4].astype(np.float64))
    assert cols.ignored == ("ring",)
    # the stored type says the scale: uint8 -> / 255; floats as stored
    frame = pf.read_frame(str(tmp_path / "c.npy"))
    np.testing.assert_allclose(frame["intensity"], INTENSITY_U8 / 255.0, rtol=1e-6)
    np.testing.assert_allclose(pf.read_frame(str(tmp_path / "g.bin"))["intensity"], INTENSITY_F, rtol=1e-7)


def test_frame_dict_has_the_project_shapes(tmp_path):
    from conftest import AV2_LOG
    from ff3d_tf.data.av2 import argoverse2
    np.save(tmp_path / "a.npy", XYZ)
    pose = np.eye(4)
    pose[:3, 3] = (5.0, -2.0, 0.5)
    frame = pf.read_frame(str(tmp_path / "a.npy"), pose=pose)
    av2 = argoverse2.read_sweep(AV2_LOG, argoverse2.sweep_timestamps(AV2_LOG)[0])
    assert tuple(frame) == schema.FRAME_KEYS == tuple(av2)
    for key in schema.FRAME_KEYS:
        assert np.asarray(frame[key]).dtype == np.asarray(av2[key]).dtype, key
        assert np.ndim(frame[key]) == np.ndim(av2[key]), key
    assert frame["points_xyz"].shape == (7, 3) and np.all(frame["intensity"] == 0)  # no intensity column: 0
    assert np.all(frame["class_id"] == schema.CLASS_NO_LABEL) and np.all(frame["flow_mps"] == 0)
    np.testing.assert_array_equal(frame["pose"], pose)
    np.testing.assert_array_equal(pf.read_frame(str(tmp_path / "a.npy"))["pose"], np.eye(4))


# --- PCD ------------------------------------------------------------------------------------------------------------

PCD_FIELDS = "x y z intensity rgb _ ring"  # "_" with COUNT 2: PCL's padding
PCD_HEADER = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE 4 4 4 1 4 1 2\n"
              "TYPE F F F U U U U\nCOUNT 1 1 1 1 1 2 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              "DATA {data}\n")
RGB = np.arange(7, dtype=np.uint32) * 65793
RING = np.arange(7, dtype=np.uint16) * 3


def _pcd_rows():
    return [(*XYZ[i], int(INTENSITY_U8[i]), int(RGB[i]), 9, 9, int(RING[i])) for i in range(7)]


def _pcd(data: str, n: int = 7) -> str:
    return PCD_HEADER.format(fields=PCD_FIELDS, n=n, data=data)


def _pcd_binary_bytes():
    return _pcd("binary").encode() + b"".join(struct.pack("<fffBIBBH", *row) for row in _pcd_rows())


def _pcd_compressed_bytes():
    columns = [XYZ[:, 0].astype("<f4"), XYZ[:, 1].astype("<f4"), XYZ[:, 2].astype("<f4"), INTENSITY_U8,
               RGB.astype("<u4"), np.full((7, 2), 9, np.uint8), RING.astype("<u2")]
    raw = b"".join(c.tobytes() for c in columns)  # field after field: all x, all y, ...
    packed = lzf_compress(raw)
    return _pcd("binary_compressed").encode() + struct.pack("<II", len(packed), len(raw)) + packed


def test_pcd_ascii_binary_and_compressed_as_written(tmp_path):
    text = _pcd("ascii") + "".join(" ".join(repr(float(v)) if k < 3 else str(v) for k, v in enumerate(row)) + "\n"
                                   for row in _pcd_rows())
    files = {"ascii": _write(tmp_path / "a.pcd", text), "binary": _write(tmp_path / "b.pcd", _pcd_binary_bytes()),
             "binary_compressed": _write(tmp_path / "c.pcd", _pcd_compressed_bytes())}
    for kind, path in files.items():
        cols = pf.read_point_file(path)
        np.testing.assert_array_equal(cols.xyz, XYZ.astype(np.float64), err_msg=kind)
        np.testing.assert_array_equal(cols.intensity, INTENSITY_U8.astype(np.float64), err_msg=kind)
        assert cols.intensity_dtype == np.uint8, kind
        assert cols.ignored == ("rgb", "_", "ring") and cols.notes == (), kind
        np.testing.assert_allclose(pf.read_frame(path)["intensity"], INTENSITY_U8 / 255.0, rtol=1e-6)
        np.testing.assert_allclose(pf.read_frame(path, intensity_scale=0.5)["intensity"], INTENSITY_U8 * 0.5)


def test_pcd_without_count_and_an_empty_cloud(tmp_path):
    head = "VERSION .7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary"
    data = (head.format(n=2) + "\n").encode() + struct.pack("<6d", 1.5, -2.0, 0.25, 1e-3, 7.0, -3.5)
    cols = pf.read_point_file(_write(tmp_path / "d.pcd", data))  # COUNT defaults to 1; float64 fields
    np.testing.assert_array_equal(cols.xyz, [[1.5, -2.0, 0.25], [1e-3, 7.0, -3.5]])
    assert cols.intensity is None
    cols = pf.read_point_file(_write(tmp_path / "e.pcd", head.format(n=0)))  # no newline after DATA, no points
    assert cols.xyz.shape == (0, 3)
    assert pf.read_frame(str(tmp_path / "e.pcd"))["points_xyz"].shape == (0, 3)


def test_pcd_viewpoint_is_reported(tmp_path):
    text = _pcd("ascii").replace("VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 1 2 3 1 0 0 0") + "".join(
        " ".join(str(v) for v in row) + "\n" for row in _pcd_rows())
    cols = pf.read_point_file(_write(tmp_path / "v.pcd", text))
    assert len(cols.notes) == 1 and "VIEWPOINT 1 2 3 1 0 0 0 ignored" in cols.notes[0]


def test_bad_pcd_files_name_file_and_field(tmp_path):
    rows = ["".join(" ".join(str(v) for v in row)) for row in _pcd_rows()]
    nan = rows.copy()
    nan[4] = nan[4].split()[0] + " nan " + " ".join(nan[4].split()[2:])
    path = _write(tmp_path / "nan.pcd", _pcd("ascii") + "\n".join(nan) + "\n")
    assert "at point 4" in _raises(path, "y", pf.read_point_file, path)
    short = rows.copy()
    short[2] = " ".join(short[2].split()[:-1])
    path = _write(tmp_path / "short.pcd", _pcd("ascii") + "\n".join(short) + "\n")
    assert "7 values; the header's 7 fields take 8" in _raises(path, "data line 3", pf.read_point_file, path)
    path = _write(tmp_path / "half.pcd", _pcd("ascii").replace(
        "SIZE 4 4 4", "SIZE 4 4 2") + "\n".join(rows) + "\n")
    assert "TYPE F SIZE 2" in _raises(path, "z", pf.read_point_file, path)
    path = _write(tmp_path / "type.pcd", _pcd("ascii").replace("TYPE F F F U U", "TYPE F F F U Q") + "\n".join(rows))
    assert "unknown PCD field type" in _raises(path, "rgb", pf.read_point_file, path)
    path = _write(tmp_path / "trunc.pcd", _pcd_binary_bytes()[:-5])
    assert "truncated" in _raises(path, "data", pf.read_point_file, path)
    path = _write(tmp_path / "ctrunc.pcd", _pcd_compressed_bytes()[:-3])
    assert "truncated" in _raises(path, "data", pf.read_point_file, path)
    path = _write(tmp_path / "extra.pcd", _pcd_binary_bytes() + b"\0" * 3)
    assert "3 bytes after the last" in _raises(path, "data", pf.read_point_file, path)
    path = _write(tmp_path / "count.pcd", _pcd("ascii", n=9) + "\n".join(rows))
    assert "9 points, the data has 7 lines" in _raises(path, "data", pf.read_point_file, path)
    path = _write(tmp_path / "noz.pcd", _pcd("ascii").replace(PCD_FIELDS, "x y w intensity rgb _ ring") +
                  "\n".join(rows))
    assert "missing" in _raises(path, "z", pf.read_point_file, path)
    path = _write(tmp_path / "lzo.pcd", _pcd("binary_lzo"))
    _raises(path, "DATA", pf.read_point_file, path)


# --- PLY ------------------------------------------------------------------------------------------------------------

def _ply_header(fmt: str, intensity_type: str = "uchar") -> str:
    return (f"ply\nformat {fmt} 1.0\ncomment written by hand\nelement vertex 7\nproperty float x\nproperty float y\n"
            f"property double z\nproperty {intensity_type} intensity\nproperty ushort ring\n"
            "element face 1\nproperty list uchar int vertex_indices\nend_header\n")


def _ply_binary(order: str) -> bytes:
    body = b"".join(struct.pack(order + "ffdBH", *XYZ[i, :2], float(XYZ[i, 2]), int(INTENSITY_U8[i]), int(RING[i]))
                    for i in range(7))
    face = struct.pack(order + "B3i", 3, 0, 1, 2)
    return _ply_header("binary_little_endian" if order == "<" else "binary_big_endian").encode() + body + face


def test_ply_ascii_and_binary_as_written(tmp_path):
    ascii_text = _ply_header("ascii") + "".join(f"{float(XYZ[i, 0])!r} {float(XYZ[i, 1])!r} {float(XYZ[i, 2])!r} "
                                                f"{INTENSITY_U8[i]} {RING[i]}\n" for i in range(7)) + "3 0 1 2\n"
    files = {"ascii": _write(tmp_path / "a.ply", ascii_text), "le": _write(tmp_path / "b.ply", _ply_binary("<")),
             "be": _write(tmp_path / "c.ply", _ply_binary(">"))}
    for kind, path in files.items():
        cols = pf.read_point_file(path)
        np.testing.assert_array_equal(cols.xyz, XYZ.astype(np.float64), err_msg=kind)
        np.testing.assert_array_equal(cols.intensity, INTENSITY_U8.astype(np.float64), err_msg=kind)
        assert cols.intensity_dtype == np.uint8 and cols.ignored == ("ring",), kind
    # an element before the vertices (fixed-size properties) is skipped in binary files
    head = ("ply\nformat binary_little_endian 1.0\nelement camera 2\nproperty float f\nelement vertex 2\n"
            "property float x\nproperty float y\nproperty float z\nproperty float reflectance\nend_header\n")
    data = head.encode() + struct.pack("<2f", 9.0, 9.0) + struct.pack("<8f", 1, 2, 3, 0.25, 4, 5, 6, 0.75)
    cols = pf.read_point_file(_write(tmp_path / "d.ply", data))
    np.testing.assert_array_equal(cols.xyz, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(cols.intensity, [0.25, 0.75])
    assert cols.intensity_dtype == np.float32  # reflectance is an intensity name


def test_bad_ply_files_name_file_and_field(tmp_path):
    path = _write(tmp_path / "trunc.ply", _ply_binary("<")[:len(_ply_header("binary_little_endian")) + 50])
    assert "truncated" in _raises(path, "data", pf.read_point_file, path)
    path = _write(tmp_path / "type.ply", _ply_header("ascii").replace("property ushort ring", "property half ring"))
    assert "'half' unknown" in _raises(path, "ring", pf.read_point_file, path)
    path = _write(tmp_path / "list.ply", _ply_header("ascii").replace("property ushort ring",
                                                                     "property list uchar int ring"))
    _raises(path, "ring", pf.read_point_file, path)
    path = _write(tmp_path / "fmt.ply", _ply_header("binary_middle_endian"))
    _raises(path, "format", pf.read_point_file, path)
    lines = "".join(f"{XYZ[i, 0]} {XYZ[i, 1]} {XYZ[i, 2]} 1\n" for i in range(7))  # 4 values for 5 properties
    path = _write(tmp_path / "cols.ply", _ply_header("ascii") + lines)
    assert "4 values" in _raises(path, "vertex line 1", pf.read_point_file, path)
    inf = "".join(f"{XYZ[i, 0]} {XYZ[i, 1]} {'inf' if i == 6 else XYZ[i, 2]} 1 2\n" for i in range(7))
    path = _write(tmp_path / "inf.ply", _ply_header("ascii") + inf)
    assert "at point 6" in _raises(path, "z", pf.read_point_file, path)


def test_bad_npy_npz_bin_files(tmp_path):
    path = str(tmp_path / "five.npy")
    np.save(path, np.zeros((4, 5), np.float32))
    assert "shape (4, 5)" in _raises(path, "array", pf.read_point_file, path)
    path = str(tmp_path / "nan.npy")
    bad = XYZ.copy()
    bad[3, 0] = np.nan
    np.save(path, bad)
    assert "at point 3" in _raises(path, "x", pf.read_point_file, path)
    path = str(tmp_path / "obj.npy")
    np.save(path, np.array([object()] * 3), allow_pickle=True)
    assert "pickled" in _raises(path, "file", pf.read_point_file, path)
    path = str(tmp_path / "keys.npz")
    np.savez(path, points=XYZ, colour=XYZ)
    assert "unknown array" in _raises(path, "colour", pf.read_point_file, path)
    path = str(tmp_path / "len.npz")
    np.savez(path, x=XYZ[:, 0], y=XYZ[:, 1], z=XYZ[:3, 2])
    assert "3 values, but x has 7" in _raises(path, "z", pf.read_point_file, path)
    path = _write(tmp_path / "odd.bin", np.zeros(10, "<f4").tobytes())  # 40 bytes: 2.5 points
    assert "not a multiple of 16" in _raises(path, "file", pf.read_point_file, path)
    path = _write(tmp_path / "odd.pcd.bin", np.zeros(8, "<f4").tobytes())  # 32 bytes: 1.6 nuScenes points
    assert "not a multiple of 20" in _raises(path, "file", pf.read_point_file, path)
    path = _write(tmp_path / "a.xyz", "1 2 3\n")
    assert "unknown point file suffix" in _raises(path, "file", pf.read_point_file, path)


def _npy_header_only(path, descr, shape, rows_written=0):
    """An .npy whose header says `shape` of `descr`, followed by `rows_written` rows of zeros (float32 x 4)."""
    from numpy.lib import format as npy_format
    with open(path, "wb") as f:
        npy_format.write_array_header_1_0(f, {"descr": descr, "fortran_order": False, "shape": shape})
        f.write(np.zeros((rows_written, 4), "<f4").tobytes())
    return str(path)


def test_npy_header_declaring_a_huge_shape_is_refused_before_any_allocation(tmp_path):
    """A crafted header claiming 4e9 x 4 float32 is refused from the file's size, naming the file and the field: no
    MemoryError, and nothing near the claimed size is allocated (NumPy's allocations are traced by tracemalloc)."""
    import tracemalloc
    path = _npy_header_only(tmp_path / "huge.npy", "<f4", (4_000_000_000, 4), rows_written=10)
    tracemalloc.start()
    try:
        message = _raises(path, "file", pf.read_point_file, path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "(4000000000, 4)" in message and "truncated" in message, message
    assert peak < (1 << 20), peak  # the error comes from the header and the file's size, not from an allocation
    # the same header as a pose file and as an .npz member
    assert "truncated" in _raises(path, "pose", pf.read_pose, path)
    # types without bytes a value would make any shape fit any file size: refused as such, never a raw error
    for name, descr in (("fields.npy", []), ("void.npy", "|V0")):
        path = _npy_header_only(tmp_path / name, descr, (10 ** 12,))
        assert "no bytes a value" in _raises(path, "file", pf.read_point_file, path)
    path = _npy_header_only(tmp_path / "negative.npy", "<f4", (-1, 4))
    assert "negative dimension" in _raises(path, "file", pf.read_point_file, path)


# --- poses ----------------------------------------------------------------------------------------------------------

def _pose(yaw, t):
    """4x4 vehicle -> world pose of a yaw rotation and a translation."""
    return geometry.box_matrices_np(t, yaw)[0]


def test_poses_text_and_npy(tmp_path):
    pose = _pose(0.3, (10.0, -4.0, 1.5))
    text = "# vehicle -> world\n" + "\n".join(" ".join(repr(float(v)) for v in row) for row in pose) + "\n"
    np.testing.assert_array_equal(pf.read_pose(_write(tmp_path / "p.txt", text)), pose)
    commas = ", ".join(repr(float(v)) for v in pose[:3].reshape(-1)) + "  # 3x4, KITTI style\n"
    np.testing.assert_array_equal(pf.read_pose(_write(tmp_path / "q.txt", commas)), pose)
    np.save(tmp_path / "r.npy", pose)
    np.testing.assert_array_equal(pf.read_pose(str(tmp_path / "r.npy")), pose)
    scaled = pose.copy()
    scaled[:3, :3] *= 2
    np.save(tmp_path / "s.npy", scaled)
    message = _raises(tmp_path / "s.npy", "pose", pf.read_pose, str(tmp_path / "s.npy"))
    assert geometry.pose_rule_messages("the pose")["orthonormal"] in message
    path = _write(tmp_path / "n.txt", "1 0 0 0 0 1 0 0 0 0 1 nan 0 0 0 1\n")
    assert geometry.pose_rule_messages("the pose")["finite"] in _raises(path, "pose", pf.read_pose, path)
    path = _write(tmp_path / "f.txt", "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0\n")
    assert "15 numbers" in _raises(path, "pose", pf.read_pose, path)
    path = _write(tmp_path / "w.txt", "1 0 0 x\n")
    assert "'x' is not a number" in _raises(path, "line 1", pf.read_pose, path)


def test_sweeps_directory_and_its_poses(tmp_path):
    d = tmp_path / "log"
    d.mkdir()
    for name in ("000002.npy", "000000.npy", "000001.npy"):
        np.save(d / name, XYZ)
    _write(d / "README.txt", "not a sweep")
    sweeps = pf.list_sweeps(str(d))
    assert [os.path.basename(s) for s in sweeps] == ["000000.npy", "000001.npy", "000002.npy"]
    assert pf.sweep_poses(str(d), sweeps) is None
    poses = [_pose(0.1 * k, (k, 0.0, 0.0)) for k in range(3)]
    _write(d / "poses.txt", "".join(" ".join(repr(float(v)) for v in p[:3].reshape(-1)) + "\n" for p in poses))
    for got, want in zip(pf.sweep_poses(str(d), sweeps), poses):
        np.testing.assert_array_equal(got, want)
    _write(d / "poses.txt", "".join(" ".join(repr(float(v)) for v in p.reshape(-1)) + "\n" for p in poses[:2]))
    assert "2 poses for 3 sweeps" in _raises(d / "poses.txt", "file", pf.sweep_poses, str(d), sweeps)
    os.remove(d / "poses.txt")
    for k in (0, 1):
        np.save(d / f"00000{k}.pose.npy", poses[k])
    assert pf.list_sweeps(str(d)) == sweeps  # *.pose.npy are poses, not sweeps
    _raises(d / "000002.pose.txt", "pose", pf.sweep_poses, str(d), sweeps)  # the missing one is named
    _write(d / "000002.pose.txt", "\n".join(" ".join(repr(float(v)) for v in row) for row in poses[2]))
    for got, want in zip(pf.sweep_poses(str(d), sweeps), poses):
        np.testing.assert_array_equal(got, want)
    _write(d / "poses.txt", "")
    _raises(d / "000000.pose.npy", "pose", pf.sweep_poses, str(d), sweeps)  # both kinds at once
    np.savez(d / "000001.npz", points=XYZ)
    _raises(d / "000001.npz", "file", pf.list_sweeps, str(d))  # two sweeps of one name


# --- intensity scale and outputs ------------------------------------------------------------------------------------

def test_intensity_scale_rule():
    assert pf.parse_intensity_scale("auto") is None
    assert pf.parse_intensity_scale("1/255") == 1 / 255 and pf.parse_intensity_scale("0.5") == 0.5
    for bad in ("x", "-1", "1/0", "1/2/3", "nan"):
        with pytest.raises(ValueError, match="intensity scale"):
            pf.parse_intensity_scale(bad)
    assert pf.intensity_scale_of(np.uint8, None) == 1 / 255  # the Argoverse 2 rule
    assert pf.intensity_scale_of(np.uint16, None) == 1 / 65535
    assert pf.intensity_scale_of(np.int8, None) == 1 / 127
    assert pf.intensity_scale_of(np.float32, None) == 1.0 and pf.intensity_scale_of(np.float64, None) == 1.0
    assert pf.intensity_scale_of(np.uint8, 0.25) == 0.25


def test_write_predictions_npz_and_feather_agree(tmp_path):
    import pyarrow.feather as feather
    flow = RNG.normal(size=(7, 3)).astype(np.float32)
    valid = np.array([1, 1, 0, 1, 0, 1, 1], bool)
    npz, fea = pf.write_predictions(str(tmp_path / "out"), XYZ, flow, valid)
    with np.load(npz) as z:
        np.testing.assert_array_equal(z["flow_mps"], flow)
        np.testing.assert_array_equal(z["point_valid"], valid)
        np.testing.assert_array_equal(z["points_xyz_t0"], XYZ)
    t = feather.read_table(fea)
    assert tuple(t.column_names) == pf.FLOW_FEATHER_COLUMNS
    np.testing.assert_array_equal(np.stack([t["flow_x_mps"], t["flow_y_mps"], t["flow_z_mps"]], -1), flow)
    np.testing.assert_array_equal(np.stack([t["x_m"], t["y_m"], t["z_m"]], -1), XYZ)
    np.testing.assert_array_equal(t["point_valid"].to_numpy(zero_copy_only=False), valid)
