"""WOD v1 `Frame` decoding in graph: range images (+ scene-flow labels) of all five lidars -> points in the vehicle frame.

The conversion follows the official `frame_utils.convert_range_image_to_point_cloud` conventions (the polar geometry
of `ff3d_tf.data.wod_format`: column azimuths, reversed inclinations, extrinsic, TOP per-pixel pose correction) but
masks the returns first, so it costs a fraction of the official path. Geometry runs in float64 (per-pixel TOP
rotations in float32, as their angles are stored) and is cast to float32 at the end.

`decode_frame_tensors` runs five named steps: parse (protos), pose (frame pose), calibrate (extrinsic, inclinations),
to points (range image -> xyz) and flow (labels), each a function of this module.

Errors: every check is a `tf.debugging.Assert` whose message this module writes (`_check`: a tag with field, kind,
reason and the record's source), checked before any allocation of a declared size; `parse_tagged_error` reads it
back. A codec failure (a record that is not a protobuf, corrupt zlib) carries no tag: `diagnose_record` then finds
the field by re-reading the record in Python. Either way the caller gets a `FrameDecodeError` naming file, record
and field; nothing parses TensorFlow's own wording. See `ff3d_tf.schema` for the decoded keys.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import logging
import time
import zlib
from typing import Iterator, NamedTuple

import tensorflow as tf

from ff3d_tf import geometry, schema
from ff3d_tf.data import wod_format
from ff3d_tf.data.wod_format import descriptor_source

_LOG = logging.getLogger(__name__)
_PKG = "waymo.open_dataset."
DECODE_WORKERS = 2  # threads of decoded_records; each decode also runs its independent ops in parallel
# Declared range image sizes beyond these are refused before anything of that size is allocated (a WOD TOP range
# image is 64 x 2650; a decompressed matrix is never reshaped to dims its data does not fill).
MAX_RANGE_IMAGE_DIM = 1 << 16
# Messages the decoder parses with decode_proto (what `diagnose_record` descends into).
_DECODED_MESSAGES = ("Frame", "Context", "LaserCalibration", "Laser", "RangeImage", "Transform")
TF_OPS = wod_format.ArrayOps(to_f64=lambda x: tf.cast(x, tf.float64),
                             arange_f64=lambda n: tf.range(tf.cast(n, tf.float64)), atan2=tf.atan2, cos=tf.cos,
                             sin=tf.sin, stack_last=lambda xs: tf.stack(xs, -1))


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


# --- The decoder's own error messages -----------------------------------------------------------------------------
_TAG_OPEN, _TAG_CLOSE = "<<FRAME_DECODE_ERROR|", "|END_FRAME_DECODE_ERROR>>"
_KIND_ERROR, _KIND_MISSING_FLOW = "error", "missing_flow"


class TaggedError(NamedTuple):
    field: str
    kind: str
    reason: str
    source: str  # "<path> record <index>", as passed to decode_frame_tensors


def _check(cond, field: str, reason: str, source, kind: str = _KIND_ERROR) -> tf.Operation:
    """An assertion whose message is `<<FRAME_DECODE_ERROR|field|kind|reason|source|END...>>` (no `|` in field, kind
    or reason; the source may hold anything)."""
    assert "|" not in field + kind + reason, (field, kind, reason)
    message = tf.strings.join([f"{_TAG_OPEN}{field}|{kind}|{reason}|", source, _TAG_CLOSE])
    return tf.debugging.Assert(cond, [message], summarize=1)


def parse_tagged_error(message: str) -> TaggedError | None:
    """The first tag written by `_check` in an error message, or None."""
    start = message.find(_TAG_OPEN)
    end = message.find(_TAG_CLOSE, start)
    if start < 0 or end < 0:
        return None
    parts = message[start + len(_TAG_OPEN): end].split("|", 3)
    return TaggedError(*parts) if len(parts) == 4 else None


def _split_source(source: str) -> tuple[str, int]:
    """("path", index) of a source written as "<path> record <index>"."""
    path, _, index = source.rpartition(" record ")
    return (path, int(index)) if path and index.lstrip("-").isdigit() else (source, -1)


def _guarded(tensor, checks):
    with tf.control_dependencies(checks):
        return tf.identity(tensor)


# --- Step "parse": protos -> tensors ------------------------------------------------------------------------------
def _proto(serialized, message, fields, types):
    """decode_proto of one scalar message -> (sizes [F], [values_f]) with leading batch dim removed."""
    sizes, values = tf.io.decode_proto(tf.reshape(serialized, [1]), _PKG + message, fields, types,
                                       descriptor_source=descriptor_source())
    # One default element appended so that `[0]` of an absent optional field still works; sizes say what is real.
    return sizes[0], [tf.concat([v[0], tf.zeros([1], t) if t != tf.string else tf.constant([""])], 0)
                      for v, t in zip(values, types)]


def _decode_repeated(serialized_list, message, fields, types):
    """decode_proto over a [K] list of messages -> sizes [K, F], values [K, max_count] each."""
    return tf.io.decode_proto(serialized_list, _PKG + message, fields, types, descriptor_source=descriptor_source())


def _col0(values, fill):
    """First column of a [K, max_count] decode_proto output, also when max_count is 0."""
    pad = tf.fill([tf.shape(values)[0], 1], tf.constant(fill, values.dtype))
    return tf.concat([values, pad], 1)[:, 0]


class ParsedFrame(NamedTuple):
    """The parts of a `Frame` the decoder reads, one row per calibration / laser entry in file order."""

    timestamp_micros: tf.Tensor  # [] int64 (0 when absent)
    pose_msg: tf.Tensor  # [] serialized Transform
    cal_names: tf.Tensor  # [C] LaserName
    cal_num_inclinations: tf.Tensor  # [C]
    cal_inclinations: tf.Tensor  # [C, max] float64, stored (ascending) order
    cal_inclination_min: tf.Tensor  # [C] float64
    cal_inclination_max: tf.Tensor  # [C] float64
    cal_extrinsics: tf.Tensor  # [C] serialized Transform
    laser_names: tf.Tensor  # [L] LaserName
    laser_returns: tuple  # ([L] serialized RangeImage of return 1, [L] of return 2)


def parse_frame(serialized, source) -> ParsedFrame:
    """Step "parse": the Frame, its Context and the repeated calibrations and lasers (no range image yet)."""
    sizes, (context, timestamp, pose_msg, lasers) = _proto(
        serialized, "Frame", ["context", "timestamp_micros", "pose", "lasers"],
        [tf.string, tf.int64, tf.string, tf.string])
    checks = [_check(tf.equal(sizes[0], 1), "context", "missing", source),
              _check(tf.equal(sizes[2], 1), "pose", "missing", source)]
    context = _guarded(context[:1], checks)[0]
    csizes, (calibs,) = _proto(context, "Context", ["laser_calibrations"], [tf.string])
    cal_sizes, (cal_names, incl, incl_min, incl_max, extrinsics) = _decode_repeated(
        calibs[: csizes[0]], "LaserCalibration",
        ["name", "beam_inclinations", "beam_inclination_min", "beam_inclination_max", "extrinsic"],
        [tf.int32, tf.float64, tf.float64, tf.float64, tf.string])
    _, (las_names, ri1, ri2) = _decode_repeated(lasers[: sizes[3]], "Laser", ["name", "ri_return1", "ri_return2"],
                                                [tf.int32, tf.string, tf.string])
    return ParsedFrame(timestamp[0], pose_msg[0], _col0(cal_names, 0), cal_sizes[:, 1], incl, _col0(incl_min, 0.0),
                       _col0(incl_max, 0.0), _col0(extrinsics, ""), _col0(las_names, 0),
                       (_col0(ri1, ""), _col0(ri2, "")))


def _select_by_name(names, name: int, what: str, source):
    """Index of the single entry of a repeated message whose `name` equals `name`."""
    hits = tf.cast(tf.where(tf.equal(names, name))[:, 0], tf.int32)
    check = _check(tf.equal(tf.size(hits), 1), f"{what}[{schema.LASER_NAMES[name]}]",
                   "missing (or duplicated) for this laser", source)
    with tf.control_dependencies([check]):
        return tf.concat([hits, [0]], 0)[0]


def _transform(serialized, field: str, source):
    """Serialized `Transform` -> [4, 4] float64, 16 finite values."""
    sizes, (values,) = _proto(serialized, "Transform", ["transform"], [tf.float64])
    values = values[: sizes[0]]
    checks = [_check(tf.equal(sizes[0], 16), field, "transform must have 16 values", source)]
    values = _guarded(tf.concat([values, tf.zeros([16], tf.float64)], 0)[:16], checks)
    finite = _check(tf.reduce_all(tf.math.is_finite(values)), field, "non-finite values", source)
    return tf.reshape(_guarded(values, [finite]), [4, 4])


def _matrix_float_payload(raw):
    """(data [M] float32, serialized MatrixShape) of a serialized MatrixFloat.

    Fast path for the layout every writer produces (packed `data` first: tag 0x0A, varint length, little-endian
    floats; then `shape`): the floats are reinterpreted in place with decode_raw, and only the small tail is parsed
    as a proto. Any other layout goes through decode_proto.
    """
    n = tf.cast(tf.strings.length(raw), tf.int64)
    head = tf.io.decode_raw(tf.strings.join([tf.strings.substr(raw, 0, 6), "\0" * 6]), tf.uint8)[:6]  # tag+varint
    b = tf.cast(head[1:6], tf.int64)
    ends = b < 128  # varint bytes without the continuation bit
    nbytes = tf.cast(tf.argmax(tf.cast(ends, tf.int32)), tf.int64) + 1
    length = tf.reduce_sum(tf.where(tf.range(5, dtype=tf.int64) < nbytes,
                                    tf.bitwise.left_shift(tf.bitwise.bitwise_and(b, 127),
                                                          7 * tf.range(5, dtype=tf.int64)), 0))
    start = 1 + nbytes
    fast = tf.equal(head[0], 0x0A) & tf.reduce_any(ends) & (start + length <= n) & tf.equal(length % 4, 0)

    def fast_path():
        payload = tf.strings.substr(raw, start, length)
        tail = tf.strings.substr(raw, start + length, n - start - length)
        tail_sizes, (tail_data, shape_msg) = _proto(tail, "MatrixFloat", ["data", "shape"], [tf.float32, tf.string])
        data = tf.io.decode_raw(payload, tf.float32, little_endian=True)
        # A second `data` field in the tail (legal, never written in practice) is appended as the proto would.
        return tf.concat([data, tail_data[: tail_sizes[0]]], 0), shape_msg[0]

    def slow_path():
        sizes, (data, shape_msg) = _proto(raw, "MatrixFloat", ["data", "shape"], [tf.float32, tf.string])
        return data[: sizes[0]], shape_msg[0]

    return tf.cond(fast, fast_path, slow_path)


def _matrix(compressed, field: str, channels: int, source):
    """zlib -> MatrixFloat -> [H, W, channels] with a checked shape (before the reshape) and finite values."""
    raw = tf.io.decode_compressed(compressed, "ZLIB")
    data, shape_msg = _matrix_float_payload(raw)
    dims_sizes, (dims,) = _proto(shape_msg, "MatrixShape", ["dims"], [tf.int32])
    dims = tf.cast(tf.concat([dims[: dims_sizes[0]], [1, 1, 1]], 0)[:3], tf.int64)
    rank_ok = _check(tf.equal(dims_sizes[0], 3), field, "matrix shape must have 3 dims", source)
    dims_ok = _check(tf.reduce_all((dims >= 0) & (dims <= MAX_RANGE_IMAGE_DIM)), field,
                     f"declared dims must be in [0, {MAX_RANGE_IMAGE_DIM}]", source)
    with tf.control_dependencies([rank_ok, dims_ok]):
        dims = tf.identity(dims)
    checks = [
        _check(tf.equal(dims[2], channels), field, f"expected {channels} channels", source),
        _check(tf.equal(tf.size(data, out_type=tf.int64), tf.reduce_prod(dims)), field,
               "data size disagrees with its declared shape (truncated or corrupt matrix)", source),
    ]
    data = _guarded(data, checks)
    data = _guarded(data, [_check(tf.reduce_all(tf.math.is_finite(data)), field, "non-finite values", source)])
    out = tf.reshape(data, dims)
    out.set_shape([None, None, channels])
    return out


def _range_image_message(parsed: ParsedFrame, las_index, ret: int):
    """(sizes [4], [range, pose, flow] compressed bytes) of one laser return's `RangeImage`."""
    ri_msg = tf.gather(parsed.laser_returns[ret - 1], las_index)
    sizes, (range_c, pose_c, flow_c) = _proto(
        ri_msg, "RangeImage", ["range_image_compressed", "range_image_pose_compressed", "range_image_flow_compressed"],
        [tf.string] * 3)
    return sizes, range_c[0], pose_c[0], flow_c[0]


