"""Reading WOD v1 segment files: TFRecord records -> decoded frames (`ff3d_tf.data.wod.wod_decode`), and what is wrong
with a record that cannot be decoded.

Every failure reaches the caller as a `FrameDecodeError` (`ff3d_tf.data.wod_errors`) naming file, record and field.
The decoder's own checks carry field and reason in their tag. A codec failure (a record that is not a protobuf,
corrupt zlib) carries none: `diagnose_record` then finds the field by re-reading the record in Python, checking what
the codecs check (`codec_fault`). A frame without lidar data gets a `NoLidarDataError` whose reason says what the frame
holds instead (`lidar_absence`). See `ff3d_tf.schema` for the decoded keys.
"""
from __future__ import annotations

import dataclasses
import logging
import time
import zlib
from typing import Iterator

import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.data.wod import wod_decode, wod_format
from ff3d_tf.data.wod.wod_decode import DecodeOptions
from ff3d_tf.data.wod_errors import (KIND_NO_LIDAR, NO_LIDAR_HELP, SOURCE_SEPARATOR, FrameDecodeError,
                                     MissingFlowLabelsError, TaggedError, parse_tagged_error, record_source,
                                     split_source)
from ff3d_tf.parallel import ordered_map

_LOG = logging.getLogger(__name__)
DECODE_WORKERS = 2  # threads of decoded_records; each decode also runs its independent ops in parallel
PIPELINE_SCAN_BUDGET_S = 60.0  # how long `pipeline_error` may re-read the input to find a record the codecs reject
_SKIP_HINT = " (data.skip_bad_records=true skips bad records)"


@dataclasses.dataclass
class ReadStats:
    """Counts of one read: records framed, decoded and skipped, and each skipped record's error."""

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


# --- Diagnosis of a record the decoder rejected --------------------------------------------------------------------
def codec_fault(record: bytes, options: DecodeOptions = DecodeOptions()) -> tuple[str, str] | None:
    """(field, reason) of the first part of a record that the graph decoder's codecs would reject, or None.

    Checks what the codecs check, in the decoder's order, in Python: the protobuf wire format of the messages it
    parses, then each zlib-compressed matrix it reads (decompression, MatrixFloat wire format).
    """
    from waymo_open_dataset import dataset_pb2
    bad = wod_format.malformed_field(record, dataset_pb2.Frame.DESCRIPTOR, wod_decode.DECODED_MESSAGES)
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


def lidar_absence(record: bytes) -> tuple[str, str] | None:
    """("lasers", reason) of a Frame without lidar data (no `lasers` entry holds a range image: the decoder's own
    test), None for any other record. The reason says what the frame holds instead, so which release it seems to
    come from, and where frames with lidar data are."""
    from waymo_open_dataset import dataset_pb2
    try:
        frame = dataset_pb2.Frame.FromString(record)
    except Exception:  # noqa: BLE001 - not a Frame: `codec_fault` names that
        return None
    if any(las.ri_return1.ByteSize() or las.ri_return2.ByteSize() for las in frame.lasers):
        return None
    what = "no `lasers`" if not frame.lasers else f"{len(frame.lasers)} `lasers` entries, none with a range image"
    if frame.images:
        origin = (f"it has camera images ({len(frame.images)}) but no lidar, so it seems to come from a camera-only "
                  f"WOD release (e.g. the end-to-end driving release) or a copy without the lidar data, not from the "
                  f"perception release")
    elif frame.lasers or frame.context.laser_calibrations:
        origin = ("it has lidar calibrations or laser entries but no range images, so it seems to be a copy without "
                  "the lidar data")
    else:
        origin = "it has no camera images either, so it does not seem to be a perception frame (another release)"
    return "lasers", f"the frame has no lidar data ({what}): {origin}. {NO_LIDAR_HELP}"


def diagnose_record(record: bytes, options: DecodeOptions = DecodeOptions()) -> tuple[str, str]:
    """(field, reason) of a record the graph decoder rejected without a tag: its codec fault (`codec_fault`), else
    its lack of lidar data (`lidar_absence`), else ("Frame", ...) if no single field is found."""
    return (codec_fault(record, options) or lidar_absence(record)
            or ("Frame", "cannot decode: the record's protobuf or zlib data is corrupt"))


def _tagged_error(tagged: TaggedError, record: bytes | None, path: str | None = None, record_index: int | None = None,
                  hint: str = "") -> FrameDecodeError:
    """The error of a decoder tag; a frame without lidar data gets `lidar_absence`'s reason when its record is at
    hand."""
    found = lidar_absence(record) if tagged.kind == KIND_NO_LIDAR and record is not None else None
    return tagged.error(path, record_index, (found[1] if found else tagged.reason) + hint)


def _decode_error(path: str, record_index: int, err: tf.errors.OpError, record: bytes | None,
                  options: DecodeOptions) -> FrameDecodeError:
    """The FrameDecodeError of a failed decode: from the decoder's tag, else from `diagnose_record`."""
    tagged = parse_tagged_error(err.message)
    if tagged is not None:
        return _tagged_error(tagged, record, path, record_index)
    field, reason = diagnose_record(record, options) if record is not None else ("Frame", "cannot decode")
    return FrameDecodeError(path, record_index, field, reason)


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


def _record_at(path: str, record_index: int) -> bytes | None:
    """Record `record_index` of a file, read again; None if the file cannot be read that far."""
    try:
        return next((record for index, record in iterate_records(path) if index == record_index), None)
    except FrameDecodeError:
        return None


