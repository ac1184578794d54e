"""WOD v1 format facts shared by the reader and the writers: proto descriptors, matrix encoding, polar geometry.

Sources: `waymo_open_dataset/dataset.proto` (field layout), the official `range_image_utils` conversion (geometry
conventions). Nothing here is copied; the conventions are re-derived below.
"""
from __future__ import annotations

import functools
import zlib

import numpy as np


@functools.lru_cache(maxsize=1)
def descriptor_source() -> bytes:
    """`bytes://` descriptor source for `tf.io.decode_proto`: the Frame proto file and its imports, dependencies first."""
    from google.protobuf import descriptor_pb2
    from waymo_open_dataset import dataset_pb2

    ordered, seen = [], set()

    def visit(fd):
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            visit(dep)
        proto = descriptor_pb2.FileDescriptorProto()
        fd.CopyToProto(proto)
        ordered.append(proto)

    visit(dataset_pb2.DESCRIPTOR)
    fds = descriptor_pb2.FileDescriptorSet(file=ordered)
    return b"bytes://" + fds.SerializeToString()


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def encode_matrix(array: np.ndarray, compress_level: int = 1) -> bytes:
    """zlib-compressed serialized `MatrixFloat` (float arrays) or `MatrixInt32` (integer arrays).

    Both messages are `data = 1 (packed)`, `shape = 2 (MatrixShape{dims = 1 (int32, unpacked)})`, so the wire format is
    written directly (byte-identical to the protobuf serializer and ~50x faster than filling a repeated field), and
    float payloads go to zlib straight from the array's memory.
    """
    array = np.asarray(array)
    if np.issubdtype(array.dtype, np.floating):
        payload = memoryview(np.ascontiguousarray(array, dtype="<f4").reshape(-1)).cast("B")
    else:
        values = np.ascontiguousarray(array, dtype=np.int64).ravel()
        payload = b"".join(_varint(int(v) & 0xFFFFFFFFFFFFFFFF) for v in values) if np.any(values) else \
            b"\x00" * values.size  # all zeros: one byte each
    shape_msg = b"".join(b"\x08" + _varint(int(d)) for d in array.shape)  # proto2 `repeated int32`: unpacked
    compressor = zlib.compressobj(compress_level)
    head = b"\x0a" + _varint(len(payload)) if len(payload) else b""
    return b"".join([compressor.compress(head), compressor.compress(payload),
                     compressor.compress(b"\x12" + _varint(len(shape_msg)) + shape_msg), compressor.flush()])


def encode_transform(matrix: np.ndarray) -> list[float]:
    """Row-major 16 doubles of a 4x4 `Transform`."""
    return [float(v) for v in np.asarray(matrix, dtype=np.float64).reshape(16)]


def rotation_from_rpy(roll, pitch, yaw) -> np.ndarray:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll) (the range image pose convention), [..., 3, 3]."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def column_azimuths(width: int, extrinsic: np.ndarray) -> np.ndarray:
    """Azimuth (rad, sensor frame) of each range image column: column 0 looks backwards, azimuth falls to the right."""
    az_correction = np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    ratios = (np.arange(width, 0, -1, dtype=np.float64) - 0.5) / width
    return (ratios * 2.0 - 1.0) * np.pi - az_correction


def row_inclinations(height: int, beam_inclinations=None, inclination_min=None, inclination_max=None) -> np.ndarray:
    """Inclination (rad) of each range image row, row 0 = highest beam (stored values are ascending)."""
    if beam_inclinations is not None and len(beam_inclinations):
        incl = np.asarray(beam_inclinations, dtype=np.float64)
    else:
        incl = inclination_min + (np.arange(height) + 0.5) / height * (inclination_max - inclination_min)
    return incl[::-1].copy()


def uniform_inclinations_ascending(height: int, inclination_min: float, inclination_max: float) -> np.ndarray:
    return inclination_min + (np.arange(height) + 0.5) / height * (inclination_max - inclination_min)