def _present_bytes(size, value, field: str, source, reason: str = "missing", kind: str = _KIND_ERROR):
    present = tf.logical_and(tf.equal(size, 1), tf.greater(tf.strings.length(value), 0))
    return _guarded(value, [_check(present, field, reason, source, kind)])


# --- Step "pose": the frame pose ---------------------------------------------------------------------------------
def frame_pose(parsed: ParsedFrame, source):
    """Step "pose": (vehicle -> world [4,4], world -> vehicle [4,4]) float64; the pose must be rigid."""
    pose = _transform(parsed.pose_msg, "pose", source)
    pose = _guarded(pose, [_check(geometry.is_rigid_pose(pose), "pose", f"not a rigid transform (finite, "
                                  f"rotation orthonormal within {geometry.POSE_RIGIDITY_TOLERANCE:g}, det > 0, bottom "
                                  f"row 0 0 0 1)", source)])
    vehicle_from_world = geometry.rigid_inverse(pose)
    return pose, vehicle_from_world


# --- Step "calibrate": extrinsic and row inclinations ----------------------------------------------------------
class LaserCalibration(NamedTuple):
    extrinsic: tf.Tensor  # [4, 4] float64, sensor -> vehicle
    num_inclinations: tf.Tensor  # [] explicit beam inclinations (0: uniform between min and max)
    inclinations: tf.Tensor  # [num_inclinations] float64, ascending (stored order)
    inclination_min: tf.Tensor
    inclination_max: tf.Tensor


