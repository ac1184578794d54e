"""Damage to one serialized WOD `Frame` record, one way per kind (`KINDS`): bytes (bit flips, a cut), fields
(deleted, written twice), compressed matrices (corrupt zlib, declared shapes huge, negative or disagreeing with the
data or the calibration) and values (NaN/Inf and extremes in floats read and ignored, non-rigid poses)."""
from __future__ import annotations

import zlib

import numpy as np

from ff3d_tf.data.wod import wod_format
from ff3d_tf.fuzz.report import NONFINITE, pick

KINDS = ("bit_flip", "truncate", "delete_field", "duplicate_field", "corrupt_zlib", "shape_huge", "shape_negative",
         "shape_vs_calibration", "nan_float", "extreme_value", "nonfinite_extrinsic", "nonfinite_pose", "nonrigid_pose")


def _frame(record: bytes):
    from waymo_open_dataset import dataset_pb2
    return dataset_pb2.Frame.FromString(record)


def _laser(frame, rng):
    return frame.lasers[int(rng.integers(len(frame.lasers)))]


def _compressed_fields(frame) -> list[tuple[object, str, str]]:
    """(RangeImage message, field name, label) of every compressed matrix the decoder may read."""
    out = []
    for laser in frame.lasers:
        for i, ret in enumerate((laser.ri_return1, laser.ri_return2)):
            names = ["range_image_compressed", "range_image_flow_compressed"]
            names += ["range_image_pose_compressed"] if laser.name == 1 and i == 0 else []
            out += [(ret, name, f"lasers[{laser.name}].ri_return{i + 1}.{name}") for name in names]
    return [(m, f, label) for m, f, label in out if getattr(m, f)]


def matrix_bytes(data: np.ndarray, dims) -> bytes:
    """A serialized MatrixFloat with `data` and arbitrary (possibly lying, negative) int32 `dims`."""
    payload = np.ascontiguousarray(data, "<f4").tobytes()
    shape = b"".join(b"\x08" + wod_format._varint(int(d) & 0xFFFFFFFFFFFFFFFF) for d in dims)
    head = b"\x0a" + wod_format._varint(len(payload)) if payload else b""
    return head + payload + b"\x12" + wod_format._varint(len(shape)) + shape


def _decoded_matrix(compressed: bytes) -> np.ndarray:
    from waymo_open_dataset import dataset_pb2
    m = dataset_pb2.MatrixFloat.FromString(zlib.decompress(compressed))
    return np.asarray(m.data, np.float32).reshape(tuple(m.shape.dims))


def _with_wire_duplicate(data: bytes, rng) -> bytes:
    """`data` (a serialized message) with one of its top-level fields written twice."""
    fields = wod_format.wire_fields(data)
    if not fields:
        return data
    i = int(rng.integers(len(fields)))
    encoded = []
    for number, wire, value in fields:
        key = wod_format._varint(number << 3 | wire)
        if wire == 0:
            encoded.append(key + wod_format._varint(value))
        elif wire == 2:
            encoded.append(key + wod_format._varint(len(value)) + bytes(value))
        else:
            encoded.append(key + bytes(value))
    return b"".join(encoded[: i + 1] + [encoded[i]] + encoded[i + 1:])


def _delete_field(frame, rng) -> str:
    laser = _laser(frame, rng)
    cal = frame.context.laser_calibrations[int(rng.integers(len(frame.context.laser_calibrations)))]
    choices = {
        "context": lambda: frame.ClearField("context"),
        "pose": lambda: frame.ClearField("pose"),
        "timestamp_micros": lambda: frame.ClearField("timestamp_micros"),
        "lasers[i]": lambda: frame.lasers.remove(laser),
        "laser_calibrations[i]": lambda: frame.context.laser_calibrations.remove(cal),
        "extrinsic": lambda: cal.ClearField("extrinsic"),
        "beam_inclinations": lambda: cal.ClearField("beam_inclinations"),
        "beam_inclination_min/max": lambda: (cal.ClearField("beam_inclination_min"),
                                             cal.ClearField("beam_inclination_max")),
        "ri_return1": lambda: laser.ClearField("ri_return1"),
        "range_image_compressed": lambda: laser.ri_return1.ClearField("range_image_compressed"),
        "range_image_flow_compressed": lambda: laser.ri_return1.ClearField("range_image_flow_compressed"),
        "range_image_pose_compressed": lambda: laser.ri_return1.ClearField("range_image_pose_compressed"),
        "laser name": lambda: laser.ClearField("name"),
    }
    name = pick(rng, sorted(choices))
    choices[name]()
    return f"deleted {name} (laser {laser.name}, calibration {cal.name})"


