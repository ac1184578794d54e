"""Decode-once pair records: model input pairs written once, read back with no per-point work but a byte copy.

Why: decoding a WOD frame on the fly (zlib, range image to points, pairing) costs more CPU per pair than an
accelerator's training step (`benchmarks/input_cpu.json`). A record holds one pair exactly as `ff3d_tf.data.pairs`
makes it before its studies (every point kept, the t-1 cloud already in the t0 frame), so reading it and applying the
studies gives the same example, bit for bit, as decoding the frames (`tests/data/test_pair_records.py`).

File: `<name>.pairs.tfrecord` (TFRecord, optionally ZLIB-compressed), one `tf.train.Example` per pair. Every array is
one bytes feature holding its little-endian raw bytes; point counts are int64 features. `RECORD_FIELDS` below is the
layout. Precision `exact` keeps float32 everywhere; `compact` stores point features and flows as float16 (coordinates
stay float32, so pillar indices never change): float16 keeps 11 significant bits (relative error <= 2^-11, 0.05%),
and a pair of N + N points takes 39 N bytes instead of 53 N.

With `data.num_frames` > 2 a record also holds the older sweeps (`schema.past_sweep_keys`), copied into it: each
record stands alone, at the cost of storing every sweep N - 1 times over a log (`Manifest.num_frames`).

A directory of records has a manifest `pair_records.json` (`Manifest`): what wrote it (WOD or Argoverse 2, which lidars
and returns, which labels), checked against the experiment config before any work starts.
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import NamedTuple

import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.data import wod_errors

FILE_SUFFIX = ".pairs.tfrecord"
MANIFEST_NAME = "pair_records.json"
FORMAT_NAME, FORMAT_VERSION = "ff3d_tf.pair_records", 1
PRECISIONS = ("exact", "compact")
COMPRESSIONS = ("none", "zlib")
SOURCES = ("wod", "av2", "files")  # "files": a user's own sequences (labels/own_records.py)
# Scalar metadata of a record (not model input): the timestamps of the t0 cloud and of its partner (the t-1 cloud,
# or with `Manifest.partner` "next" the later one), in ns (WOD: microseconds x 1000), and the id of the sequence it
# comes from (WOD segment file name, Argoverse 2 log id).
TIMESTAMP_KEY, PARTNER_TIMESTAMP_KEY, SEQUENCE_KEY = "timestamp_ns_t0", "timestamp_ns_partner", "sequence_id"
METADATA_KEYS = (TIMESTAMP_KEY, PARTNER_TIMESTAMP_KEY, SEQUENCE_KEY)


def missing_sweep(time_ns: int, before_ns: int, before: str, max_gap_s: float) -> str:
    """Why the sweep at `time_ns` cannot follow the one at `before_ns` (named `before`) in any example."""
    return (f"the sweep at {time_ns} ns comes {(time_ns - before_ns) * 1e-9:.3f} s after {before}, more than "
            f"data.max_frame_gap_s = {max_gap_s} s: a sweep is missing (data.skip_bad_records=true skips the examples "
            "across the gap)")


def pair_gap_s(example: dict) -> float:
    """The time between a record's two clouds (s, > 0 whichever `Manifest.partner`)."""
    return abs(int(example[PARTNER_TIMESTAMP_KEY]) - int(example[TIMESTAMP_KEY])) * 1e-9


class RecordField(NamedTuple):
    exact: str  # stored dtype with precision "exact"
    compact: str  # ... and with "compact"
    model_dtype: str  # dtype of the example key (`ff3d_tf.schema`)
    tail_shape: tuple  # per-point shape after the point axis
    count_key: str  # the point count that gives the first axis


# The layout of every per-point key (`schema.POINT_KEYS`; the optional ones are present in a file when its manifest
# lists them).
RECORD_FIELDS = {key: RecordField(spec.stored, spec.stored_compact or spec.stored, spec.dtype, spec.tail_shape,
                                  schema.cloud_keys(spec.cloud)["count"]) for key, spec in schema.POINT_KEYS.items()}
REQUIRED_POINT_KEYS = schema.PAIR_T0_POINT_KEYS + schema.PAIR_TM1_POINT_KEYS


def record_keys(num_frames: int = 2) -> tuple[tuple, tuple, tuple]:
    """(per-point keys, count keys, pose keys) every record of `num_frames` sweeps holds."""
    clouds = schema.sweep_clouds(num_frames)
    past = [schema.cloud_keys(c) for c in clouds[2:]]
    return (REQUIRED_POINT_KEYS + tuple(k[part] for k in past for part in ("xyz", "features")),
            tuple(schema.cloud_keys(c)["count"] for c in clouds), tuple(schema.cloud_keys(c)["pose"] for c in clouds))