def laser_calibration(parsed: ParsedFrame, laser: int, source) -> LaserCalibration:
    """Step "calibrate" (first half): the calibration entry of one laser, with finite values."""
    lname = schema.LASER_NAMES[laser]
    field = f"laser_calibrations[{lname}]"
    cal_index = _select_by_name(parsed.cal_names, laser, "laser_calibrations", source)
    extrinsic = _transform(tf.gather(parsed.cal_extrinsics, cal_index), f"{field}.extrinsic", source)
    n_incl = tf.gather(parsed.cal_num_inclinations, cal_index)
    explicit = tf.gather(parsed.cal_inclinations, cal_index)[:n_incl]
    lo, hi = tf.gather(parsed.cal_inclination_min, cal_index), tf.gather(parsed.cal_inclination_max, cal_index)
    checks = [_check(tf.reduce_all(tf.math.is_finite(explicit)), f"{field}.beam_inclinations", "non-finite values",
                     source),
              _check(tf.math.is_finite(lo) & tf.math.is_finite(hi), f"{field}.beam_inclination_min",
                     "non-finite beam_inclination_min or beam_inclination_max", source)]
    return LaserCalibration(extrinsic, n_incl, _guarded(explicit, checks), _guarded(lo, checks), hi)


def row_inclinations(cal: LaserCalibration, height, field: str, source):
    """Step "calibrate" (second half): inclination of each row of a range image of `height` rows, row 0 highest
    (`wod_format.row_inclinations` in graph)."""
    agrees = _check(tf.logical_or(tf.equal(cal.num_inclinations, 0), tf.equal(cal.num_inclinations, height)), field,
                    "range image height disagrees with the calibration's beam_inclinations", source)
    with tf.control_dependencies([agrees]):
        ascending = tf.cond(cal.num_inclinations > 0, lambda: cal.inclinations,
                            lambda: wod_format.uniform_inclinations_ascending(height, cal.inclination_min,
                                                                              cal.inclination_max, TF_OPS))
    return tf.reverse(ascending, [0])


