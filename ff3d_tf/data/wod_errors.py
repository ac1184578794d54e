"""The WOD reader's errors and its tag protocol: how a failed in-graph check names its field and record.

Every check of the graph decoder (`ff3d_tf.data.wod.wod_decode`) is a `tf.debugging.Assert` written by `check`: its
message holds a tag `<<FRAME_DECODE_ERROR|field|kind|reason|source|END_FRAME_DECODE_ERROR>>`, the source being
`record_source(path, index)`. `parse_tagged_error` reads the tag back out of whatever TensorFlow wraps around it, and
`TaggedError.error` turns it into the error of its kind; nothing parses TensorFlow's own wording.
"""
from __future__ import annotations

from typing import NamedTuple

import tensorflow as tf

TAG_OPEN, TAG_CLOSE = "<<FRAME_DECODE_ERROR|", "|END_FRAME_DECODE_ERROR>>"
KIND_ERROR, KIND_MISSING_FLOW, KIND_NO_LIDAR = "error", "missing_flow", "no_lidar"
SOURCE_SEPARATOR = " record "  # a source is "<path> record <index>"


class FrameDecodeError(ValueError):
    """A record that cannot be decoded: names the file, the record index and the field."""

    def __init__(self, path: str, record_index: int, field: str, reason: str):
        self.path, self.record_index, self.field, self.reason = path, record_index, field, reason
        record = f"record {record_index}" if record_index >= 0 else "record unknown"
        super().__init__(f"{path}: {record}: field {field}: {reason}")


class MissingFlowLabelsError(FrameDecodeError):
    """The frame has no `range_image_flow_compressed`; the message says how to get labels."""


class NoLidarDataError(FrameDecodeError):
    """The frame has no lidar data (no `lasers`, or no range image in any); the message says where to get some."""


MISSING_FLOW_HELP = (
    "this frame has no scene-flow labels (range_image_flow_compressed). Ordinary WOD v1 frames carry none: use the "
    "scene-flow release of WOD (Jund et al., appendix 'Dataset Format for Annotations'), or bootstrap labels from the "
    "tracked boxes with `python tools/annotate_flow.py`; for model input without labels pass inference_only=True")
NO_LIDAR_HELP = (
    "This reader needs WOD v1 Frame records with lidar range images: the perception release (waymo.com/open, "
    "'Perception Dataset' v1.x, one segment-*.tfrecord file per segment) or its scene-flow release, whose frames also "
    "carry range_image_flow_compressed")
_ERROR_OF_KIND = {KIND_ERROR: FrameDecodeError, KIND_MISSING_FLOW: MissingFlowLabelsError,
                  KIND_NO_LIDAR: NoLidarDataError}


def record_source(path: str, record_index: int) -> str:
    """The source of one record as the tags carry it: "<path> record <index>"."""
    return f"{path}{SOURCE_SEPARATOR}{record_index}"


def split_source(source: str) -> tuple[str, int]:
    """("path", index) of a `record_source` string; (source, -1) if it has no index."""
    path, _, index = source.rpartition(SOURCE_SEPARATOR)
    return (path, int(index)) if path and index.lstrip("-").isdigit() else (source, -1)


class TaggedError(NamedTuple):
    field: str
    kind: str
    reason: str
    source: str  # `record_source(path, index)`, as passed to the decoder

    def error(self, path: str | None = None, record_index: int | None = None, reason: str | None = None
              ) -> FrameDecodeError:
        """The error of this tag's kind; file and record from the tag's source unless given, `reason` likewise."""
        tag_path, tag_index = split_source(self.source)
        return _ERROR_OF_KIND.get(self.kind, FrameDecodeError)(
            tag_path if path is None else path, tag_index if record_index is None else record_index, self.field,
            self.reason if reason is None else reason)


def check(cond, field: str, reason, source, kind: str = KIND_ERROR) -> tf.Operation:
    """An assertion whose message is the tag of (field, kind, reason, source) (no `|` in field, kind or reason; the
    reason may be a scalar string tensor, e.g. one naming a timestamp; the source, one too, may hold anything)."""
    assert "|" not in field + kind + (reason if isinstance(reason, str) else ""), (field, kind, reason)
    message = tf.strings.join([f"{TAG_OPEN}{field}|{kind}|", reason, "|", source, TAG_CLOSE])
    return tf.debugging.Assert(cond, [message], summarize=1)


def parse_tagged_error(message: str) -> TaggedError | None:
    """The first tag written by `check` in an error message, or None."""
    start = message.find(TAG_OPEN)
    end = message.find(TAG_CLOSE, start)
    if start < 0 or end < 0:
        return None
    parts = message[start + len(TAG_OPEN): end].split("|", 3)
    return TaggedError(*parts) if len(parts) == 4 else None
