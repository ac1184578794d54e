"""Bootstrap scene-flow labels for whole WOD segments (paper Sec. 3), as an Apache Beam pipeline.

One Beam element per segment file: its frames are read in order, every selected lidar/return gets flow from the
frame's `laser_labels` and the previous frame's (`ff3d_tf.labels.box_flow.bootstrap_flow`), and the frames are written
again with `range_image_flow_compressed` filled in the release's format ([H,W,4]: vx, vy, vz in m/s, class), so the
reader and training take them unchanged. Points in no-label zones (range image channel is_in_nlz > 0) get class -1;
pixels without a return hold zeros and class -1. The first frame of a segment has no t-1 boxes: its object points get
class -1.

The range image format has no place for the box each point belongs to; `run_wod_records_job` writes the pair records
of labelled segments (`ff3d_tf.data.wod.write_records`) with that box (`instance_id_t0`, from the frames'
`laser_labels` by the rule the labels came from), for DeltaFlow's instance term (`ff3d_tf.model.losses`).
"""
from __future__ import annotations

import ctypes
import functools
import logging
import os
import time

import numpy as np

from ff3d_tf import schema
from ff3d_tf.labels.box_flow import boxes_from_wod_labels, bootstrap_flow, points_in_boxes
from ff3d_tf.data import beam_job, pair_records
from ff3d_tf.data.wod_errors import FrameDecodeError
from ff3d_tf.data.wod import waymo, write_records
from ff3d_tf.data.wod.wod_decode import DecodeOptions
from ff3d_tf.data.wod.wod_format import encode_matrix
from ff3d_tf.parallel import ordered_map

_LOG = logging.getLogger(__name__)
ANNOTATION_THREADS = 1  # one labelling thread beside the two decoder threads (benchmarks/annotation_cpu.json)
COUNT_KEYS = (("frames", "points", "invalid_points") + tuple(schema.CLASS_NAMES[c] for c in sorted(schema.CLASS_NAMES))
              + ("no_label_zone_points",))


