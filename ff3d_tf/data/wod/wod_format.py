"""WOD v1 format facts shared by the reader and the writers: proto descriptors, matrix encoding, polar geometry.

Sources: `waymo_open_dataset/dataset.proto` (field layout), the official `range_image_utils` conversion (geometry
conventions). Nothing here is copied; the conventions are re-derived below.
"""
from __future__ import annotations

import dataclasses
import functools
import zlib
from typing import Callable

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
    written directly (byte-identical to the protobuf serializer and much faster than filling a repeated field), and
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


@dataclasses.dataclass(frozen=True)
class ArrayOps:
    """The few array operations the polar geometry needs, so the same formulas serve NumPy (writers, tests) and
    TensorFlow graphs (the reader: `ff3d_tf.data.wod.wod_decode.TF_OPS`) without this module importing TensorFlow."""

    to_f64: Callable  # scalar or array -> float64
    arange_f64: Callable  # n -> [0, 1, ..., n-1] float64
    atan2: Callable
    cos: Callable
    sin: Callable
    stack_last: Callable  # list of [M] arrays -> [M, k]


NUMPY_OPS = ArrayOps(to_f64=lambda x: np.asarray(x, np.float64), arange_f64=lambda n: np.arange(n, dtype=np.float64),
                     atan2=np.arctan2, cos=np.cos, sin=np.sin, stack_last=lambda xs: np.stack(xs, -1))


def column_azimuths(width, extrinsic, ops: ArrayOps = NUMPY_OPS):
    """Azimuth (rad, sensor frame) of each range image column: column 0 looks backwards, azimuth falls to the right.

    Column c of W points at ((W - c - 0.5) / W * 2 - 1) * pi, less the extrinsic's yaw atan2(R10, R00).
    """
    w = ops.to_f64(width)
    ratios = (w - ops.arange_f64(width) - 0.5) / w
    return (ratios * 2.0 - 1.0) * np.pi - ops.atan2(extrinsic[1, 0], extrinsic[0, 0])


def uniform_inclinations_ascending(height, inclination_min, inclination_max, ops: ArrayOps = NUMPY_OPS):
    """Beam inclinations (rad, lowest beam first, the stored order) of a lidar calibrated by min/max only: the centres
    of `height` equal bins."""
    return inclination_min + (ops.arange_f64(height) + 0.5) / ops.to_f64(height) * (inclination_max - inclination_min)


def row_inclinations(height: int, beam_inclinations=None, inclination_min=None, inclination_max=None) -> np.ndarray:
    """Inclination (rad) of each range image row, row 0 = highest beam (stored values are ascending)."""
    if beam_inclinations is not None and len(beam_inclinations):
        incl = np.asarray(beam_inclinations, dtype=np.float64)
    else:
        incl = uniform_inclinations_ascending(height, inclination_min, inclination_max)
    return incl[::-1].copy()


def rotate_rpy(rpy, xyz, ops: ArrayOps = NUMPY_OPS):
    """`rotation_from_rpy(roll, pitch, yaw) @ xyz` per row, without forming [M, 3, 3] matrices: rpy, xyz [M, 3].

    Roll about x, then pitch about y, then yaw about z (the range image pose convention). Keeps the input dtype.
    """
    cr, sr = ops.cos(rpy[:, 0]), ops.sin(rpy[:, 0])
    cp, sp = ops.cos(rpy[:, 1]), ops.sin(rpy[:, 1])
    cy, sy = ops.cos(rpy[:, 2]), ops.sin(rpy[:, 2])
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    y1, z1 = cr * y - sr * z, sr * y + cr * z
    x2, z2 = cp * x + sp * z1, cp * z1 - sp * x
    return ops.stack_last([cy * x2 - sy * y1, sy * x2 + cy * y1, z2])


# Protobuf wire format (https://protobuf.dev/programming-guides/encoding/): wire types of each field type.
_WIRE_OF_TYPE = {1: 1, 6: 1, 16: 1,  # double, fixed64, sfixed64
                 2: 5, 7: 5, 15: 5,  # float, fixed32, sfixed32
                 9: 2, 11: 2, 12: 2}  # string, message, bytes; every other type (ints, bool, enum) is a varint (0)
# descriptor.proto FieldDescriptorProto: Type TYPE_MESSAGE, Label LABEL_REPEATED.
_TYPE_MESSAGE, _LABEL_REPEATED = 11, 3