# --- Step "to points": range image -> xyz in the vehicle frame ------------------------------------------------
def top_pixel_pose(return1_message, image_hw, source):
    """[H, W, 6] per-pixel (roll, pitch, yaw, x, y, z) vehicle -> world of the TOP lidar, from its return 1
    `_range_image_message` (return 1 serves both returns)."""
    field = "lasers[TOP].ri_return1.range_image_pose_compressed"
    sizes, _, pose_c, _ = return1_message
    pose_img = _matrix(_present_bytes(sizes[1], pose_c, field, source), field, 6, source)
    same = tf.reduce_all(tf.equal(tf.shape(pose_img)[:2], image_hw))
    return _guarded(pose_img, [_check(same, field, "shape disagrees with the range image", source)])


def range_image_to_points(range_image, cal: LaserCalibration, inclinations, vehicle_from_world=None,
                          pixel_pose=None):
    """Step "to points": (pixel_row_col [M,2] int32 of the returns (range > 0, row-major), their range image values
    [M,4], xyz [M,3] float64 in the vehicle frame). TOP passes its per-pixel pose and the world -> vehicle transform."""
    pixel_rc = tf.cast(tf.where(range_image[..., 0] > 0), tf.int32)
    values = tf.gather_nd(range_image, pixel_rc)  # [M, 4] range, intensity, elongation, no-label zone
    rng = tf.cast(values[:, 0], tf.float64)
    # Trigonometry once per column (azimuth) and per row (inclination), gathered per point.
    azimuth = wod_format.column_azimuths(tf.shape(range_image)[1], cal.extrinsic, TF_OPS)
    row, col = pixel_rc[:, 0], pixel_rc[:, 1]
    cos_incl_rng = tf.gather(tf.cos(inclinations), row) * rng
    xyz_sensor = tf.stack([tf.gather(tf.cos(azimuth), col) * cos_incl_rng,
                           tf.gather(tf.sin(azimuth), col) * cos_incl_rng,
                           tf.gather(tf.sin(inclinations), row) * rng], -1)
    xyz = tf.linalg.matmul(xyz_sensor, cal.extrinsic[:3, :3], transpose_b=True) + cal.extrinsic[:3, 3]
    if pixel_pose is not None:
        # Per-pixel rotation in float32 (the stored angles are float32; < 1e-5 m at 75 m range); the world
        # translation and everything after it in float64.
        pix = tf.gather_nd(pixel_pose, pixel_rc)  # [M, 6]
        xyz_world = tf.cast(wod_format.rotate_rpy(pix[:, :3], tf.cast(xyz, tf.float32), TF_OPS), tf.float64) + \
            tf.cast(pix[:, 3:], tf.float64)
        xyz = tf.linalg.matmul(xyz_world, vehicle_from_world[:3, :3], transpose_b=True) + vehicle_from_world[:3, 3]
    return pixel_rc, values, xyz