def _duplicate_field(frame, rng) -> tuple[str, bytes | None]:
    laser = _laser(frame, rng)
    cal = frame.context.laser_calibrations[int(rng.integers(len(frame.context.laser_calibrations)))]
    choice = int(rng.integers(6))
    if choice == 0:
        frame.lasers.add().CopyFrom(laser)
        return f"laser {laser.name} twice", None
    if choice == 1:
        frame.context.laser_calibrations.add().CopyFrom(cal)
        return f"calibration {cal.name} twice", None
    if choice == 2:
        frame.pose.transform.extend(list(frame.pose.transform))
        return "pose with 32 values", None
    if choice == 3:
        cal.beam_inclinations.extend(list(cal.beam_inclinations) or [0.1])
        return f"calibration {cal.name} beam_inclinations doubled", None
    if choice == 4:
        laser.ri_return1.MergeFromString(_with_wire_duplicate(laser.ri_return1.SerializeToString(), rng))
        return f"laser {laser.name} ri_return1 field written twice (wire)", None
    return "a top-level Frame field written twice (wire)", _with_wire_duplicate(frame.SerializeToString(), rng)


def _corrupt_zlib(frame, rng) -> str:
    msg, name, label = pick(rng, _compressed_fields(frame))
    data = bytearray(getattr(msg, name))
    how = int(rng.integers(5))
    if how == 0:
        data = bytearray(rng.integers(0, 256, size=len(data), dtype=np.uint8).tobytes())
        what = "random bytes"
    elif how == 1:
        for _ in range(int(rng.integers(1, 8))):
            i = int(rng.integers(2, len(data))) if len(data) > 2 else 0
            data[i] ^= 1 << int(rng.integers(8))
        what = "bit flips inside the stream"
    elif how == 2:
        data = data[: int(rng.integers(0, max(1, len(data) - 1)))]
        what = "stream cut short"
    elif how == 3:
        data = bytearray(zlib.compress(rng.integers(0, 256, size=int(rng.integers(1, 200)), dtype=np.uint8)
                                       .tobytes()))
        what = "valid zlib of random bytes (not a MatrixFloat)"
    else:
        data = bytearray(zlib.compress(b""))
        what = "valid zlib of nothing"
    setattr(msg, name, bytes(data))
    return f"{label}: {what}"


def _reshape_matrix(frame, rng, dims_fn, what: str) -> str:
    msg, name, label = pick(rng, _compressed_fields(frame))
    array = _decoded_matrix(getattr(msg, name))
    dims = dims_fn(array.shape, rng)
    setattr(msg, name, zlib.compress(matrix_bytes(array.reshape(-1), dims), 1))
    return f"{label} {array.shape} declared as {tuple(dims)} ({what})"


def _huge_dims(shape, rng):
    h, w, c = shape
    return pick(rng, [(2 ** 31 - 1, 2 ** 31 - 1, c), (65536, 65536, 4), (1 << 20, 1 << 20, c), (h * 1000, w, c),
                       (2 ** 31 - 1, 1, c), (h, w, 2 ** 31 - 1), (0, 2 ** 31 - 1, c)])


def _negative_dims(shape, rng):
    h, w, c = shape
    return pick(rng, [(-h, w, c), (-h, -w, c), (h, w, -c), (-1, w, c), (-(2 ** 31), w, c), (h, -w, -c)])