@dataclasses.dataclass(frozen=True)
class Manifest:
    """What a directory of pair records holds (`pair_records.json`)."""

    source: str  # one of SOURCES
    laser_names: tuple[int, ...]
    returns: tuple[int, ...]
    max_frame_gap_s: float
    precision: str = "exact"
    compression: str = "none"
    extras: tuple[str, ...] = ()  # optional point keys every record of the directory holds
    # False: raw LiDAR without flow labels (flow 0, class -1 everywhere): input for tools/pseudo_label.py only.
    human_labels: bool = True
    # Argoverse 2 records for the 2024 challenge pair each sweep (t0) with the NEXT sweep (as "t-1"): the model's
    # flow is then minus the challenge's flow per 0.1 s (docs/datasets.md, "Argoverse 2"). WOD records are always "previous".
    partner: str = "previous"
    num_frames: int = 2  # sweeps per record: t0, t-1 and num_frames - 2 older ones (`data.num_frames`)
    written_by: str = ""  # the writer's command line or description

    def validate(self, where: str) -> "Manifest":
        def bad(field, why):
            return wod_errors.FrameDecodeError(where, -1, field, why)
        if self.source not in SOURCES:
            raise bad("source", f"{self.source!r}: one of {SOURCES}")
        if self.precision not in PRECISIONS:
            raise bad("precision", f"{self.precision!r}: one of {PRECISIONS}")
        if self.compression not in COMPRESSIONS:
            raise bad("compression", f"{self.compression!r}: one of {COMPRESSIONS}")
        unknown = set(self.extras) - set(schema.PAIR_EXTRA_POINT_KEYS)
        if unknown:
            raise bad("extras", f"unknown keys {sorted(unknown)}; known: {schema.PAIR_EXTRA_POINT_KEYS}")
        if self.partner not in schema.PARTNERS:
            raise bad("partner", f"{self.partner!r}: one of {schema.PARTNERS}")
        if isinstance(self.num_frames, bool) or not isinstance(self.num_frames, int) or \
                not 2 <= self.num_frames <= schema.MAX_NUM_FRAMES:
            raise bad("num_frames", f"{self.num_frames!r}: an integer in [2, {schema.MAX_NUM_FRAMES}]")
        problem = schema.lidar_selection_problem(self.laser_names, self.returns)
        if problem is not None:
            raise bad("laser_names", problem)
        return self

    def to_json(self) -> str:
        return json.dumps({"format": FORMAT_NAME, "version": FORMAT_VERSION, **dataclasses.asdict(self)}, indent=1)


def manifest_path(directory: str) -> str:
    return os.path.join(directory, MANIFEST_NAME)


def write_manifest(directory: str, manifest: Manifest) -> None:
    """Writes (atomically) or checks the manifest of `directory`: a directory holds records of one manifest only."""
    manifest.validate(manifest_path(directory))
    tf.io.gfile.makedirs(directory)
    path = manifest_path(directory)
    if tf.io.gfile.exists(path):
        existing = read_manifest(directory)
        if dataclasses.replace(existing, written_by="") != dataclasses.replace(manifest, written_by=""):
            raise wod_errors.FrameDecodeError(path, -1, "manifest", f"the directory holds records written as "
                                              f"{existing}; these would be {manifest}: use another --out_dir")
        return
    with tf.io.gfile.GFile(path + ".partial", "w") as f:
        f.write(manifest.to_json())
    tf.io.gfile.rename(path + ".partial", path, overwrite=True)


def read_manifest(directory: str) -> Manifest:
    path = manifest_path(directory)
    if not tf.io.gfile.exists(path):
        raise FileNotFoundError(f"{path}: missing; pair records come with their manifest "
                                "(written by tools/write_pair_records.py)")
    try:
        with tf.io.gfile.GFile(path) as f:
            raw = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise wod_errors.FrameDecodeError(path, -1, "file", f"not JSON ({err})") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT_NAME or raw.get("version") != FORMAT_VERSION:
        raise wod_errors.FrameDecodeError(path, -1, "format", f"expected {FORMAT_NAME} version {FORMAT_VERSION}")
    fields = {f.name for f in dataclasses.fields(Manifest)}
    unknown = set(raw) - fields - {"format", "version"}
    if unknown:
        raise wod_errors.FrameDecodeError(path, -1, sorted(unknown)[0], "unknown manifest field")
    try:
        manifest = Manifest(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.items() if k in fields})
    except TypeError as err:
        raise wod_errors.FrameDecodeError(path, -1, "manifest", str(err)) from None
    return manifest.validate(path)