# --- Step "flow": scene-flow labels --------------------------------------------------------------------------------
def flow_labels(size, flow_c, image_hw, pixel_rc, field: str, source):
    """Step "flow": (flow_mps [M,3] float32, class_id [M] int32) of the returns from `range_image_flow_compressed`."""
    flow_bytes = _present_bytes(size, flow_c, field, source, MISSING_FLOW_HELP, _KIND_MISSING_FLOW)
    flow_img = _matrix(flow_bytes, field, 4, source)
    same = tf.reduce_all(tf.equal(tf.shape(flow_img)[:2], image_hw))
    flow_img = _guarded(flow_img, [_check(same, field, "shape disagrees with the range image", source)])
    values = tf.gather_nd(flow_img, pixel_rc)
    cls = values[:, 3]
    known = (tf.equal(cls, tf.round(cls)) & (cls >= schema.CLASS_NO_LABEL) & (cls <= max(schema.CLASS_NAMES)))
    cls = _guarded(cls, [_check(tf.reduce_all(known), field, f"class channel must be an integer in "
                                                        f"[{schema.CLASS_NO_LABEL}, {max(schema.CLASS_NAMES)}]",
                                source)])
    return values[:, :3], tf.cast(cls, tf.int32)


@tf.autograph.experimental.do_not_convert  # plain TF ops and static Python loops: no AutoGraph pass per dataset
def decode_frame_tensors(serialized, source, options: DecodeOptions = DecodeOptions()) -> dict[str, tf.Tensor]:
    """Graph decoder of one serialized `Frame` (usable inside `tf.data.Dataset.map`): parse, pose, and per laser
    and return calibrate, to points, flow.

    Args:
      serialized: scalar tf.string, one record.
      source: scalar tf.string naming the record in error messages, "<path> record <index>".
      options: lasers, returns, flow requirement.
    Returns:
      dict of tensors as in `ff3d_tf.schema` (decoded frame), plus pixel indices when `options.with_pixels`.
    """
    parsed = parse_frame(serialized, source)
    pose, vehicle_from_world = frame_pose(parsed, source)
    outputs: dict[str, list] = collections.defaultdict(list)
    for laser in sorted(options.laser_names):
        lname = schema.LASER_NAMES[laser]
        cal = laser_calibration(parsed, laser, source)
        las_index = _select_by_name(parsed.laser_names, laser, "lasers", source)
        messages = {ret: _range_image_message(parsed, las_index, ret)
                    for ret in sorted(set(options.returns) | ({1} if laser == 1 else set()))}
        for ret in sorted(options.returns):
            field = f"lasers[{lname}].ri_return{ret}"
            sizes, range_c, _, flow_c = messages[ret]
            range_field = f"{field}.range_image_compressed"
            ri = _matrix(_present_bytes(sizes[0], range_c, range_field, source), range_field, 4, source)
            image_hw = tf.shape(ri)[:2]
            inclinations = row_inclinations(cal, image_hw[0], range_field, source)
            pixel_pose = top_pixel_pose(messages[1], image_hw, source) if laser == 1 else None
            pixel_rc, values, xyz = range_image_to_points(ri, cal, inclinations, vehicle_from_world, pixel_pose)
            points_xyz = tf.cast(xyz, tf.float32)
            points_xyz = _guarded(points_xyz, [_check(tf.reduce_all(tf.math.is_finite(points_xyz)), field,
                                                      "points out of float32 range (range image, extrinsic or pose "
                                                      "values too large)", source)])
            m = tf.shape(pixel_rc)[0]
            if options.require_flow:
                flow_mps, class_id = flow_labels(sizes[2], flow_c, image_hw, pixel_rc,
                                                 f"{field}.range_image_flow_compressed", source)
            else:
                flow_mps, class_id = tf.zeros([m, 3]), tf.fill([m], schema.CLASS_NO_LABEL)
            outputs["points_xyz"].append(points_xyz)
            outputs["intensity"].append(values[:, 1])
            outputs["elongation"].append(values[:, 2])
            outputs["flow_mps"].append(flow_mps)
            outputs["class_id"].append(class_id)
            outputs["laser_name"].append(tf.fill([m], laser))
            if options.with_pixels:
                outputs["pixel_row_col"].append(pixel_rc)
                outputs["return_index"].append(tf.fill([m], ret))
                outputs["in_no_label_zone"].append(values[:, 3] > 0)
                outputs["range_image_hw"].append(tf.reshape(image_hw, [1, 2]))
    result = {k: tf.concat(v, 0) for k, v in outputs.items()}
    result["pose"] = pose
    result["timestamp_micros"] = parsed.timestamp_micros
    return result


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