def keep_freed_memory() -> bool:
    """Asks glibc to serve arrays up to 32 MB from its heap and to keep freed memory (mallopt); returns success.

    Labelling allocates and frees arrays of several MB per frame; by default glibc maps and unmaps each one, and the
    page faults then dominate the labelling time (benchmarks/annotation_cpu.json). The cost is that the
    process keeps its peak heap. Process-wide and idempotent; a no-op off glibc.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(libc.mallopt(m_mmap_threshold, 32 << 20) and libc.mallopt(m_trim_threshold, 1 << 30))


def decode_options(laser_names=schema.ALL_LASERS, returns=(1, 2)) -> DecodeOptions:
    return DecodeOptions(tuple(sorted(laser_names)), tuple(sorted(returns)), require_flow=False, with_pixels=True)


def annotate_frame(frame, decoded: dict, prev: tuple | None, laser_names=schema.ALL_LASERS, returns=(1, 2),
                   boxes: dict | None = None) -> tuple[bytes, dict]:
    """Fills `range_image_flow_compressed` of one parsed Frame from its decoded points (`decode_options`).

    prev: (boxes, pose, timestamp_micros) of the previous frame, or None. Returns (serialized frame, counts).
    """
    boxes = boxes_from_wod_labels(frame.laser_labels) if boxes is None else boxes
    if prev is None:
        # No t-1 frame: object points are unlabelled (class -1); background stays 0.
        flow, cls = bootstrap_flow(decoded["points_xyz"], boxes, {"track_id": np.zeros(0, str)}, decoded["pose"],
                                   decoded["pose"], 0.1)
    else:
        prev_boxes, prev_pose, prev_ts = prev
        dt_s = (decoded["timestamp_micros"] - prev_ts) * 1e-6
        flow, cls = bootstrap_flow(decoded["points_xyz"], boxes, prev_boxes, decoded["pose"], prev_pose, dt_s)
    nlz = decoded["in_no_label_zone"]
    if nlz.any():
        cls[nlz] = schema.CLASS_NO_LABEL
        flow[nlz] = 0.0
    counts = dict.fromkeys(COUNT_KEYS, 0)
    counts["frames"], counts["points"] = 1, len(cls)
    per_class = np.bincount(cls + 1, minlength=6)  # classes -1..4
    counts["invalid_points"] = int(per_class[0])
    counts["no_label_zone_points"] = int(nlz.sum())
    for c, name in schema.CLASS_NAMES.items():
        counts[name] = int(per_class[c + 1])
    labels = np.empty((len(cls), len(schema.FLOW_CHANNELS)), np.float32)  # one row per point: the image's channels
    labels[:, schema.FLOW_VELOCITY] = flow
    labels[:, schema.FLOW_CHANNEL["class"]] = cls
    lasers = {laser.name: laser for laser in frame.lasers}
    shapes = iter(decoded["range_image_hw"])  # decoder order: sorted lasers, then sorted returns
    # Points come ordered by laser, then return: each range image's points are one contiguous slice.
    key = decoded["laser_name"].astype(np.int64) * 4 + decoded["return_index"]
    for name in sorted(laser_names):
        for ret in sorted(returns):
            height, width = (int(v) for v in next(shapes))
            ri = lasers[name].ri_return1 if ret == 1 else lasers[name].ri_return2
            lo, hi = np.searchsorted(key, name * 4 + ret, "left"), np.searchsorted(key, name * 4 + ret, "right")
            if hi == lo:
                ri.range_image_flow_compressed = _empty_flow_image(height, width)
                continue
            image = _empty_flow_array(height, width).copy()
            rc = decoded["pixel_row_col"][lo:hi]
            image.reshape(-1, len(schema.FLOW_CHANNELS))[rc[:, 0] * width + rc[:, 1]] = labels[lo:hi]
            ri.range_image_flow_compressed = encode_matrix(image)
    return frame.SerializeToString(), counts


@functools.lru_cache(maxsize=16)
def _empty_flow_array(height: int, width: int) -> np.ndarray:
    """Flow image of a range image without returns: zeros, class -1 (read-only; copy before writing)."""
    image = np.zeros((height, width, len(schema.FLOW_CHANNELS)), np.float32)
    image[..., schema.FLOW_CHANNEL["class"]] = schema.CLASS_NO_LABEL
    image.flags.writeable = False
    return image


@functools.lru_cache(maxsize=16)
def _empty_flow_image(height: int, width: int) -> bytes:
    """Encoded `_empty_flow_array`, made once per size."""
    return encode_matrix(_empty_flow_array(height, width))


def _frames_to_label(in_path: str, options: DecodeOptions, skip_bad_records: bool, stats: waymo.ReadStats):
    """(index, Frame, decoded, boxes, prev) per decoded record, in file order; `prev` is the previous frame's
    (boxes, pose, timestamp), or None after a skipped record (that frame has no valid t-1)."""
    from waymo_open_dataset import dataset_pb2
    prev, last_index = None, -1
    for index, record, decoded in waymo.decoded_records(in_path, options, skip_bad_records, stats):
        if index != last_index + 1:
            prev = None
        last_index = index
        frame = dataset_pb2.Frame.FromString(record)
        boxes = boxes_from_wod_labels(frame.laser_labels)
        yield index, frame, decoded, boxes, prev
        prev = (boxes, decoded["pose"], decoded["timestamp_micros"])


def _log_progress(in_path: str, frames_done: int, t0: float, first_frame_seconds: float) -> None:
    elapsed = time.time() - t0
    _LOG.info("%s: %d frames, %.1f frames/s (%.1f after the first frame)", os.path.basename(in_path), frames_done,
              frames_done / elapsed, (frames_done - 1) / max(elapsed - first_frame_seconds, 1e-9))


def annotate_segment(in_path: str, out_path: str, laser_names=schema.ALL_LASERS, returns=(1, 2),
                     skip_bad_records: bool = False) -> dict:
    """Annotates one segment file into `out_path` (written atomically; an existing output is kept: resumable).

    Returns counts (COUNT_KEYS, skipped_records), `seconds` and `first_frame_seconds` (start-up: decoder tracing on
    the first segment of a process, and the pipeline filling).
    """
    import tensorflow as tf

    keep_freed_memory()
    totals = dict.fromkeys(COUNT_KEYS, 0)
    totals["skipped_records"] = 0
    gfile = tf.io.gfile  # local paths and gs:// alike (Beam workers on a cloud runner)
    if gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        totals["already_done"] = 1
        return totals
    gfile.makedirs(os.path.dirname(out_path) or ".")
    tmp = out_path + ".partial"
    t0 = time.time()
    stats = waymo.ReadStats()

    def label(item):
        _, frame, decoded, boxes, prev = item
        return annotate_frame(frame, decoded, prev, laser_names, returns, boxes)

    # Records decode on the reader's threads while one worker thread labels and re-encodes earlier ones (NumPy and
    # zlib release the GIL). A frame needs only its own record and the previous frame's boxes and pose, so frames
    # are independent; outputs are written in record order.
    items = _frames_to_label(in_path, decode_options(laser_names, returns), skip_bad_records, stats)
    try:
        with tf.io.TFRecordWriter(tmp) as writer:
            for frames_done, (_, (data, counts)) in enumerate(
                    ordered_map(label, items, ANNOTATION_THREADS, 2 * ANNOTATION_THREADS), 1):
                writer.write(data)
                totals.setdefault("first_frame_seconds", time.time() - t0)
                for k, v in counts.items():
                    totals[k] += v
                if frames_done % 10 == 0:
                    _log_progress(in_path, frames_done, t0, totals["first_frame_seconds"])
    except BaseException:
        if gfile.exists(tmp):
            gfile.remove(tmp)  # nothing half-written is left to be mistaken for output
        raise
    totals["skipped_records"] = stats.skipped
    gfile.rename(tmp, out_path, overwrite=True)
    totals["seconds"] = time.time() - t0
    totals.setdefault("first_frame_seconds", totals["seconds"])  # no frame at all
    return totals


def _annotate_into(out_dir: str, laser_names, returns, skip_bad_records: bool, path: str) -> dict:
    return annotate_segment(path, os.path.join(out_dir, os.path.basename(path)), laser_names, returns,
                            skip_bad_records)


def run_pipeline(input_files: list[str], out_dir: str, beam_args: list[str] | None = None,
                 laser_names=schema.ALL_LASERS, returns=(1, 2), skip_bad_records: bool = False) -> dict:
    """Beam pipeline (`ff3d_tf.data.beam_job`: one element per segment, resumable); returns the summed counts.

    `--direct_num_workers=N --direct_running_mode=multi_processing` annotates N segments at once on one machine.
    """
    return beam_job.run_per_input(
        list(input_files), functools.partial(_annotate_into, out_dir, laser_names, returns, skip_bad_records),
        out_dir, "annotate_flow", beam_args, result_name="annotation_counts.json")


# The extras `run_wod_records_job` adds to WOD pair records.
WOD_RECORD_EXTRAS = ("instance_id_t0",)


def instance_ids_of_segment(segment_path: str, skip_bad_records: bool = False):
    """fn(pair example, NumPy) -> {"instance_id_t0": int32 [N0]}: the labelled box each t0 point is in, -1 for none.

    The boxes are the t0 frame's `laser_labels` (types 1..4, `boxes_from_wod_labels`), numbered by their place among
    them, and the test is `bootstrap_flow`'s (`points_in_boxes`, the same tolerance): each point's id is the box its
    flow and class come from. The segment's labels are read once here (a frame per record, matched to a pair by its
    t0 timestamp); a record that does not parse is skipped with `skip_bad_records` (its frame gives no pair).
    """
    from google.protobuf.message import DecodeError
    from waymo_open_dataset import dataset_pb2
    boxes_at = {}
    for index, record in waymo.iterate_records(segment_path, skip_bad_records=skip_bad_records):
        try:
            frame = dataset_pb2.Frame.FromString(record)
        except DecodeError as err:
            if skip_bad_records:
                continue
            raise FrameDecodeError(segment_path, index, "record", f"not a Frame ({err})") from None
        boxes_at[int(frame.timestamp_micros)] = boxes_from_wod_labels(frame.laser_labels)

    def instance_ids(example: dict) -> dict:
        micros = int(example[pair_records.TIMESTAMP_KEY]) // 1000
        if micros not in boxes_at:
            raise ValueError(f"{segment_path}: no frame at {micros} us for the pair's t0 cloud")
        return {"instance_id_t0": points_in_boxes(example["points_xyz_t0"], boxes_at[micros])}

    return instance_ids


def run_wod_records_job(files: list[str], out_dir: str, cfg, precision: str = "exact", compression: str = "none",
                        beam_args: list[str] | None = None, written_by: str = "") -> dict:
    """Pair records of labelled WOD segments (`write_records.run_wod_job`) that also hold `WOD_RECORD_EXTRAS`
    (`instance_ids_of_segment`)."""
    add_extras = functools.partial(instance_ids_of_segment, skip_bad_records=cfg.data.skip_bad_records)
    return write_records.run_wod_job(files, out_dir, cfg, precision, compression, beam_args, written_by,
                                     human_labels=True, extras=WOD_RECORD_EXTRAS, add_extras=add_extras)
