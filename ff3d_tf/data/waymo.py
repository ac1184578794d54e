"""WOD v1 `Frame` decoding in graph: range images (+ scene-flow labels) of all five lidars -> points in the vehicle frame.

The conversion follows the official `frame_utils.convert_range_image_to_point_cloud` conventions (column azimuths,
reversed inclinations, extrinsic, TOP per-pixel pose correction) but masks the returns first and builds rotations in
closed form, so it costs a fraction of the official path. Geometry runs in float64 (per-pixel TOP rotations in
float32, as their angles are stored) and is cast to float32 at the end.

Errors: every check raises through `tf.debugging.Assert` with a message starting `FRAME_DECODE_ERROR field=<field>`;
codec failures carry the failing field in their op name. `read_frames` turns both into `FrameDecodeError` naming the
file, the record index and the field. See `ff3d_tf.schema` for the decoded keys.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import re
from typing import Iterator

import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.data.wod_format import descriptor_source

_LOG = logging.getLogger(__name__)
_PKG = "waymo.open_dataset."
_ERROR_TAG = "FRAME_DECODE_ERROR"
DECODE_WORKERS = 2  # threads of decoded_records; each decode also runs its independent ops in parallel


class FrameDecodeError(ValueError):
    """A record that cannot be decoded: names the file, the record index and the field."""

    def __init__(self, path: str, record_index: int, field: str, reason: str):
        self.path, self.record_index, self.field, self.reason = path, record_index, field, reason
        record = f"record {record_index}" if record_index >= 0 else "record unknown"
        super().__init__(f"{path}: {record}: field {field}: {reason}")


class MissingFlowLabelsError(FrameDecodeError):
    """The frame has no `range_image_flow_compressed`; the message says how to get labels."""


MISSING_FLOW_HELP = (
    "this frame has no scene-flow labels (range_image_flow_compressed). Ordinary WOD v1 frames carry none: use the "
    "scene-flow release of WOD (Jund et al., appendix 'Dataset Format for Annotations'), or bootstrap labels from the "
    "tracked boxes with `python tools/annotate_flow.py`; for model input without labels pass inference_only=True")


@dataclasses.dataclass(frozen=True)
class DecodeOptions:
    laser_names: tuple[int, ...] = schema.ALL_LASERS
    returns: tuple[int, ...] = (1,)
    require_flow: bool = True  # False: frames without labels decode with flow 0 and class -1 (inference input)
    # Also return pixel_row_col [N,2], return_index [N], in_no_label_zone [N] and range_image_hw [L*R,2] (height,
    # width of each decoded range image, sorted by laser then return): what label writers need.
    with_pixels: bool = False

    def __post_init__(self):
        if not self.laser_names or not set(self.laser_names) <= set(schema.ALL_LASERS):
            raise ValueError(f"laser names {self.laser_names}: each must be one of {schema.ALL_LASERS} (TOP..REAR)")
        if not self.returns or not set(self.returns) <= {1, 2}:
            raise ValueError(f"returns {self.returns}: each must be 1 or 2")


def _op_name(kind: str, field: str) -> str:
    """Op names carry the field, so a codec error names it: `zlib__lasers_TOP_.ri_return1.range_image_compressed`."""
    return f"{kind}__" + re.sub(r"[^A-Za-z0-9_.]", "_", field)


def _proto(serialized, message, fields, types, name):
    """decode_proto of one scalar message -> (sizes [F], [values_f]) with leading batch dim removed."""
    sizes, values = tf.io.decode_proto(
        tf.reshape(serialized, [1]), _PKG + message, fields, types,
        descriptor_source=descriptor_source(), name=_op_name("frame" if name.startswith("frame__") else
                                                             name.split("__")[0], name.split("__", 1)[1]))
    # One default element appended so that `[0]` of an absent optional field still works; sizes say what is real.
    return sizes[0], [tf.concat([v[0], tf.zeros([1], t) if t != tf.string else tf.constant([""])], 0)
                      for v, t in zip(values, types)]


def _check(cond, field: str, reason: str, source) -> tf.Operation:
    return tf.debugging.Assert(cond, [f"{_ERROR_TAG} field={field}: {reason}; source:", source], summarize=1)


def _guarded(tensor, checks):
    with tf.control_dependencies(checks):
        return tf.identity(tensor)


def _matrix_float_payload(raw, field: str):
    """(data [M] float32, serialized MatrixShape) of a serialized MatrixFloat.

    Fast path for the layout every writer produces (packed `data` first: tag 0x0A, varint length, little-endian
    floats; then `shape`): the floats are reinterpreted in place with decode_raw, and only the small tail is parsed
    as a proto. Any other layout goes through decode_proto.
    """
    n = tf.strings.length(raw)
    head = tf.io.decode_raw(tf.strings.join([tf.strings.substr(raw, 0, 6), "\0" * 6]), tf.uint8)[:6]  # tag+varint
    b = tf.cast(head[1:6], tf.int64)
    ends = b < 128  # varint bytes without the continuation bit
    nbytes = tf.cast(tf.argmax(tf.cast(ends, tf.int32)), tf.int64) + 1
    length = tf.reduce_sum(tf.where(tf.range(5, dtype=tf.int64) < nbytes,
                                    tf.bitwise.left_shift(tf.bitwise.bitwise_and(b, 127),
                                                          7 * tf.range(5, dtype=tf.int64)), 0))
    start = 1 + nbytes
    fast = (tf.equal(head[0], 0x0A) & tf.reduce_any(ends) & (start + length <= tf.cast(n, tf.int64)) &
            tf.equal(length % 4, 0))

    def fast_path():
        payload = tf.strings.substr(raw, start, length)
        tail = tf.strings.substr(raw, start + length, tf.cast(n, tf.int64) - start - length)
        tail_sizes, (tail_data, shape_msg) = _proto(tail, "MatrixFloat", ["data", "shape"], [tf.float32, tf.string],
                                                    f"matrix__{field}")
        data = tf.io.decode_raw(payload, tf.float32, little_endian=True)
        # A second `data` field in the tail (legal, never written in practice) is appended as the proto would.
        return tf.concat([data, tail_data[: tail_sizes[0]]], 0), shape_msg[0]

    def slow_path():
        sizes, (data, shape_msg) = _proto(raw, "MatrixFloat", ["data", "shape"], [tf.float32, tf.string],
                                          f"matrix__{field}")
        return data[: sizes[0]], shape_msg[0]

    return tf.cond(fast, fast_path, slow_path)


def _matrix(compressed, field: str, channels: int, source):
    """zlib -> MatrixFloat -> [H, W, channels] with checked shape and finite values."""
    raw = tf.io.decode_compressed(compressed, "ZLIB", name=_op_name("zlib", field))
    data, shape_msg = _matrix_float_payload(raw, field)
    dims_sizes, (dims,) = _proto(shape_msg, "MatrixShape", ["dims"], [tf.int32], f"shape__{field}")
    dims = dims[: dims_sizes[0]]
    checks = [
        _check(tf.equal(tf.size(dims), 3), field, "matrix shape must have 3 dims", source),
    ]
    with tf.control_dependencies(checks):
        dims3 = tf.identity(tf.concat([dims, [1, 1, 1]], 0)[:3])
    checks = [
        _check(tf.equal(dims3[2], channels), field, f"expected {channels} channels", source),
        _check(tf.equal(tf.size(data), tf.reduce_prod(dims3)), field,
               "data size disagrees with its shape (truncated or corrupt matrix)", source),
        _check(tf.reduce_all(tf.math.is_finite(data)), field, "non-finite values", source),
    ]
    data = _guarded(data, checks)
    out = tf.reshape(data, dims3)
    out.set_shape([None, None, channels])
    return out


def _transform(serialized, field: str, source):
    sizes, (values,) = _proto(serialized, "Transform", ["transform"], [tf.float64], f"transform__{field}")
    checks = [_check(tf.equal(sizes[0], 16), field, "transform must have 16 values", source),
              _check(tf.reduce_all(tf.math.is_finite(values)), field, "non-finite values", source)]
    values = _guarded(tf.concat([values[: sizes[0]], tf.zeros([16], tf.float64)], 0)[:16], checks)
    return tf.reshape(values, [4, 4])


def _rotate_rpy(rpy, xyz):
    """Rz(yaw) Ry(pitch) Rx(roll) @ xyz per row: rpy, xyz [M,3] -> [M,3], without forming [M,3,3] matrices."""
    cr, sr = tf.cos(rpy[:, 0]), tf.sin(rpy[:, 0])
    cp, sp = tf.cos(rpy[:, 1]), tf.sin(rpy[:, 1])
    cy, sy = tf.cos(rpy[:, 2]), tf.sin(rpy[:, 2])
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    # Roll about x, then pitch about y, then yaw about z.
    y1, z1 = cr * y - sr * z, sr * y + cr * z
    x2, z2 = cp * x + sp * z1, cp * z1 - sp * x
    return tf.stack([cy * x2 - sy * y1, sy * x2 + cy * y1, z2], -1)


def _col0(values, fill):
    """First column of a [K, max_count] decode_proto output, also when max_count is 0."""
    pad = tf.fill([tf.shape(values)[0], 1], tf.constant(fill, values.dtype))
    return tf.concat([values, pad], 1)[:, 0]


def _select_by_name(names, values, name: int, what: str, source):
    """The single entry of a repeated message whose `name` equals `name`."""
    hits = tf.where(tf.equal(names, name))[:, 0]
    check = _check(tf.equal(tf.size(hits), 1), f"{what}[{schema.LASER_NAMES[name]}]",
                   "missing (or duplicated) for this laser", source)
    with tf.control_dependencies([check]):
        return tf.gather(values, tf.concat([hits, [0]], 0)[0])


@tf.autograph.experimental.do_not_convert  # plain TF ops and static Python loops: no AutoGraph pass per dataset
def decode_frame_tensors(serialized, source, options: DecodeOptions = DecodeOptions()) -> dict[str, tf.Tensor]:
    """Graph decoder of one serialized `Frame` (usable inside `tf.data.Dataset.map`).

    Args:
      serialized: scalar tf.string, one record.
      source: scalar tf.string naming the record in error messages (e.g. "file.tfrecord record 3").
      options: lasers, returns, flow requirement.
    Returns:
      dict of tensors as in `ff3d_tf.schema` (decoded frame), plus pixel indices when `options.with_pixels`.
    """
    sizes, (context, timestamp, pose_msg, lasers) = _proto(
        serialized, "Frame", ["context", "timestamp_micros", "pose", "lasers"],
        [tf.string, tf.int64, tf.string, tf.string], "frame__Frame")
    checks = [_check(tf.equal(sizes[0], 1), "context", "missing", source),
              _check(tf.equal(sizes[2], 1), "pose", "missing", source)]
    context, pose_msg = _guarded(context[:1], checks)[0], pose_msg[0]
    timestamp = timestamp[0]
    lasers = lasers[: sizes[3]]
    frame_pose = _transform(pose_msg, "pose", source)

    csizes, (calibs,) = _proto(context, "Context", ["laser_calibrations"], [tf.string], "frame__Context")
    calibs = calibs[: csizes[0]]
    cal_sizes, (cal_names, incl, incl_min, incl_max, extrinsics) = _decode_repeated(
        calibs, "LaserCalibration",
        ["name", "beam_inclinations", "beam_inclination_min", "beam_inclination_max", "extrinsic"],
        [tf.int32, tf.float64, tf.float64, tf.float64, tf.string])
    _, (las_names, ri1, ri2) = _decode_repeated(lasers, "Laser", ["name", "ri_return1", "ri_return2"],
                                                        [tf.int32, tf.string, tf.string])
    vehicle_from_world = tf.linalg.inv(frame_pose)

    outputs: dict[str, list] = {k: [] for k in ("points_xyz", "intensity", "elongation", "flow_mps", "class_id",
                                                "laser_name", "pixel_row_col", "return_index", "in_no_label_zone",
                                                "range_image_hw")}
    for laser in sorted(options.laser_names):
        lname = schema.LASER_NAMES[laser]
        cal_index = _select_by_name(_col0(cal_names, 0), tf.range(tf.shape(cal_names)[0]), laser, "laser_calibrations",
                                    source)
        las_index = _select_by_name(_col0(las_names, 0), tf.range(tf.shape(las_names)[0]), laser, "lasers", source)
        extrinsic = _transform(tf.gather(_col0(extrinsics, ""), cal_index), f"laser_calibrations[{lname}].extrinsic",
                               source)
        n_incl = tf.gather(cal_sizes[:, 1], cal_index)
        explicit_incl = tf.gather(incl, cal_index)[:n_incl]
        top_pose = None
        for ret in sorted(options.returns):
            field = f"lasers[{lname}].ri_return{ret}"
            ri_msg = tf.gather(_col0(ri1 if ret == 1 else ri2, ""), las_index)
            ri_sizes, (ri_c, pose_c, flow_c, nlz_dummy) = _proto(
                ri_msg, "RangeImage",
                ["range_image_compressed", "range_image_pose_compressed", "range_image_flow_compressed",
                 "segmentation_label_compressed"], [tf.string] * 4, f"frame__RangeImage_{lname}_{ret}")
            del nlz_dummy
            has_range = tf.logical_and(tf.equal(ri_sizes[0], 1), tf.greater(tf.strings.length(ri_c[0]), 0))
            range_bytes = _guarded(ri_c[0], [_check(has_range, f"{field}.range_image_compressed", "missing", source)])
            ri = _matrix(range_bytes, f"{field}.range_image_compressed", 4, source)
            height, width = tf.shape(ri)[0], tf.shape(ri)[1]
            incl_check = _check(tf.logical_or(tf.equal(n_incl, 0), tf.equal(n_incl, height)),
                                f"{field}.range_image_compressed",
                                "range image height disagrees with the calibration's beam_inclinations", source)
            with tf.control_dependencies([incl_check]):
                uniform = tf.gather(_col0(incl_min, 0.0), cal_index) + (tf.cast(tf.range(height), tf.float64) + 0.5) / \
                    tf.cast(height, tf.float64) * (tf.gather(_col0(incl_max, 0.0), cal_index) -
                                                   tf.gather(_col0(incl_min, 0.0), cal_index))
            inclinations = tf.reverse(tf.cond(n_incl > 0, lambda: explicit_incl, lambda: uniform), [0])

            if options.require_flow:
                has_flow = tf.logical_and(tf.equal(ri_sizes[2], 1), tf.greater(tf.strings.length(flow_c[0]), 0))
                flow_bytes = _guarded(flow_c[0], [_check(has_flow, f"{field}.range_image_flow_compressed",
                                                         "MISSING_FLOW " + MISSING_FLOW_HELP, source)])
                flow_img = _matrix(flow_bytes, f"{field}.range_image_flow_compressed", 4, source)
                shape_ok = tf.reduce_all(tf.equal(tf.shape(flow_img)[:2], tf.shape(ri)[:2]))
                flow_img = _guarded(flow_img, [_check(shape_ok, f"{field}.range_image_flow_compressed",
                                                      "shape disagrees with the range image", source)])
            else:
                flow_img = None
            if laser == 1 and top_pose is None:
                # The TOP pose lives in return 1 and serves both returns (as in the official conversion).
                ri1_msg = tf.gather(_col0(ri1, ""), las_index)
                p_sizes, (pose_bytes,) = _proto(ri1_msg, "RangeImage", ["range_image_pose_compressed"], [tf.string],
                                                "frame__TopPose")
                pfield = "lasers[TOP].ri_return1.range_image_pose_compressed"
                has_pose = tf.logical_and(tf.equal(p_sizes[0], 1), tf.greater(tf.strings.length(pose_bytes[0]), 0))
                pose_bytes = _guarded(pose_bytes[0], [_check(has_pose, pfield, "missing", source)])
                top_pose = _matrix(pose_bytes, pfield, 6, source)
                pshape_ok = tf.reduce_all(tf.equal(tf.shape(top_pose)[:2], tf.shape(ri)[:2]))
                top_pose = _guarded(top_pose, [_check(pshape_ok, pfield, "shape disagrees with the range image",
                                                      source)])

            # Mask first: only pixels with a return are converted. [M, 2] row-major (official order).
            pixel_rc = tf.cast(tf.where(ri[..., 0] > 0), tf.int32)
            values = tf.gather_nd(ri, pixel_rc)  # [M, 4]
            rng = tf.cast(values[:, 0], tf.float64)
            # Trigonometry once per column (azimuth) and per row (inclination), gathered per point.
            az_correction = tf.atan2(extrinsic[1, 0], extrinsic[0, 0])
            w = tf.cast(width, tf.float64)
            azimuth = ((w - tf.cast(tf.range(width), tf.float64) - 0.5) / w * 2.0 - 1.0) * np.pi - az_correction
            col, row = pixel_rc[:, 1], pixel_rc[:, 0]
            cos_incl_rng = tf.gather(tf.cos(inclinations), row) * rng
            xyz_sensor = tf.stack([tf.gather(tf.cos(azimuth), col) * cos_incl_rng,
                                   tf.gather(tf.sin(azimuth), col) * cos_incl_rng,
                                   tf.gather(tf.sin(inclinations), row) * rng], -1)
            xyz = tf.linalg.matmul(xyz_sensor, extrinsic[:3, :3], transpose_b=True) + extrinsic[:3, 3]
            if laser == 1:
                # Per-pixel rotation in float32 (the stored angles are float32; < 1e-5 m at 75 m range), written
                # out per component; the world translation and everything after it in float64.
                pix_pose = tf.gather_nd(top_pose, pixel_rc)  # [M, 6] float32 as stored
                xyz_world = tf.cast(_rotate_rpy(pix_pose[:, :3], tf.cast(xyz, tf.float32)), tf.float64) + \
                    tf.cast(pix_pose[:, 3:], tf.float64)
                xyz = tf.linalg.matmul(xyz_world, vehicle_from_world[:3, :3], transpose_b=True) + \
                    vehicle_from_world[:3, 3]
            m = tf.shape(pixel_rc)[0]
            if flow_img is not None:
                flow_values = tf.gather_nd(flow_img, pixel_rc)
                flow_mps, class_id = flow_values[:, :3], tf.cast(tf.round(flow_values[:, 3]), tf.int32)
            else:
                flow_mps, class_id = tf.zeros([m, 3]), tf.fill([m], schema.CLASS_NO_LABEL)
            outputs["points_xyz"].append(tf.cast(xyz, tf.float32))
            outputs["intensity"].append(values[:, 1])
            outputs["elongation"].append(values[:, 2])
            outputs["flow_mps"].append(flow_mps)
            outputs["class_id"].append(class_id)
            outputs["laser_name"].append(tf.fill([m], laser))
            outputs["pixel_row_col"].append(pixel_rc)
            outputs["return_index"].append(tf.fill([m], ret))
            outputs["in_no_label_zone"].append(values[:, 3] > 0)
            outputs["range_image_hw"].append(tf.reshape(tf.shape(ri)[:2], [1, 2]))

    result = {k: tf.concat(v, 0) for k, v in outputs.items()}
    if not options.with_pixels:
        for k in ("pixel_row_col", "return_index", "in_no_label_zone", "range_image_hw"):
            result.pop(k)
    result["pose"] = frame_pose
    result["timestamp_micros"] = timestamp
    return result


def _decode_repeated(serialized_list, message, fields, types):
    """decode_proto over a [K] list of messages -> sizes [K, F], values [K, max_count] each."""
    sizes, values = tf.io.decode_proto(serialized_list, _PKG + message, fields, types,
                                       descriptor_source=descriptor_source(), name=f"frame__{message}")
    return sizes, values


_DECODERS: dict[DecodeOptions, tf.types.experimental.ConcreteFunction] = {}


def _decoder(options: DecodeOptions):
    if options not in _DECODERS:
        fn = tf.function(lambda s, src: decode_frame_tensors(s, src, options))
        _DECODERS[options] = fn.get_concrete_function(tf.TensorSpec([], tf.string), tf.TensorSpec([], tf.string))
    return _DECODERS[options]


def _to_numpy(tensors: dict) -> dict:
    out = {k: v.numpy() for k, v in tensors.items()}
    out["timestamp_micros"] = int(out["timestamp_micros"])
    return out


_FIELD_FROM_NODE = re.compile(r"(?:zlib|matrix|shape|transform|frame)__([A-Za-z0-9_.]+)")


def _field_from_op_error(err: tf.errors.OpError) -> tuple[str, str]:
    """(field, reason) from a decoder op error: our Assert tag or the name of the failing codec op."""
    msg = err.message
    tag = re.search(_ERROR_TAG + r" field=([^:]+): (.*?); source:", msg, re.S)
    if tag:
        return tag.group(1), tag.group(2).strip()
    node = _FIELD_FROM_NODE.search(msg)
    field = node.group(1) if node else "Frame"
    field = re.sub(r"_(TOP|FRONT|SIDE_LEFT|SIDE_RIGHT|REAR)_\.", r"[\1].", field)
    field = re.sub(r"RangeImage_(TOP|FRONT|SIDE_LEFT|SIDE_RIGHT|REAR)_(\d)", r"lasers[\1].ri_return\2", field)
    first_line = msg.strip().splitlines()[0] if msg.strip() else type(err).__name__
    return field, f"cannot decode ({first_line[:200]})"


def decode_frame(serialized_frame: bytes, *, laser_names=schema.ALL_LASERS, returns=(1,), inference_only=False,
                 with_pixels=False, source: str = "<bytes>", record_index: int = 0) -> dict:
    """Eager helper: one serialized WOD `Frame` -> dict of NumPy arrays (keys and order: `ff3d_tf.schema`).

    Raises FrameDecodeError (MissingFlowLabelsError without labels unless `inference_only`).
    """
    options = DecodeOptions(tuple(laser_names), tuple(returns), not inference_only, with_pixels)
    try:
        return _to_numpy(_decoder(options)(tf.constant(serialized_frame), tf.constant(f"{source} record "
                                                                                      f"{record_index}")))
    except tf.errors.OpError as err:
        raise _decode_error(source, record_index, err) from None


def _decode_error(path: str, record_index: int, err: tf.errors.OpError) -> FrameDecodeError:
    field, reason = _field_from_op_error(err)
    if reason.startswith("MISSING_FLOW"):
        return MissingFlowLabelsError(path, record_index, field, reason[len("MISSING_FLOW "):])
    return FrameDecodeError(path, record_index, field, reason)


@dataclasses.dataclass
class ReadStats:
    records: int = 0
    decoded: int = 0
    skipped: int = 0
    errors: list = dataclasses.field(default_factory=list)


def iterate_records(path: str, stats: ReadStats | None = None, skip_bad_records: bool = False
                    ) -> Iterator[tuple[int, bytes]]:
    """(record_index, bytes) of one TFRecord file; a truncated/corrupt file gives a FrameDecodeError."""
    index = 0
    iterator = iter(tf.data.TFRecordDataset(path))
    while True:
        try:
            record = next(iterator)
        except StopIteration:
            return
        except (tf.errors.DataLossError, tf.errors.InvalidArgumentError, tf.errors.OutOfRangeError) as err:
            error = FrameDecodeError(path, index, "tfrecord", f"corrupt or truncated TFRecord ({err.message[:160]})")
            if not skip_bad_records:
                raise error from None
            if stats is not None:
                stats.skipped += 1
                stats.errors.append(str(error))
            _LOG.warning("skipping the rest of %s: %s", path, error)
            return
        except tf.errors.NotFoundError as err:
            raise FrameDecodeError(path, index, "file", f"cannot open ({err.message[:160]})") from None
        if stats is not None:
            stats.records += 1
        yield index, record.numpy()
        index += 1


def frames_dataset(path: str, options: DecodeOptions = DecodeOptions(), skip_bad_records: bool = False
                   ) -> tf.data.Dataset:
    """(record_index, decoded frame) of one file, decoded in graph in parallel, in file order.

    A bad record raises from the iterator (see `pipeline_error` for a FrameDecodeError), or with `skip_bad_records`
    is dropped with a warning (a truncated file ends there). The map calls the decoder traced once per process
    (`_decoder`): building the dataset costs no tracing.
    """
    decoder = _decoder(options)

    def decode(index, record):
        return index, decoder(record, tf.strings.join([path, " record ", tf.strings.as_string(index)]))

    records = tf.data.TFRecordDataset(path)
    if skip_bad_records:
        records = records.ignore_errors(log_warning=True)
    frames = records.enumerate().map(decode, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    return frames.ignore_errors(log_warning=True) if skip_bad_records else frames


def pipeline_error(err: tf.errors.OpError, files: list[str]) -> FrameDecodeError | None:
    """A FrameDecodeError for an input-pipeline error raised by the decoder of `frames_dataset`, or None if the
    error did not come from decoding.

    The decoder's own checks carry the record's source, so those name file, record and field. A codec failure (a
    record that is not a Frame, corrupt zlib, a truncated file) names its field but not its record: the error says
    how to find it.
    """
    if "user-defined function" not in err.message and "DataLoss" not in type(err).__name__:
        return None
    field, reason = _field_from_op_error(err)
    source = re.search(_ERROR_TAG + r".*?source:\]? \[?(.*?) record (\d+)\]?", err.message, re.S)
    hint = " (data.skip_bad_records=true skips bad records)"
    if source:
        error = _decode_error(source.group(1).strip(), int(source.group(2)), err)
        return type(error)(error.path, error.record_index, error.field, error.reason + hint)
    where = files[0] if len(files) == 1 else f"one of {len(files)} files ({files[0]}, ...)"
    if "user-defined function" not in err.message:
        field = "tfrecord"  # raised by the TFRecord reader: a corrupt or truncated file
    first_line = re.sub(r"\{\{[^}]*\}\}|\[Op:[^\]]*\]|name:\s*$", "", err.message.strip().splitlines()[0]).strip()
    reason = "cannot decode: " + first_line.split(": ")[-1][:200]
    return FrameDecodeError(where, -1, field, reason + hint + "; `python tools/dataset_stats.py --data_dir ...` "
                            "reads the same files and names the bad record")


def decoded_records(path: str, options: DecodeOptions = DecodeOptions(), skip_bad_records: bool = False,
                    stats: ReadStats | None = None, workers: int = DECODE_WORKERS
                    ) -> Iterator[tuple[int, bytes, dict]]:
    """(record_index, record bytes, decoded frame as NumPy) of one file, in file order.

    `workers` threads call the decoder traced once per process (`_decoder`), so a new file costs no tracing or graph
    optimisation (a per-file `tf.data` map costs about 4 s of both). A bad record raises a FrameDecodeError naming
    file, record and field, or (skip_bad_records) is counted and reading goes on with the next record. A corrupt or
    truncated TFRecord ends the file (nothing after it can be framed). Frames without scene-flow labels always raise
    MissingFlowLabelsError when labels are required (skipping them would silently drop a whole segment).
    """
    stats = stats if stats is not None else ReadStats()
    decoder = _decoder(options)

    def decode(index: int, record: bytes):
        try:
            return _to_numpy(decoder(tf.constant(record), tf.constant(f"{path} record {index}")))
        except tf.errors.OpError as err:
            return _decode_error(path, index, err)

    with concurrent.futures.ThreadPoolExecutor(max(1, workers)) as pool:
        pending: collections.deque = collections.deque()

        def oldest():
            index, record, future = pending.popleft()
            result = future.result()
            if isinstance(result, FrameDecodeError):
                if not skip_bad_records or isinstance(result, MissingFlowLabelsError):
                    raise result
                stats.skipped += 1
                stats.errors.append(str(result))
                _LOG.warning("skipping %s", result)
                return None
            stats.decoded += 1
            return index, record, result

        records = iterate_records(path, stats, skip_bad_records)
        framing_error = None
        while True:
            try:
                index, record = next(records)
            except StopIteration:
                break
            except FrameDecodeError as err:  # corrupt TFRecord: raised after the records before it (file order)
                framing_error = err
                break
            pending.append((index, record, pool.submit(decode, index, record)))
            if len(pending) > max(1, workers):
                done = oldest()
                if done is not None:
                    yield done
        while pending:
            done = oldest()
            if done is not None:
                yield done
        if framing_error is not None:
            raise framing_error


def read_frames(paths, *, laser_names=schema.ALL_LASERS, returns=(1,), inference_only=False, with_pixels=False,
                skip_bad_records=False, stats: ReadStats | None = None) -> Iterator[tuple[str, int, dict]]:
    """Yields (path, record_index, decoded frame) over files; bad records raise, or are skipped and counted."""
    options = DecodeOptions(tuple(laser_names), tuple(returns), not inference_only, with_pixels)
    for path in ([paths] if isinstance(paths, str) else paths):
        for index, _, frame in decoded_records(path, options, skip_bad_records, stats):
            yield path, index, frame