def codec_fault(record: bytes, options: DecodeOptions = DecodeOptions()) -> tuple[str, str] | None:
    """(field, reason) of the first part of a record that the graph decoder's codecs would reject, or None.

    Checks what the codecs check, in the decoder's order, in Python: the protobuf wire format of the messages it
    parses, then each zlib-compressed matrix it reads (decompression, MatrixFloat wire format).
    """
    from waymo_open_dataset import dataset_pb2
    bad = wod_format.malformed_field(record, dataset_pb2.Frame.DESCRIPTOR, _DECODED_MESSAGES)
    if bad is not None:
        return bad
    try:
        frame = dataset_pb2.Frame.FromString(record)
    except Exception as err:  # noqa: BLE001 - protobuf's DecodeError differs between its Python and upb backends
        return "Frame", f"not a serialized Frame ({type(err).__name__})"
    lasers = {las.name: las for las in frame.lasers}
    for laser in sorted(options.laser_names):
        if laser not in lasers:
            continue
        lname = schema.LASER_NAMES[laser]
        for ret in sorted(options.returns):
            ri = getattr(lasers[laser], f"ri_return{ret}")
            names = ["range_image_compressed"] + (["range_image_pose_compressed"] if laser == 1 and ret == 1 else [])
            names += ["range_image_flow_compressed"] if options.require_flow else []
            for name in names:
                field = f"lasers[{lname}].ri_return{ret}.{name}"
                if not getattr(ri, name):
                    continue  # absent: the decoder's own check names it
                try:
                    raw = zlib.decompress(getattr(ri, name))
                except zlib.error as err:
                    return field, f"corrupt zlib stream ({err})"
                bad = wod_format.malformed_field(raw, dataset_pb2.MatrixFloat.DESCRIPTOR, ("MatrixShape",), field)
                if bad is not None:
                    return bad
    return None