def pipeline_error(err: tf.errors.OpError, files: list[str], options: DecodeOptions | None = None,
                   budget_s: float = PIPELINE_SCAN_BUDGET_S) -> FrameDecodeError | None:
    """A FrameDecodeError for an input-pipeline error raised by the decoder of `frames_dataset`, or None if the
    error did not come from decoding.

    The decoder's own checks carry their field and the record's source in their tag (a frame without lidar data is
    read again for its reason). A codec failure (a record that is not a Frame, corrupt zlib) or a truncated file
    reaches here without the record, so the files are read again in Python (`locate_codec_fault`, at most
    `budget_s`) to name file, record and field.
    """
    tagged = parse_tagged_error(err.message)
    if tagged is not None:
        record = _record_at(*split_source(tagged.source)) if tagged.kind == KIND_NO_LIDAR else None
        return _tagged_error(tagged, record, hint=_SKIP_HINT)
    if not isinstance(err, (tf.errors.DataLossError, tf.errors.InvalidArgumentError)):
        return None  # the codecs and the TFRecord reader raise only these
    found = locate_codec_fault(list(files), options or DecodeOptions(), budget_s)
    if found is None:
        return None
    return FrameDecodeError(found.path, found.record_index, found.field, found.reason + _SKIP_HINT)


# --- Decoding --------------------------------------------------------------------------------------------------------
def _to_numpy(tensors: dict) -> dict:
    out = {k: v.numpy() for k, v in tensors.items()}
    out["timestamp_micros"] = int(out["timestamp_micros"])
    return out


def decode_frame(serialized_frame: bytes, *, laser_names=schema.ALL_LASERS, returns=(1,), inference_only=False,
                 with_pixels=False, source: str = "<bytes>", record_index: int = 0) -> dict:
    """Eager helper: one serialized WOD `Frame` -> dict of NumPy arrays (keys and order: `ff3d_tf.schema`).

    Raises FrameDecodeError (MissingFlowLabelsError without labels unless `inference_only`, NoLidarDataError without
    lidar data).
    """
    options = DecodeOptions(tuple(laser_names), tuple(returns), not inference_only, with_pixels)
    try:
        return _to_numpy(wod_decode.traced_decoder(options)(tf.constant(serialized_frame),
                                                            tf.constant(record_source(source, record_index))))
    except tf.errors.OpError as err:
        raise _decode_error(source, record_index, err, serialized_frame, options) from None


def frames_dataset(path: str, options: DecodeOptions = DecodeOptions(), skip_bad_records: bool = False
                   ) -> tf.data.Dataset:
    """(record_index, decoded frame) of one file, decoded in graph in parallel, in file order.

    A bad record raises from the iterator (see `pipeline_error` for a FrameDecodeError), or with `skip_bad_records`
    is dropped with a warning (a truncated file ends there). The map calls the decoder traced once per process
    (`wod_decode.traced_decoder`): building the dataset costs no tracing.
    """
    decoder = wod_decode.traced_decoder(options)

    def decode(index, record):
        return index, decoder(record, tf.strings.join([path, SOURCE_SEPARATOR, tf.strings.as_string(index)]))

    records = tf.data.TFRecordDataset(path)
    if skip_bad_records:
        records = records.ignore_errors(log_warning=True)
    frames = records.enumerate().map(decode, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    return frames.ignore_errors(log_warning=True) if skip_bad_records else frames


def decoded_records(path: str, options: DecodeOptions = DecodeOptions(), skip_bad_records: bool = False,
                    stats: ReadStats | None = None, workers: int = DECODE_WORKERS
                    ) -> Iterator[tuple[int, bytes, dict]]:
    """(record_index, record bytes, decoded frame as NumPy) of one file, in file order.

    `workers` threads (`ff3d_tf.parallel.ordered_map`) call the decoder traced once per process, so a new file costs
    no tracing or graph optimisation (a per-file `tf.data` map costs about 4 s of both). A bad record raises a
    FrameDecodeError naming file, record and field, or (skip_bad_records) is counted and reading goes on with the
    next record. A corrupt or truncated TFRecord ends the file (nothing after it can be framed), raised after the
    records before it. Frames without scene-flow labels always raise MissingFlowLabelsError when labels are required
    (skipping them would silently drop a whole segment).
    """
    stats = stats if stats is not None else ReadStats()
    decoder = wod_decode.traced_decoder(options)

    def decode(item: tuple[int, bytes]):
        index, record = item
        try:
            return _to_numpy(decoder(tf.constant(record), tf.constant(record_source(path, index))))
        except tf.errors.OpError as err:
            return _decode_error(path, index, err, record, options)

    for (index, record), result in ordered_map(decode, iterate_records(path, stats, skip_bad_records), workers):
        if isinstance(result, FrameDecodeError):
            if not skip_bad_records or isinstance(result, MissingFlowLabelsError):
                raise result
            stats.skipped += 1
            stats.errors.append(str(result))
            _LOG.warning("skipping %s", result)
            continue
        stats.decoded += 1
        yield index, record, result


def read_frames(paths, *, laser_names=schema.ALL_LASERS, returns=(1,), inference_only=False, with_pixels=False,
                skip_bad_records=False, stats: ReadStats | None = None) -> Iterator[tuple[str, int, dict]]:
    """Yields (path, record_index, decoded frame) over files; bad records raise, or are skipped and counted."""
    options = DecodeOptions(tuple(laser_names), tuple(returns), not inference_only, with_pixels)
    for path in ([paths] if isinstance(paths, str) else paths):
        for index, _, frame in decoded_records(path, options, skip_bad_records, stats):
            yield path, index, frame