def manifest_of_files(files: list[str]) -> Manifest:
    """The one manifest of the directories holding `files` (records of different manifests are not mixed)."""
    directories = sorted({os.path.dirname(f) for f in files})
    manifests = {d: read_manifest(d) for d in directories}
    first = manifests[directories[0]]
    for d, m in manifests.items():
        if dataclasses.replace(m, written_by="") != dataclasses.replace(first, written_by=""):
            raise wod_errors.FrameDecodeError(manifest_path(d), -1, "manifest",
                                              f"differs from {manifest_path(directories[0])}: one kind of records "
                                              "per dataset")
    return first


# --- Writing ---------------------------------------------------------------------------------------------------------
def _bytes_feature(data: bytes) -> tf.train.Feature:
    return tf.train.Feature(bytes_list=tf.train.BytesList(value=[data]))


def _int_feature(value: int) -> tf.train.Feature:
    return tf.train.Feature(int64_list=tf.train.Int64List(value=[int(value)]))


def serialize_pair(example: dict, precision: str = "exact", extras: tuple[str, ...] = (), num_frames: int = 2
                   ) -> bytes:
    """One record of a pair (NumPy arrays under `schema.PAIR_KEYS`, `METADATA_KEYS` and `extras`; with `num_frames`
    > 2 also `schema.past_sweep_keys`), as `RECORD_FIELDS` lays it out."""
    timestamp_ns, sequence_id = int(example[TIMESTAMP_KEY]), example[SEQUENCE_KEY]
    sequence_id = sequence_id.decode() if isinstance(sequence_id, bytes) else str(sequence_id)
    point_keys, count_keys, pose_keys = record_keys(num_frames)
    n = {k: len(example[schema.cloud_keys(cloud)["xyz"]]) for k, cloud in zip(count_keys,
                                                                            schema.sweep_clouds(num_frames))}
    features = {k: _int_feature(v) for k, v in n.items()}
    for key in point_keys + tuple(extras):
        spec = RECORD_FIELDS[key]
        value = np.asarray(example[key])
        want = (n[spec.count_key],) + spec.tail_shape
        if value.shape != want:
            raise ValueError(f"{sequence_id} at {timestamp_ns}: {key} has shape {value.shape}, expected {want}")
        stored = getattr(spec, precision)
        features[key] = _bytes_feature(value.astype(f"<{np.dtype(stored).str[1:]}", copy=False).tobytes())
    for key in pose_keys:
        features[key] = _bytes_feature(np.asarray(example[key], "<f8").reshape(4, 4).tobytes())
    if num_frames > 2:
        features[schema.FULL_HISTORY_KEY] = _int_feature(bool(example[schema.FULL_HISTORY_KEY]))
    features[TIMESTAMP_KEY] = _int_feature(timestamp_ns)
    features[PARTNER_TIMESTAMP_KEY] = _int_feature(example[PARTNER_TIMESTAMP_KEY])
    features[SEQUENCE_KEY] = _bytes_feature(sequence_id.encode())
    return tf.train.Example(features=tf.train.Features(feature=features)).SerializeToString()


def write_records_atomically(out_path: str, records, compression: str = "none") -> int:
    """Writes serialized records to `out_path` through `<out_path>.partial` and a rename; returns their count.
    An interrupted write leaves no output (a rerun writes the file again)."""
    tmp = out_path + ".partial"
    tf.io.gfile.makedirs(os.path.dirname(out_path) or ".")
    count = 0
    options = tf.io.TFRecordOptions(compression_type="ZLIB" if compression == "zlib" else "")
    try:
        with tf.io.TFRecordWriter(tmp, options) as writer:
            for record in records:
                writer.write(record)
                count += 1
    except BaseException:
        if tf.io.gfile.exists(tmp):
            tf.io.gfile.remove(tmp)
        raise
    tf.io.gfile.rename(tmp, out_path, overwrite=True)
    return count


def records_file_name(sequence_id: str) -> str:
    """`<sequence>.pairs.tfrecord` for a WOD segment file name (its .tfrecord suffix dropped) or an AV2 log id."""
    base = os.path.basename(sequence_id)
    for suffix in (".tfrecord", ".tfrecords"):
        if base.endswith(suffix):
            base = base[: -len(suffix)]
    return base + FILE_SUFFIX