def diagnose_record(record: bytes, options: DecodeOptions = DecodeOptions()) -> tuple[str, str]:
    """(field, reason) of a record the graph decoder's codecs rejected (`codec_fault`), ("Frame", ...) if no single
    field is found."""
    return codec_fault(record, options) or ("Frame", "cannot decode: the record's protobuf or zlib data is corrupt")


def _decode_error(path: str, record_index: int, err: tf.errors.OpError, record: bytes | None,
                  options: DecodeOptions) -> FrameDecodeError:
    """The FrameDecodeError of a failed decode: from the decoder's tag, else from `diagnose_record`."""
    tagged = parse_tagged_error(err.message)
    if tagged is None:
        field, reason = diagnose_record(record, options) if record is not None else ("Frame", "cannot decode")
        return FrameDecodeError(path, record_index, field, reason)
    if tagged.kind == _KIND_MISSING_FLOW:
        return MissingFlowLabelsError(path, record_index, tagged.field, tagged.reason)
    return FrameDecodeError(path, record_index, tagged.field, tagged.reason)


def decode_frame(serialized_frame: bytes, *, laser_names=schema.ALL_LASERS, returns=(1,), inference_only=False,
                 with_pixels=False, source: str = "<bytes>", record_index: int = 0) -> dict:
    """Eager helper: one serialized WOD `Frame` -> dict of NumPy arrays (keys and order: `ff3d_tf.schema`).

    Raises FrameDecodeError (MissingFlowLabelsError without labels unless `inference_only`).
    """
    options = DecodeOptions(tuple(laser_names), tuple(returns), not inference_only, with_pixels)
    try:
        return _to_numpy(_decoder(options)(tf.constant(serialized_frame),
                                           tf.constant(f"{source} record {record_index}")))
    except tf.errors.OpError as err:
        raise _decode_error(source, record_index, err, serialized_frame, options) from None


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
        except (tf.errors.DataLossError, tf.errors.InvalidArgumentError, tf.errors.OutOfRangeError):
            error = FrameDecodeError(path, index, "tfrecord", "corrupt or truncated TFRecord (a record's length or "
                                     "checksum does not match the file); nothing after it can be read")
            if not skip_bad_records:
                raise error from None
            if stats is not None:
                stats.skipped += 1
                stats.errors.append(str(error))
            _LOG.warning("skipping the rest of %s: %s", path, error)
            return
        except tf.errors.NotFoundError:
            raise FrameDecodeError(path, index, "file", "cannot open: no such file") from None
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


