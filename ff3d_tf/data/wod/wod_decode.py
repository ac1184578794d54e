"""WOD v1 `Frame` decoding in graph: range images (+ scene-flow labels) of the five lidars -> points in the vehicle frame.

The conversion follows the official `frame_utils.convert_range_image_to_point_cloud` conventions (the polar geometry
of `ff3d_tf.data.wod.wod_format`: column azimuths, reversed inclinations, extrinsic, TOP per-pixel pose correction) but
masks the returns first, so it costs a fraction of the official path. Geometry runs in float64 (per-pixel TOP
rotations in float32, as their angles are stored) and is cast to float32 at the end. Range image channels are read by
their names in `ff3d_tf.schema`.

`decode_frame_tensors` runs five named steps: parse (protos), pose (frame pose), calibrate (extrinsic, inclinations),
to points (range image -> xyz) and flow (labels), each a function of this module. Every check is a tagged assertion
(`ff3d_tf.data.wod_errors.check`), made before any allocation of a declared size. See `ff3d_tf.schema` for the
decoded keys; `ff3d_tf.data.wod.waymo` reads files with it.
"""
from __future__ import annotations

import collections
import dataclasses
from typing import NamedTuple

import tensorflow as tf

from ff3d_tf import geometry, schema
from ff3d_tf.data.wod import wod_format
from ff3d_tf.data.wod_errors import (KIND_ERROR, KIND_MISSING_FLOW, KIND_NO_LIDAR, MISSING_FLOW_HELP, NO_LIDAR_HELP,
                                    check)
from ff3d_tf.data.wod.wod_format import descriptor_source

_PKG = "waymo.open_dataset."
# Declared range image sizes beyond these are refused before anything of that size is allocated (a WOD TOP range
# image is 64 x 2650; a decompressed matrix is never reshaped to dims its data does not fill).
MAX_RANGE_IMAGE_DIM = 1 << 16
# Messages the decoder parses with decode_proto (what the reader's Python diagnosis descends into).
DECODED_MESSAGES = ("Frame", "Context", "LaserCalibration", "Laser", "RangeImage", "Transform")
TF_OPS = wod_format.ArrayOps(to_f64=lambda x: tf.cast(x, tf.float64),
                             arange_f64=lambda n: tf.range(tf.cast(n, tf.float64)), atan2=tf.atan2, cos=tf.cos,
                             sin=tf.sin, stack_last=lambda xs: tf.stack(xs, -1))
_RANGE, _INTENSITY, _ELONGATION, _NLZ = (schema.RANGE_CHANNEL[c] for c in ("range", "intensity", "elongation",
                                                                          "is_in_nlz"))


@dataclasses.dataclass(frozen=True)
class DecodeOptions:
    laser_names: tuple[int, ...] = schema.ALL_LASERS
    returns: tuple[int, ...] = (1,)
    require_flow: bool = True  # False: frames without labels decode with flow 0 and class -1 (inference input)
    # Also return pixel_row_col [N,2], return_index [N], in_no_label_zone [N] and range_image_hw [L*R,2] (height,
    # width of each decoded range image, sorted by laser then return): what label writers need.
    with_pixels: bool = False

    def __post_init__(self):
        problem = schema.lidar_selection_problem(self.laser_names, self.returns)
        if problem is not None:
            raise ValueError(problem)


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
    """decode_proto over a [K] list of messages -> sizes [K, F], values [K, max_count] each, also when K is 0
    (decode_proto refuses an empty batch: one empty message is decoded after the list and dropped)."""
    k = tf.shape(serialized_list)[0]
    sizes, values = tf.io.decode_proto(tf.concat([serialized_list, [""]], 0), _PKG + message, fields, types,
                                       descriptor_source=descriptor_source())
    return sizes[:k], [v[:k] for v in values]


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
    """Step "parse": the Frame, its Context and the repeated calibrations and lasers (no range image yet). A frame
    without lidar data (no `lasers` entry holding a range image) fails here, before any other check."""
    sizes, (context, timestamp, pose_msg, lasers) = _proto(
        serialized, "Frame", ["context", "timestamp_micros", "pose", "lasers"],
        [tf.string, tf.int64, tf.string, tf.string])
    _, (las_names, ri1, ri2) = _decode_repeated(lasers[: sizes[3]], "Laser", ["name", "ri_return1", "ri_return2"],
                                                [tf.int32, tf.string, tf.string])
    ri1, ri2 = _col0(ri1, ""), _col0(ri2, "")
    has_lidar = tf.reduce_any((tf.strings.length(ri1) > 0) | (tf.strings.length(ri2) > 0))
    lidar = [check(has_lidar, "lasers", f"no lidar data (no `lasers` entry holds a range image). {NO_LIDAR_HELP}",
                   source, KIND_NO_LIDAR)]
    with tf.control_dependencies(lidar):  # every other check comes after this one
        checks = [check(tf.equal(sizes[0], 1), "context", "missing", source),
                  check(tf.equal(sizes[2], 1), "pose", "missing", source)]
    context = _guarded(context[:1], checks)[0]
    csizes, (calibs,) = _proto(context, "Context", ["laser_calibrations"], [tf.string])
    cal_sizes, (cal_names, incl, incl_min, incl_max, extrinsics) = _decode_repeated(
        calibs[: csizes[0]], "LaserCalibration",
        ["name", "beam_inclinations", "beam_inclination_min", "beam_inclination_max", "extrinsic"],
        [tf.int32, tf.float64, tf.float64, tf.float64, tf.string])
    return ParsedFrame(timestamp[0], _guarded(pose_msg[0], checks), _col0(cal_names, 0), cal_sizes[:, 1], incl,
                       _col0(incl_min, 0.0), _col0(incl_max, 0.0), _col0(extrinsics, ""),
                       _guarded(_col0(las_names, 0), lidar), (ri1, ri2))


