"""Mutation fuzzing of the project's readers: WOD records, Argoverse 2 feather logs and YAML configs.

Each mutant damages a valid input one way (a `kind`) and must end as either
  - `decoded`: a decode whose arrays are finite and consistent (a config that validates and round-trips), or
  - `named_error`: the reader's own error naming file, record and field (`FrameDecodeError`; `Argoverse2FormatError`
    naming file and column; `ConfigError` naming the key and what is allowed).
Anything else is a defect: `unnamed_error` (our error without file/record/field), `raw_error` (a TensorFlow or
library error escaping), `crash` (any other exception), `nonfinite` (a decode with NaN/Inf or inconsistent arrays),
`slow` (over the per-input time bound). `tools/fuzz_reader.py` runs thousands; `tests/data/test_fuzz.py` a few hundred.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import faulthandler
import os
import resource
import shutil
import time
import zlib

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data import wod_format

WOD_KINDS = ("bit_flip", "truncate", "delete_field", "duplicate_field", "corrupt_zlib", "shape_huge",
             "shape_negative", "shape_vs_calibration", "nan_float", "extreme_value", "nonfinite_extrinsic",
             "nonfinite_pose", "nonrigid_pose")
AV2_KINDS = ("bit_flip", "truncate", "not_feather", "missing_file", "drop_column", "wrong_dtype", "nan_value",
             "empty_table", "zero_quaternion")
CONFIG_KINDS = ("wrong_type", "unknown_key", "out_of_range", "non_finite", "wrong_length", "not_a_mapping",
                "broken_yaml")
DEFECTS = ("unnamed_error", "raw_error", "crash", "nonfinite", "slow")
SECONDS_PER_INPUT = 10.0  # bound on one decode (tiny records take ~10 ms; full-size ~50 ms)


@dataclasses.dataclass
class Result:
    kind: str
    outcome: str
    seconds: float
    detail: str


@dataclasses.dataclass
class Report:
    """Outcomes of a fuzz run: counts by kind x outcome, the slowest input, peak memory."""

    results: list = dataclasses.field(default_factory=list)

    def add(self, result: Result) -> None:
        self.results.append(result)

    @property
    def defects(self) -> list[Result]:
        return [r for r in self.results if r.outcome in DEFECTS]

    def table(self) -> dict[str, collections.Counter]:
        by_kind: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        for r in self.results:
            by_kind[r.kind][r.outcome] += 1
        return dict(by_kind)

    def slowest(self) -> Result | None:
        return max(self.results, key=lambda r: r.seconds, default=None)

    def format(self, title: str) -> str:
        outcomes = ("decoded", "named_error") + DEFECTS
        lines = [f"{title}: {len(self.results)} inputs",
                 f"  {'kind':24s}" + "".join(f"{o:>14s}" for o in outcomes)]
        for kind, counts in sorted(self.table().items()):
            lines.append(f"  {kind:24s}" + "".join(f"{counts.get(o, 0):14d}" for o in outcomes))
        slow = self.slowest()
        if slow is not None:
            lines.append(f"  slowest: {slow.seconds * 1e3:.1f} ms ({slow.kind}: {slow.detail[:120]})")
        lines.append(f"  peak memory (max RSS of this process): {peak_rss_mib():.0f} MiB")
        for r in self.defects[:20]:
            lines.append(f"  DEFECT {r.kind} -> {r.outcome}: {r.detail[:300]}")
        return "\n".join(lines)


@contextlib.contextmanager
def watchdog(seconds: float | None):
    """Aborts the process with every thread's traceback if the block runs longer than `seconds` (a hang is a defect
    to see, not to wait for); None: no watchdog."""
    if seconds is None:
        yield
        return
    faulthandler.dump_traceback_later(seconds, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


WATCHDOG_S: float | None = None  # set by tools/fuzz_reader.py: abort on a hang instead of waiting


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


# --- WOD record mutators -----------------------------------------------------------------------------------------
def _frame(record: bytes):
    from waymo_open_dataset import dataset_pb2
    return dataset_pb2.Frame.FromString(record)


def _pick(rng, items):
    return items[int(rng.integers(len(items)))]


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


def _matrix_bytes(data: np.ndarray, dims) -> bytes:
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
    name = _pick(rng, sorted(choices))
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
    msg, name, label = _pick(rng, _compressed_fields(frame))
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
    msg, name, label = _pick(rng, _compressed_fields(frame))
    array = _decoded_matrix(getattr(msg, name))
    dims = dims_fn(array.shape, rng)
    setattr(msg, name, zlib.compress(_matrix_bytes(array.reshape(-1), dims), 1))
    return f"{label} {array.shape} declared as {tuple(dims)} ({what})"


def _huge_dims(shape, rng):
    h, w, c = shape
    return _pick(rng, [(2 ** 31 - 1, 2 ** 31 - 1, c), (65536, 65536, 4), (1 << 20, 1 << 20, c), (h * 1000, w, c),
                       (2 ** 31 - 1, 1, c), (h, w, 2 ** 31 - 1), (0, 2 ** 31 - 1, c)])


def _negative_dims(shape, rng):
    h, w, c = shape
    return _pick(rng, [(-h, w, c), (-h, -w, c), (h, w, -c), (-1, w, c), (-(2 ** 31), w, c), (h, -w, -c)])


def _disagreeing_dims(shape, rng):
    h, w, c = shape
    return _pick(rng, [(w, h, c), (h * w, 1, c), (h, w * c, 1), (h, w), (h, w, c, 1), (h, w, c + 1), (h - 1, w, c),
                       (h * 2, w // 2 if w % 2 == 0 else w, c)])


def _shape_vs_calibration(frame, rng) -> str:
    if rng.random() < 0.5:
        return _reshape_matrix(frame, rng, _disagreeing_dims, "disagrees with the data or calibration")
    cal = _pick(rng, [c for c in frame.context.laser_calibrations])
    if len(cal.beam_inclinations) and rng.random() < 0.5:
        del cal.beam_inclinations[-1]
        return f"calibration {cal.name}: one beam inclination fewer than image rows"
    cal.beam_inclinations.extend([0.01] * int(rng.integers(1, 4)) if len(cal.beam_inclinations) else [0.0, 0.1, 0.2])
    return f"calibration {cal.name}: beam_inclinations count differs from image rows"


_NONFINITE = (np.nan, np.inf, -np.inf)


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
    name, setter = _pick(rng, targets)
    value = float(_pick(rng, values))
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
        cal = _pick(rng, list(frame.context.laser_calibrations))
        ext = np.asarray(cal.extrinsic.transform, np.float64).reshape(4, 4)
        ext[:3, :3] *= float(rng.choice([0.0, 2.0]))
        cal.extrinsic.transform[:] = wod_format.encode_transform(ext)
        return f"calibration {cal.name} extrinsic rotation scaled (not rigid)"
    frame.pose.transform[:] = wod_format.encode_transform(pose)
    return f"pose {what}"


def mutate_wod(record: bytes, kind: str, rng: np.random.Generator) -> tuple[bytes, str]:
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
        what = _set_float(frame, rng, _NONFINITE)
    elif kind == "extreme_value":
        what = _set_float(frame, rng, (1e38, -1e38, 3.4e38, 1e300, -1e300, 1e-45, 0.0, -0.0))
    elif kind == "nonfinite_extrinsic":
        what = _set_float(frame, rng, _NONFINITE + (1e300,), only="extrinsic")
    elif kind == "nonfinite_pose":
        if rng.random() < 0.3:
            what = _set_float(frame, rng, _NONFINITE, only="range_image_pose_compressed")
        else:
            what = _set_float(frame, rng, _NONFINITE + (1e300,), only="pose")
    elif kind == "nonrigid_pose":
        what = _nonrigid_pose(frame, rng)
    else:
        raise ValueError(f"unknown WOD mutation kind {kind!r}; one of {WOD_KINDS}")
    return (raw if raw is not None else frame.SerializeToString()), what


def _check_frame(frame: dict) -> str | None:
    """None if a decoded frame is finite and consistent, else what is wrong."""
    n = len(frame["points_xyz"])
    for key in ("points_xyz", "intensity", "elongation", "flow_mps", "pose"):
        if not np.all(np.isfinite(frame[key])):
            return f"{key} has non-finite values"
    for key in ("intensity", "elongation", "flow_mps", "class_id", "laser_name"):
        if len(frame[key]) != n:
            return f"{key} has {len(frame[key])} rows for {n} points"
    classes = frame["class_id"]
    if classes.size and (classes.min() < schema.CLASS_NO_LABEL or classes.max() > max(schema.CLASS_NAMES)):
        return "class_id out of range"
    return None


def classify_decode(call, path: str, record_index: int) -> tuple[str, str]:
    """(outcome, detail) of decoding one record: `call()` returns the frame dict or raises."""
    import tensorflow as tf

    from ff3d_tf.data.waymo import FrameDecodeError
    try:
        frame = call()
    except FrameDecodeError as err:
        msg = str(err)
        named = (path in msg and f"record {record_index}" in msg and err.field not in ("", "unknown")
                 and f"field {err.field}" in msg)
        return ("named_error" if named else "unnamed_error"), msg
    except tf.errors.OpError as err:
        return "raw_error", f"{type(err).__name__}: {err.message[:300]}"
    except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
        return "crash", f"{type(err).__name__}: {err}"
    problem = _check_frame(frame)
    return ("nonfinite", problem) if problem else ("decoded", f"{len(frame['points_xyz'])} points")


# Decoder options the mutants cycle through: (returns, with_pixels).
ALL_OPTION_SETS = (((1,), False), ((1, 2), True), ((1,), True), ((1, 2), False))


def fuzz_wod_records(records: list[bytes], num_mutants: int, seed: int = 0, kinds=WOD_KINDS,
                     report: Report | None = None, option_sets=ALL_OPTION_SETS) -> Report:
    """Decodes `num_mutants` damaged copies of `records` (kinds round-robin) with `waymo.decode_frame`."""
    from ff3d_tf.data import waymo
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    for returns, with_pixels in option_sets:  # trace the decoders first: tracing is not decoding time
        waymo.decode_frame(records[0], with_pixels=with_pixels, returns=returns)
    for i in range(num_mutants):
        kind = kinds[i % len(kinds)]
        returns, with_pixels = option_sets[(i // len(kinds)) % len(option_sets)]
        base = records[int(rng.integers(len(records)))]
        mutant, what = mutate_wod(base, kind, rng)
        path, index = f"mutant-{kind}.tfrecord", i
        start = time.perf_counter()
        with watchdog(WATCHDOG_S):
            outcome, detail = classify_decode(
                lambda: waymo.decode_frame(mutant, source=path, record_index=index, with_pixels=with_pixels,
                                           returns=returns), path, index)
        seconds = time.perf_counter() - start
        if seconds > SECONDS_PER_INPUT:
            outcome = "slow"
        report.add(Result(kind, outcome, seconds, f"{what} (returns {returns}) -> {detail}"))
    return report


def write_records(path: str, records) -> str:
    import tensorflow as tf
    with tf.io.TFRecordWriter(path) as writer:
        for record in records:
            writer.write(record)
    return path


def fuzz_wod_files(records: list[bytes], out_dir: str, num_files: int, seed: int = 0, cfg=None,
                   report: Report | None = None, num_pair_files: int = 4) -> Report:
    """Whole files: a damaged record among good ones, or the file cut at a random byte; read by `read_frames`
    (Python-driven) and, for the first `num_pair_files` when `cfg` is given, by the tf.data pair pipeline
    (`pairs.pair_dataset`: seconds per file, as each builds its own pipeline).

    A named error must name this file and the damaged record (a cut file: the first record it breaks)."""
    from ff3d_tf.data import pairs, waymo
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    os.makedirs(out_dir, exist_ok=True)
    for i in range(num_files):
        path = os.path.join(out_dir, f"file-{i}.tfrecord")
        if i % 2:
            kind = "truncate_file"
            write_records(path, records)
            size = os.path.getsize(path)
            cut = int(rng.integers(1, size))
            with open(path, "r+b") as f:
                f.truncate(cut)
            # Record k spans [offsets[k], offsets[k+1]); framing (length + CRCs) is 16 bytes per record.
            offsets = np.cumsum([0] + [len(r) + 16 for r in records])
            bad_index = int(np.searchsorted(offsets, cut, side="right") - 1)
            what = f"file cut at byte {cut} of {size} (inside record {bad_index})"
        else:
            kind = "mixed_file"
            bad_index = int(rng.integers(len(records)))
            mutant, what = mutate_wod(records[bad_index], WOD_KINDS[int(rng.integers(len(WOD_KINDS)))], rng)
            write_records(path, records[:bad_index] + [mutant] + records[bad_index + 1:])
        for reader in ("read_frames", "pair_dataset") if cfg is not None and i < num_pair_files else ("read_frames",):
            start = time.perf_counter()
            with watchdog(None if WATCHDOG_S is None else 6 * WATCHDOG_S):
                if reader == "read_frames":
                    outcome, detail = classify_decode(lambda: _read_all(waymo.read_frames(path)), path, bad_index)
                else:
                    outcome, detail = classify_decode(lambda: _pairs_all(pairs, path, cfg), path, bad_index)
            if outcome == "named_error" and f"record {bad_index}:" not in detail:
                outcome = "unnamed_error"  # names a record, but not the damaged one
            seconds = time.perf_counter() - start
            report.add(Result(f"{kind}/{reader}", "slow" if seconds > 6 * SECONDS_PER_INPUT else outcome, seconds,
                              f"{what} -> {detail}"))
    return report


def _read_all(frames) -> dict:
    """Reads every frame; returns a frame dict concatenating all of them (for `_check_frame`)."""
    decoded = [f for _, _, f in frames]
    if not decoded:
        raise AssertionError("no frame decoded")
    merged = {k: np.concatenate([f[k] for f in decoded]) for k in decoded[0] if k not in ("pose", "timestamp_micros")}
    merged["pose"] = np.stack([f["pose"] for f in decoded])
    return merged


def _pairs_all(pairs, path: str, cfg) -> dict:
    with pairs.input_errors_named([path], pairs.decode_options(cfg)):
        examples = [{k: v.numpy() for k, v in ex.items()} for ex in pairs.pair_dataset([path], cfg)]
    if not examples:
        raise AssertionError("no pair decoded")
    ex = examples[0]
    return {"points_xyz": ex["points_xyz_t0"], "intensity": ex["point_features_t0"][:, 0],
            "elongation": ex["point_features_t0"][:, 1], "flow_mps": ex["flow_mps_t0"], "class_id": ex["class_id_t0"],
            "laser_name": np.zeros(len(ex["class_id_t0"]), np.int32), "pose": ex["pose_t0"]}


# --- Argoverse 2 ---------------------------------------------------------------------------------------------------
def small_av2_copy(src_log: str, dst_log: str, max_points: int = 2000) -> str:
    """A copy of an AV2 log reduced to its first `max_points` points per sweep and the annotations and poses of its
    sweeps (the readers' inputs; fast to fuzz). The source is never written."""
    import pyarrow.feather as feather
    from ff3d_tf.data import argoverse2
    if os.path.exists(dst_log):
        shutil.rmtree(dst_log)
    os.makedirs(os.path.join(dst_log, "sensors", "lidar"))
    stamps = argoverse2.sweep_timestamps(src_log)
    for ts in stamps:
        table = feather.read_table(os.path.join(src_log, "sensors", "lidar", f"{ts}.feather"))
        feather.write_feather(table.slice(0, max_points), os.path.join(dst_log, "sensors", "lidar", f"{ts}.feather"))
    for name in ("annotations.feather", "city_SE3_egovehicle.feather"):
        table = feather.read_table(os.path.join(src_log, name))
        keep = np.isin(table.column("timestamp_ns").to_numpy(), stamps)
        feather.write_feather(table.filter(keep), os.path.join(dst_log, name))
    return dst_log


AV2_COLUMNS = {"sweep": ("x", "y", "z", "intensity", "laser_number"),
               "annotations.feather": ("timestamp_ns", "category", "track_uuid", "length_m", "width_m", "height_m",
                                       "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m"),
               "city_SE3_egovehicle.feather": ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")}


def mutate_av2(log_dir: str, kind: str, rng: np.random.Generator) -> tuple[str, str]:
    """Damages one file of a (copied) AV2 log in place: (path of the damaged file, what was done)."""
    import pyarrow as pa
    import pyarrow.feather as feather
    from ff3d_tf.data import argoverse2
    stamps = argoverse2.sweep_timestamps(log_dir)
    name = _pick(rng, ["sweep", "annotations.feather", "city_SE3_egovehicle.feather"])
    path = (os.path.join(log_dir, "sensors", "lidar", f"{_pick(rng, stamps)}.feather") if name == "sweep"
            else os.path.join(log_dir, name))
    if kind in ("bit_flip", "truncate", "not_feather", "missing_file"):
        data = bytearray(open(path, "rb").read())
        if kind == "bit_flip":
            for _ in range(int(rng.integers(1, 17))):
                data[int(rng.integers(len(data)))] ^= 1 << int(rng.integers(8))
        elif kind == "truncate":
            data = data[: int(rng.integers(0, len(data)))]
        elif kind == "not_feather":
            data = bytearray(b"this is not an arrow file " * int(rng.integers(1, 50)))
        if kind == "missing_file":
            os.remove(path)
        else:
            with open(path, "wb") as f:
                f.write(bytes(data))
        return path, f"{kind} of {os.path.basename(path)}"
    table = feather.read_table(path)
    column = _pick(rng, list(AV2_COLUMNS[name]))
    if kind == "drop_column":
        table = table.drop_columns([column])
    elif kind == "wrong_dtype":
        table = table.set_column(table.schema.get_field_index(column), column,
                                 pa.array(["x"] * table.num_rows, pa.string()))
    elif kind == "nan_value":
        numeric = [c for c in AV2_COLUMNS[name] if pa.types.is_floating(table.schema.field(c).type)]
        column = _pick(rng, numeric)
        values = table.column(column).to_numpy().astype(np.float64)
        if values.size:
            values[int(rng.integers(values.size))] = float(_pick(rng, _NONFINITE))
        table = table.set_column(table.schema.get_field_index(column), column,
                                 pa.array(values, table.schema.field(column).type, from_pandas=False)
                                 if not pa.types.is_float16(table.schema.field(column).type)
                                 else pa.array(values.astype(np.float16)))
    elif kind == "empty_table":
        table = table.slice(0, 0)
    elif kind == "zero_quaternion":
        if name == "sweep":
            name, path = "city_SE3_egovehicle.feather", os.path.join(log_dir, "city_SE3_egovehicle.feather")
            table = feather.read_table(path)
        for q in ("qw", "qx", "qy", "qz"):
            table = table.set_column(table.schema.get_field_index(q), q, pa.array(np.zeros(table.num_rows)))
        column = "qw..qz"
    else:
        raise ValueError(f"unknown AV2 mutation kind {kind!r}; one of {AV2_KINDS}")
    feather.write_feather(table, path)
    return path, f"{kind} in {os.path.basename(path)} column {column}"


def classify_av2(call, path: str) -> tuple[str, str]:
    from ff3d_tf.data.argoverse2 import Argoverse2FormatError
    try:
        f_tm1, f_t0 = call()
    except Argoverse2FormatError as err:
        # The damaged file, or (a deleted sweep) the folder that misses it.
        named = (os.path.basename(path) in str(err) or os.path.dirname(path) in str(err)) and bool(err.column)
        return ("named_error" if named else "unnamed_error"), str(err)
    except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
        return "crash", f"{type(err).__name__}: {err}"
    for frame in (f_tm1, f_t0):
        problem = _check_frame(frame)
        if problem:
            return "nonfinite", problem
    return "decoded", f"{len(f_t0['points_xyz'])} points"


def fuzz_av2(sample_log: str, work_dir: str, num_mutants: int, seed: int = 0, max_points: int = 2000,
             report: Report | None = None) -> Report:
    """Damages a fresh reduced copy of the AV2 log per mutant and reads a labelled pair (`labelled_pair`)."""
    from ff3d_tf.data import argoverse2
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    clean = small_av2_copy(sample_log, os.path.join(work_dir, "clean"), max_points)
    for i in range(num_mutants):
        kind = AV2_KINDS[i % len(AV2_KINDS)]
        log = os.path.join(work_dir, "mutant")
        if os.path.exists(log):
            shutil.rmtree(log)
        shutil.copytree(clean, log)
        path, what = mutate_av2(log, kind, rng)
        start = time.perf_counter()
        with watchdog(WATCHDOG_S):
            outcome, detail = classify_av2(lambda: argoverse2.labelled_pair(log, 1), path)
        seconds = time.perf_counter() - start
        report.add(Result(kind, "slow" if seconds > SECONDS_PER_INPUT else outcome, seconds, f"{what} -> {detail}"))
    return report


# --- YAML configs --------------------------------------------------------------------------------------------------
_WRONG_VALUES = ("text", [1, 2], {"a": 1}, True, None, 1.5, -3, "1e-3x", [[1]])


def mutate_config(rng: np.random.Generator, kind: str) -> tuple[str, str, str]:
    """(YAML text, the dotted key it damages, what was done) from the default config."""
    import yaml

    from ff3d_tf.config import ExperimentConfig
    tree = json_tree(ExperimentConfig())
    section = _pick(rng, sorted(tree))
    key = _pick(rng, sorted(tree[section]))
    default = tree[section][key]
    dotted = f"{section}.{key}"
    if kind == "wrong_type":
        value = _pick(rng, [v for v in _WRONG_VALUES if type(v) is not type(default)])
        tree[section][key] = value
        what = f"{dotted} = {value!r}"
    elif kind == "unknown_key":
        typo = key[:-1] if rng.random() < 0.5 else key + "s"
        if rng.random() < 0.2:
            tree[section + "x"] = {key: default}
            dotted, what = section + "x", f"section {section}x"
        else:
            tree[section][typo] = default
            dotted, what = f"{section}.{typo}", f"{section}.{typo}"
    elif kind == "out_of_range":
        value = _out_of_range(default, rng)
        tree[section][key] = value
        what = f"{dotted} = {value!r}"
    elif kind == "non_finite":
        value = _pick(rng, [float("nan"), float("inf"), float("-inf")])
        tree[section][key] = [value, value] if isinstance(default, list) else value
        what = f"{dotted} = {tree[section][key]!r}"
    elif kind == "wrong_length":
        if isinstance(default, list):
            value = default + default[:1] if rng.random() < 0.5 else default[:-1]
        else:
            value = [default]
        tree[section][key] = value
        what = f"{dotted} = {value!r}"
    elif kind == "not_a_mapping":
        tree[section] = _pick(rng, [[1, 2], "text", 3])
        dotted, what = section, f"section {section} = {tree[section]!r}"
    elif kind == "broken_yaml":
        text = yaml.safe_dump(tree)
        cut = int(rng.integers(1, len(text)))
        broken = text[:cut] + _pick(rng, [": [", "\t", "{", "- -", "!!python/object:os.system x", "\x00"]) + text[cut:]
        return broken, "", f"YAML broken at character {cut}"
    else:
        raise ValueError(f"unknown config mutation kind {kind!r}; one of {CONFIG_KINDS}")
    return yaml.safe_dump(tree, sort_keys=False, allow_unicode=True), dotted, what


def json_tree(cfg) -> dict:
    """The config as plain YAML-able data (tuples as lists)."""
    import json
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def _out_of_range(default, rng):
    if isinstance(default, bool):
        return 2
    if isinstance(default, int):
        return _pick(rng, [-1, -(2 ** 40), 0, 2 ** 62])
    if isinstance(default, float):
        return _pick(rng, [-1.0, 0.0, 1e30, -1e-9, 2.0])
    if isinstance(default, str):
        return "no_such_option"
    if isinstance(default, list):
        if default and isinstance(default[0], list):
            return [[-1, 0]] * len(default)
        return [_pick(rng, [-5, 0, 99])] * len(default) if default else [7]
    return -1


_ALLOWED_WORDS = ("expected", "must", "one of", "known", "allowed", "need", "each", "multiple of", "in [", "in (",
                  ">=", "> 0", "mapping", "true/false", "a number", "an integer", "list")


def classify_config(text: str, dotted: str, tmp_path: str) -> tuple[str, str]:
    from ff3d_tf.config import ConfigError, load_config
    with open(tmp_path, "w", encoding="utf-8") as f:
        f.write(text)
    try:
        cfg = load_config(tmp_path)
    except ConfigError as err:
        msg = str(err)
        key_named = (not dotted or dotted in msg or dotted.split(".")[-1] in msg)
        allowed = any(w in msg for w in _ALLOWED_WORDS) or "YAML" in msg
        return ("named_error" if key_named and allowed else "unnamed_error"), msg
    except Exception as err:  # noqa: BLE001 - any other exception is a defect to report, not to hide
        return "crash", f"{type(err).__name__}: {err}"
    values = [v for section in json_tree(cfg).values() for v in section.values()]
    flat = np.asarray([x for v in values for x in np.ravel(np.asarray(v, dtype=object))
                       if isinstance(x, float)], np.float64)
    if not np.all(np.isfinite(flat)):
        return "nonfinite", "accepted a non-finite value"
    cfg.save(tmp_path + ".resolved.yaml")
    if load_config(tmp_path + ".resolved.yaml") != cfg:
        return "crash", "accepted config does not round-trip through its saved YAML"
    return "decoded", "accepted"


def fuzz_configs(work_dir: str, num_mutants: int, seed: int = 0, report: Report | None = None) -> Report:
    from ff3d_tf.config import ExperimentConfig
    report = report if report is not None else Report()
    rng = np.random.default_rng(seed)
    os.makedirs(work_dir, exist_ok=True)
    path = os.path.join(work_dir, "mutant.yaml")
    ExperimentConfig().save(os.path.join(work_dir, "default.yaml"))  # imports TensorFlow once, outside the timing
    for i in range(num_mutants):
        kind = CONFIG_KINDS[i % len(CONFIG_KINDS)]
        text, dotted, what = mutate_config(rng, kind)
        start = time.perf_counter()
        with watchdog(WATCHDOG_S):
            outcome, detail = classify_config(text, dotted, path)
        report.add(Result(kind, outcome, time.perf_counter() - start, f"{what} -> {detail}"))
    return report