PIPELINE_SCAN_BUDGET_S = 60.0  # how long `pipeline_error` may re-read the input to find a record the codecs reject
_SKIP_HINT = " (data.skip_bad_records=true skips bad records)"


def locate_codec_fault(files: list[str], options: DecodeOptions = DecodeOptions(),
                       budget_s: float = PIPELINE_SCAN_BUDGET_S) -> FrameDecodeError | None:
    """The first record of `files` (in order) that cannot be framed or that the codecs reject (`codec_fault`), read
    in Python; None if all read cleanly; a FrameDecodeError with record -1 if `budget_s` ran out first."""
    deadline = time.monotonic() + budget_s
    for path in files:
        try:
            for index, record in iterate_records(path):
                fault = codec_fault(record, options)
                if fault is not None:
                    return FrameDecodeError(path, index, *fault)
                if time.monotonic() > deadline:
                    where = files[0] if len(files) == 1 else f"one of {len(files)} files ({files[0]}, ...)"
                    return FrameDecodeError(where, -1, "unknown", f"a record cannot be decoded; not found within "
                                            f"{budget_s:.0f} s (`python tools/dataset_stats.py --data_dir ...` reads "
                                            f"every record and names the bad one)")
        except FrameDecodeError as err:
            return err
    return None


def pipeline_error(err: tf.errors.OpError, files: list[str], options: DecodeOptions | None = None,
                   budget_s: float = PIPELINE_SCAN_BUDGET_S) -> FrameDecodeError | None:
    """A FrameDecodeError for an input-pipeline error raised by the decoder of `frames_dataset`, or None if the
    error did not come from decoding.

    The decoder's own checks carry their field and the record's source in their tag. A codec failure (a record that
    is not a Frame, corrupt zlib) or a truncated file reaches here without the record, so the files are read again
    in Python (`locate_codec_fault`, at most `budget_s`) to name file, record and field.
    """
    tagged = parse_tagged_error(err.message)
    if tagged is not None:
        path, index = _split_source(tagged.source)
        error_type = MissingFlowLabelsError if tagged.kind == _KIND_MISSING_FLOW else FrameDecodeError
        return error_type(path, index, tagged.field, tagged.reason + _SKIP_HINT)
    if not isinstance(err, (tf.errors.DataLossError, tf.errors.InvalidArgumentError)):
        return None  # the codecs and the TFRecord reader raise only these
    found = locate_codec_fault(list(files), options or DecodeOptions(), budget_s)
    if found is None:
        return None
    return FrameDecodeError(found.path, found.record_index, found.field, found.reason + _SKIP_HINT)


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
            return _decode_error(path, index, err, record, options)

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