def _select_by_name(names, name: int, what: str, source):
    """Index of the single entry of a repeated message whose `name` equals `name`."""
    hits = tf.cast(tf.where(tf.equal(names, name))[:, 0], tf.int32)
    unique = check(tf.equal(tf.size(hits), 1), f"{what}[{schema.LASER_NAMES[name]}]",
                   "missing (or duplicated) for this laser", source)
    with tf.control_dependencies([unique]):
        return tf.concat([hits, [0]], 0)[0]


def _transform(serialized, field: str, source):
    """Serialized `Transform` -> [4, 4] float64, 16 finite values."""
    sizes, (values,) = _proto(serialized, "Transform", ["transform"], [tf.float64])
    values = values[: sizes[0]]
    checks = [check(tf.equal(sizes[0], 16), field, "transform must have 16 values", source)]
    values = _guarded(tf.concat([values, tf.zeros([16], tf.float64)], 0)[:16], checks)
    finite = check(tf.reduce_all(tf.math.is_finite(values)), field, "non-finite values", source)
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
    rank_ok = check(tf.equal(dims_sizes[0], 3), field, "matrix shape must have 3 dims", source)
    dims_ok = check(tf.reduce_all((dims >= 0) & (dims <= MAX_RANGE_IMAGE_DIM)), field,
                     f"declared dims must be in [0, {MAX_RANGE_IMAGE_DIM}]", source)
    with tf.control_dependencies([rank_ok, dims_ok]):
        dims = tf.identity(dims)
    checks = [
        check(tf.equal(dims[2], channels), field, f"expected {channels} channels", source),
        check(tf.equal(tf.size(data, out_type=tf.int64), tf.reduce_prod(dims)), field,
               "data size disagrees with its declared shape (truncated or corrupt matrix)", source),
    ]
    data = _guarded(data, checks)
    data = _guarded(data, [check(tf.reduce_all(tf.math.is_finite(data)), field, "non-finite values", source)])
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


def _present_bytes(size, value, field: str, source, reason: str = "missing", kind: str = KIND_ERROR):
    present = tf.logical_and(tf.equal(size, 1), tf.greater(tf.strings.length(value), 0))
    return _guarded(value, [check(present, field, reason, source, kind)])