# --- Reading ---------------------------------------------------------------------------------------------------------
def _feature_spec(manifest: Manifest, extras) -> dict:
    point_keys, count_keys, pose_keys = record_keys(manifest.num_frames)
    history = (schema.FULL_HISTORY_KEY,) if manifest.num_frames > 2 else ()
    spec = {k: tf.io.FixedLenFeature([], tf.int64) for k in count_keys + history +
            (TIMESTAMP_KEY, PARTNER_TIMESTAMP_KEY)}
    spec.update({k: tf.io.FixedLenFeature([], tf.string) for k in point_keys + tuple(extras) + pose_keys +
                 (SEQUENCE_KEY,)})
    return spec


def record_parser(manifest: Manifest, extras: tuple[str, ...] = ()):
    """fn(serialized record, source string "<path> record <i>") -> example dict (`schema.PAIR_KEYS`, the requested
    `extras`, `METADATA_KEYS`). A record whose arrays do not match their counts fails with a tagged error naming
    the field (`ff3d_tf.data.wod_errors`)."""
    missing = set(extras) - set(manifest.extras)
    if missing:
        raise ValueError(f"the records hold no {sorted(missing)} (they hold {list(manifest.extras) or 'no extras'})")
    point_keys, count_keys, pose_keys = record_keys(manifest.num_frames)
    keys = point_keys + tuple(extras)
    spec = _feature_spec(manifest, extras)

    @tf.autograph.experimental.do_not_convert
    def parse(record, source):
        f = tf.io.parse_single_example(record, spec)
        counts = {k: tf.cast(f[k], tf.int32) for k in count_keys}
        checks, out = [], {}
        for key in keys:
            field = RECORD_FIELDS[key]
            stored = tf.dtypes.as_dtype(getattr(field, manifest.precision))
            flat = tf.io.decode_raw(f[key], stored)
            width = int(np.prod(field.tail_shape, dtype=np.int64))
            checks.append(wod_errors.check(tf.size(flat) == counts[field.count_key] * width, key,
                                           f"byte length does not match {field.count_key} x {width} "
                                           f"{stored.name} values", source))
            out[key] = (flat, field)
        for key in pose_keys:
            flat = tf.io.decode_raw(f[key], tf.float64)
            checks.append(wod_errors.check(tf.size(flat) == 16, key, "expected 16 float64 values", source))
            out[key] = (flat, None)
        with tf.control_dependencies(checks):
            ex = {}
            for key, (flat, field) in out.items():
                if field is None:
                    ex[key] = tf.reshape(flat, [4, 4])
                    continue
                value = tf.reshape(flat, [counts[field.count_key], *field.tail_shape])
                ex[key] = value != 0 if field.model_dtype == "bool" else tf.cast(value, field.model_dtype)
        ex.update(counts)
        ex.update({k: f[k] for k in METADATA_KEYS})
        if manifest.num_frames > 2:
            ex[schema.FULL_HISTORY_KEY] = f[schema.FULL_HISTORY_KEY] != 0
        return ex

    return parse


def records_dataset(path: str, manifest: Manifest, extras: tuple[str, ...] = (), skip_bad_records: bool = False
                    ) -> tf.data.Dataset:
    """Examples of one records file, in file order (see `record_parser`); bad records raise, or are skipped."""
    parse = record_parser(manifest, extras)
    records = tf.data.TFRecordDataset(path, compression_type="ZLIB" if manifest.compression == "zlib" else "")
    if skip_bad_records:
        records = records.ignore_errors(log_warning=True)

    def decode(index, record):
        return parse(record, tf.strings.join([path, wod_errors.SOURCE_SEPARATOR, tf.strings.as_string(index)]))

    ds = records.enumerate().map(decode, num_parallel_calls=tf.data.AUTOTUNE, deterministic=True)
    return ds.ignore_errors(log_warning=True) if skip_bad_records else ds


def locate_fault(files: list[str]) -> wod_errors.FrameDecodeError | None:
    """Reads `files` again record by record to name the first one the TFRecord reader or the Example parser
    rejects (a codec error carries no record index); None if every record reads."""
    if not files:
        return None
    manifest = manifest_of_files(files)
    spec = _feature_spec(manifest, manifest.extras)
    for path in files:
        index = -1
        try:
            for index, record in enumerate(tf.data.TFRecordDataset(
                    path, compression_type="ZLIB" if manifest.compression == "zlib" else "")):
                try:
                    tf.io.parse_single_example(record, spec)
                except tf.errors.InvalidArgumentError as err:
                    return wod_errors.FrameDecodeError(path, index, "record",
                                                       f"not a pair record ({err.message.splitlines()[0][:200]})")
        except tf.errors.DataLossError:
            return wod_errors.FrameDecodeError(path, index + 1, "file",
                                               "corrupt or truncated TFRecord (records after it cannot be read)")
    return None