def _disagreeing_dims(shape, rng):
    h, w, c = shape
    return pick(rng, [(w, h, c), (h * w, 1, c), (h, w * c, 1), (h, w), (h, w, c, 1), (h, w, c + 1), (h - 1, w, c),
                       (h * 2, w // 2 if w % 2 == 0 else w, c)])


def _shape_vs_calibration(frame, rng) -> str:
    if rng.random() < 0.5:
        return _reshape_matrix(frame, rng, _disagreeing_dims, "disagrees with the data or calibration")
    cal = pick(rng, [c for c in frame.context.laser_calibrations])
    if len(cal.beam_inclinations) and rng.random() < 0.5:
        del cal.beam_inclinations[-1]
        return f"calibration {cal.name}: one beam inclination fewer than image rows"
    cal.beam_inclinations.extend([0.01] * int(rng.integers(1, 4)) if len(cal.beam_inclinations) else [0.0, 0.1, 0.2])
    return f"calibration {cal.name}: beam_inclinations count differs from image rows"


def _float_targets(frame) -> list[tuple[str, object]]:
    """(name, setter(value)) for float fields: those the decoder reads and some it ignores."""
    targets = []

    def matrix_setter(msg, name):
        def set_value(value, rng):
            array = _decoded_matrix(getattr(msg, name))
            if array.size:
                with np.errstate(over="ignore"):  # 1e300 becomes inf in float32, as a writer would store it
                    array.reshape(-1)[int(rng.integers(array.size))] = value
            setattr(msg, name, wod_format.encode_matrix(array))
        return set_value

    for msg, name, label in _compressed_fields(frame):
        targets.append((label, matrix_setter(msg, name)))
    for cal in frame.context.laser_calibrations:
        if len(cal.beam_inclinations):
            targets.append((f"cal {cal.name} beam_inclinations",
                            lambda v, rng, c=cal: c.beam_inclinations.__setitem__(
                                int(rng.integers(len(c.beam_inclinations))), v)))
        targets.append((f"cal {cal.name} beam_inclination_min",
                        lambda v, rng, c=cal: setattr(c, "beam_inclination_min", v)))
        targets.append((f"cal {cal.name} beam_inclination_max",
                        lambda v, rng, c=cal: setattr(c, "beam_inclination_max", v)))
        targets.append((f"cal {cal.name} extrinsic",
                        lambda v, rng, c=cal: c.extrinsic.transform.__setitem__(int(rng.integers(16)), v)))
    targets.append(("pose", lambda v, rng: frame.pose.transform.__setitem__(int(rng.integers(16)), v)))
    for label in list(frame.laser_labels)[:3]:  # not read by the decoder: must not matter
        targets.append(("laser_labels box center_x", lambda v, rng, b=label.box: setattr(b, "center_x", v)))
    return targets


def _set_float(frame, rng, values, only=None) -> str:
    targets = [t for t in _float_targets(frame) if only is None or only in t[0]]
    name, setter = pick(rng, targets)
    value = float(pick(rng, values))
    setter(value, rng)
    return f"{name} <- {value}"


def _nonrigid_pose(frame, rng) -> str:
    choice = int(rng.integers(4))
    pose = np.asarray(frame.pose.transform, np.float64).reshape(4, 4)
    if choice == 0:
        pose[:] = 0.0
        what = "all zeros (singular)"
    elif choice == 1:
        pose[:3, :3] *= 2.0
        what = "rotation scaled by 2"
    elif choice == 2:
        pose[3] = [0.0, 0.0, 1.0, 1.0]
        what = "bottom row not 0 0 0 1"
    else:
        cal = pick(rng, list(frame.context.laser_calibrations))
        ext = np.asarray(cal.extrinsic.transform, np.float64).reshape(4, 4)
        ext[:3, :3] *= float(rng.choice([0.0, 2.0]))
        cal.extrinsic.transform[:] = wod_format.encode_transform(ext)
        return f"calibration {cal.name} extrinsic rotation scaled (not rigid)"
    frame.pose.transform[:] = wod_format.encode_transform(pose)
    return f"pose {what}"


def mutate(record: bytes, kind: str, rng: np.random.Generator) -> tuple[bytes, str]:
    """(damaged record, what was done) of one valid serialized Frame."""
    if kind == "bit_flip":
        data = bytearray(record)
        flips = int(rng.integers(1, 17))
        for _ in range(flips):
            data[int(rng.integers(len(data)))] ^= 1 << int(rng.integers(8))
        return bytes(data), f"{flips} bit flips"
    if kind == "truncate":
        cut = int(rng.integers(0, len(record)))
        return record[:cut], f"record cut at byte {cut} of {len(record)}"
    frame = _frame(record)
    raw = None
    if kind == "delete_field":
        what = _delete_field(frame, rng)
    elif kind == "duplicate_field":
        what, raw = _duplicate_field(frame, rng)
    elif kind == "corrupt_zlib":
        what = _corrupt_zlib(frame, rng)
    elif kind == "shape_huge":
        what = _reshape_matrix(frame, rng, _huge_dims, "huge declared size")
    elif kind == "shape_negative":
        what = _reshape_matrix(frame, rng, _negative_dims, "negative declared size")
    elif kind == "shape_vs_calibration":
        what = _shape_vs_calibration(frame, rng)
    elif kind == "nan_float":
        what = _set_float(frame, rng, NONFINITE)
    elif kind == "extreme_value":
        what = _set_float(frame, rng, (1e38, -1e38, 3.4e38, 1e300, -1e300, 1e-45, 0.0, -0.0))
    elif kind == "nonfinite_extrinsic":
        what = _set_float(frame, rng, NONFINITE + (1e300,), only="extrinsic")
    elif kind == "nonfinite_pose":
        if rng.random() < 0.3:
            what = _set_float(frame, rng, NONFINITE, only="range_image_pose_compressed")
        else:
            what = _set_float(frame, rng, NONFINITE + (1e300,), only="pose")
    elif kind == "nonrigid_pose":
        what = _nonrigid_pose(frame, rng)
    else:
        raise ValueError(f"unknown WOD mutation kind {kind!r}; one of {KINDS}")
    return (raw if raw is not None else frame.SerializeToString()), what