# --- Step "pose": the frame pose ---------------------------------------------------------------------------------
def frame_pose(parsed: ParsedFrame, source):
    """Step "pose": (vehicle -> world [4,4], world -> vehicle [4,4]) float64; the pose must be rigid."""
    pose = _transform(parsed.pose_msg, "pose", source)
    pose = _guarded(pose, [check(geometry.is_rigid_pose(pose), "pose", f"not a rigid transform (finite, "
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
    checks = [check(tf.reduce_all(tf.math.is_finite(explicit)), f"{field}.beam_inclinations", "non-finite values",
                     source),
              check(tf.math.is_finite(lo) & tf.math.is_finite(hi), f"{field}.beam_inclination_min",
                     "non-finite beam_inclination_min or beam_inclination_max", source)]
    return LaserCalibration(extrinsic, n_incl, _guarded(explicit, checks), _guarded(lo, checks), hi)


def row_inclinations(cal: LaserCalibration, height, field: str, source):
    """Step "calibrate" (second half): inclination of each row of a range image of `height` rows, row 0 highest
    (`wod_format.row_inclinations` in graph)."""
    agrees = check(tf.logical_or(tf.equal(cal.num_inclinations, 0), tf.equal(cal.num_inclinations, height)), field,
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
    pose_img = _matrix(_present_bytes(sizes[1], pose_c, field, source), field, len(schema.TOP_POSE_CHANNELS), source)
    same = tf.reduce_all(tf.equal(tf.shape(pose_img)[:2], image_hw))
    return _guarded(pose_img, [check(same, field, "shape disagrees with the range image", source)])


def range_image_to_points(range_image, cal: LaserCalibration, inclinations, vehicle_from_world=None,
                          pixel_pose=None):
    """Step "to points": (pixel_row_col [M,2] int32 of the returns (range > 0, row-major), their range image values
    [M,4], xyz [M,3] float64 in the vehicle frame). TOP passes its per-pixel pose and the world -> vehicle transform."""
    pixel_rc = tf.cast(tf.where(range_image[..., _RANGE] > 0), tf.int32)
    values = tf.gather_nd(range_image, pixel_rc)  # [M, 4] schema.RANGE_CHANNELS
    rng = tf.cast(values[:, _RANGE], tf.float64)
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
        xyz_world = tf.cast(wod_format.rotate_rpy(pix[:, schema.TOP_POSE_ROTATION], tf.cast(xyz, tf.float32), TF_OPS),
                            tf.float64) + tf.cast(pix[:, schema.TOP_POSE_TRANSLATION], tf.float64)
        xyz = tf.linalg.matmul(xyz_world, vehicle_from_world[:3, :3], transpose_b=True) + vehicle_from_world[:3, 3]
    return pixel_rc, values, xyz


# --- Step "flow": scene-flow labels --------------------------------------------------------------------------------
def flow_labels(size, flow_c, image_hw, pixel_rc, field: str, source):
    """Step "flow": (flow_mps [M,3] float32, class_id [M] int32) of the returns from `range_image_flow_compressed`."""
    flow_bytes = _present_bytes(size, flow_c, field, source, MISSING_FLOW_HELP, KIND_MISSING_FLOW)
    flow_img = _matrix(flow_bytes, field, len(schema.FLOW_CHANNELS), source)
    same = tf.reduce_all(tf.equal(tf.shape(flow_img)[:2], image_hw))
    flow_img = _guarded(flow_img, [check(same, field, "shape disagrees with the range image", source)])
    values = tf.gather_nd(flow_img, pixel_rc)
    cls = values[:, schema.FLOW_CHANNEL["class"]]
    known = (tf.equal(cls, tf.round(cls)) & (cls >= schema.CLASS_NO_LABEL) & (cls <= max(schema.CLASS_NAMES)))
    cls = _guarded(cls, [check(tf.reduce_all(known), field, f"class channel must be an integer in "
                                                        f"[{schema.CLASS_NO_LABEL}, {max(schema.CLASS_NAMES)}]",
                                source)])
    return values[:, schema.FLOW_VELOCITY], tf.cast(cls, tf.int32)


@tf.autograph.experimental.do_not_convert  # plain TF ops and static Python loops: no AutoGraph pass per dataset
def decode_frame_tensors(serialized, source, options: DecodeOptions = DecodeOptions()) -> dict[str, tf.Tensor]:
    """Graph decoder of one serialized `Frame` (usable inside `tf.data.Dataset.map`): parse, pose, and per laser
    and return calibrate, to points, flow.

    Args:
      serialized: scalar tf.string, one record.
      source: scalar tf.string naming the record in error messages (`wod_errors.record_source`).
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
            range_bytes = _present_bytes(sizes[0], range_c, range_field, source)
            ri = _matrix(range_bytes, range_field, len(schema.RANGE_CHANNELS), source)
            image_hw = tf.shape(ri)[:2]
            inclinations = row_inclinations(cal, image_hw[0], range_field, source)
            pixel_pose = top_pixel_pose(messages[1], image_hw, source) if laser == 1 else None
            pixel_rc, values, xyz = range_image_to_points(ri, cal, inclinations, vehicle_from_world, pixel_pose)
            points_xyz = tf.cast(xyz, tf.float32)
            points_xyz = _guarded(points_xyz, [check(tf.reduce_all(tf.math.is_finite(points_xyz)), field,
                                                      "points out of float32 range (range image, extrinsic or pose "
                                                      "values too large)", source)])
            m = tf.shape(pixel_rc)[0]
            if options.require_flow:
                flow_mps, class_id = flow_labels(sizes[2], flow_c, image_hw, pixel_rc,
                                                 f"{field}.range_image_flow_compressed", source)
            else:
                flow_mps, class_id = tf.zeros([m, 3]), tf.fill([m], schema.CLASS_NO_LABEL)
            outputs["points_xyz"].append(points_xyz)
            outputs["intensity"].append(values[:, _INTENSITY])
            outputs["elongation"].append(values[:, _ELONGATION])
            outputs["flow_mps"].append(flow_mps)
            outputs["class_id"].append(class_id)
            outputs["laser_name"].append(tf.fill([m], laser))
            if options.with_pixels:
                outputs["pixel_row_col"].append(pixel_rc)
                outputs["return_index"].append(tf.fill([m], ret))
                outputs["in_no_label_zone"].append(values[:, _NLZ] > 0)
                outputs["range_image_hw"].append(tf.reshape(image_hw, [1, 2]))
    result = {k: tf.concat(v, 0) for k, v in outputs.items()}
    result["pose"] = pose
    result["timestamp_micros"] = parsed.timestamp_micros
    return result


_DECODERS: dict[DecodeOptions, tf.types.experimental.ConcreteFunction] = {}


def traced_decoder(options: DecodeOptions) -> tf.types.experimental.ConcreteFunction:
    """`decode_frame_tensors` of `options` as a concrete function (serialized, source) -> dict, traced once per
    process and options: every reader path calls this one, so a new file costs no tracing."""
    if options not in _DECODERS:
        fn = tf.function(lambda s, src: decode_frame_tensors(s, src, options))
        _DECODERS[options] = fn.get_concrete_function(tf.TensorSpec([], tf.string), tf.TensorSpec([], tf.string))
    return _DECODERS[options]