def is_repeated(field) -> bool:
    """Whether a protobuf FieldDescriptor is repeated: its `is_repeated` where it has one (protobuf 7 removed
    `label`), else its `label`."""
    repeated = getattr(field, "is_repeated", None)
    return bool(repeated) if repeated is not None else field.label == _LABEL_REPEATED


def _varint_at(data, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(data):
            raise ValueError(f"varint runs past the end at byte {pos}")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
        shift += 7
        if shift >= 64:
            raise ValueError(f"varint longer than 10 bytes at byte {pos}")


class WireFormatError(ValueError):
    """Broken protobuf wire format; `number` is the field being read (0 if its key itself is broken)."""

    def __init__(self, message: str, number: int = 0):
        super().__init__(message)
        self.number = number


def wire_fields(data) -> list[tuple[int, int, object]]:
    """(field number, wire type, value) of each field of one serialized message, in wire order: ints for varints,
    memoryviews for the rest. WireFormatError names the byte offset where the wire format breaks."""
    data = memoryview(data).cast("B")
    fields, pos = [], 0
    while pos < len(data):
        start = pos
        try:
            key, pos = _varint_at(data, pos)
        except ValueError as err:
            raise WireFormatError(f"field key: {err}") from None
        number, wire = key >> 3, key & 7
        try:
            value, pos = _field_value(data, pos, number, wire, start)
        except ValueError as err:
            raise WireFormatError(str(err), number) from None
        fields.append((number, wire, value))
    return fields


def _field_value(data, pos: int, number: int, wire: int, start: int):
    """(value, next position) of one field whose key was read at `start`."""
    if number == 0:
        raise ValueError(f"field number 0 at byte {start}")
    if wire == 0:
        return _varint_at(data, pos)
    if wire not in (1, 5, 2):
        raise ValueError(f"field {number} at byte {start} has wire type {wire} (groups are not used by WOD)")
    if wire == 2:
        size, pos = _varint_at(data, pos)
    else:
        size = 8 if wire == 1 else 4
    if pos + size > len(data):
        raise ValueError(f"field {number} at byte {start} declares {size} bytes; {len(data) - pos} remain")
    return data[pos:pos + size], pos + size


def malformed_field(data, descriptor, recurse_into: tuple[str, ...], path: str = "") -> tuple[str, str] | None:
    """(dotted field path, reason) of the first field whose wire format is broken, or None.

    Checks the wire format, and that each known field has its declared wire type (packed repeated fields may be
    length-delimited); descends into the message types named in `recurse_into`. Repeated messages are named by their
    `name` enum where they have one (`lasers[FRONT]`), else by position.
    """
    try:
        fields = wire_fields(data)
    except WireFormatError as err:
        field = descriptor.fields_by_number.get(err.number)
        where = ".".join(p for p in (path, field.name if field is not None else "") if p) or descriptor.name
        return where, f"malformed protobuf {descriptor.name}: {err}"
    counts: dict[str, int] = {}
    for number, wire, value in fields:
        field = descriptor.fields_by_number.get(number)
        if field is None:
            continue  # unknown fields are legal and skipped
        expected = _WIRE_OF_TYPE.get(field.type, 0)
        repeated = is_repeated(field)
        where = f"{path}.{field.name}" if path else field.name
        if wire != expected and not (repeated and wire == 2 and expected != 2):
            return where, f"wire type {wire} where {descriptor.name}.{field.name} needs {expected}"
        if field.type == _TYPE_MESSAGE and field.message_type.name in recurse_into:
            if repeated:
                k = counts[field.name] = counts.get(field.name, -1) + 1
                where = f"{where}[{_entry_name(value, field.message_type) or k}]"
            bad = malformed_field(value, field.message_type, recurse_into, where)
            if bad is not None:
                return bad
    return None


def _entry_name(data, descriptor) -> str | None:
    """The symbolic `name` enum of a repeated entry (e.g. LaserName FRONT), if it has one and it parses."""
    name = descriptor.fields_by_name.get("name")
    if name is None or name.enum_type is None:
        return None
    try:
        values = [v for n, w, v in wire_fields(data) if n == name.number and w == 0]
    except ValueError:
        return None
    entry = name.enum_type.values_by_number.get(values[-1]) if values else None
    return entry.name if entry is not None else None
