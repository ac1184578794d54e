"""Records in, fields added, records out: the one shape of a job that adds per-point fields (extras of
`schema.POINT_KEYS`) to a directory of pair records, writing them again beside everything they held.

A job names the fields it adds and computes them in one of two units:

- per pair (`enrich_pairs`): a record's fields from that record alone (NSFP pseudo-labels,
  `ff3d_tf.labels.pseudo_records`). Each pair's result is kept as soon as it is computed (`<out>.parts/<index>.npz`,
  written atomically), so a killed run resumes with the pairs not yet done; the parts are removed once the file is
  written.
- per file (`enrich_whole_file`): every record's fields from the whole file at once (a log: self-supervision's
  DUFOMap, `ff3d_tf.labels.self_supervision`); a killed run does the file again.

Either way each output file is written atomically (`pair_records.write_records_atomically`: nothing half-written), an
output that exists is skipped (`{"already_done": 1}`), a record that does not parse stops the job naming file, record
and field, or with `skip_bad_records` is skipped and counted (`skipped_records`). `run_job` writes the output manifest
(the input's with the fields among its extras, `output_manifest`) before any work and runs one Beam element per file
(`ff3d_tf.data.beam_job`), with progress per pair and per file.
"""
from __future__ import annotations

import dataclasses
import io
import logging
import os
import time
from typing import Callable, Iterator

import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.data import beam_job, pair_records, wod_errors

_LOG = logging.getLogger(__name__)
PARTS_SUFFIX = ".parts"


def output_manifest(manifest: pair_records.Manifest, fields: tuple[str, ...], written_by: str = ""
                    ) -> pair_records.Manifest:
    """The input's manifest with `fields` among its extras (after those it held, once each)."""
    extras = tuple(k for k in manifest.extras if k not in fields) + tuple(fields)
    return dataclasses.replace(manifest, extras=extras, written_by=written_by)


def records_of(path: str, manifest: pair_records.Manifest) -> tf.data.TFRecordDataset:
    """The serialized records of one records file."""
    return tf.data.TFRecordDataset(path, compression_type="ZLIB" if manifest.compression == "zlib" else "")


def count_records(path: str, manifest: pair_records.Manifest) -> int:
    """Records in the file (for progress lines); the readable ones when its framing is corrupt."""
    count = 0
    try:
        for _ in records_of(path, manifest):
            count += 1
    except tf.errors.DataLossError:
        return count  # the framing breaks here: the records before it are those the job reads
    return count


def read_examples(path: str, manifest: pair_records.Manifest, skip_bad_records: bool, counts: dict,
                  leave_out: tuple[str, ...] = ()) -> Iterator[tuple[int, dict]]:
    """(record index, every stored field of the record as NumPy, less the extras `leave_out`) of each record of
    `path`, in file order. A record that does not parse raises a FrameDecodeError naming file, record and field
    (`ff3d_tf.data.wod_errors`), or with `skip_bad_records` is logged, counted (`counts["skipped_records"]`) and left
    out; a corrupt TFRecord framing ends the file there (nothing after it can be read) in the same two ways."""
    parse = pair_records.record_parser(manifest, tuple(k for k in manifest.extras if k not in leave_out))
    iterator, index = iter(records_of(path, manifest)), -1
    while True:
        index += 1
        try:
            record = next(iterator)
        except StopIteration:
            return
        except tf.errors.DataLossError:
            error = wod_errors.FrameDecodeError(path, index, "file", "corrupt or truncated TFRecord (records after "
                                                "it cannot be read)")
            if not skip_bad_records:
                raise error from None
            _LOG.warning("skipped the rest of the file: %s", error)
            counts["skipped_records"] = counts.get("skipped_records", 0) + 1
            return
        try:
            example = parse(record, tf.constant(wod_errors.record_source(path, index)))
        except tf.errors.InvalidArgumentError as err:
            tagged = wod_errors.parse_tagged_error(err.message)
            error = tagged.error() if tagged is not None else wod_errors.FrameDecodeError(
                path, index, "record", f"not a pair record ({err.message.splitlines()[0][:200]})")
            if not skip_bad_records:
                raise error from None
            _LOG.warning("skipped: %s", error)
            counts["skipped_records"] = counts.get("skipped_records", 0) + 1
            continue
        yield index, {k: v.numpy() for k, v in example.items()}


def record_where(path: str, index: int, ex: dict) -> str:
    """How logs and errors name a record: file, index and its t0 timestamp."""
    return f"{path}: record {index} (t0 {int(ex[pair_records.TIMESTAMP_KEY])} ns)"


def _field_shape_ok(key: str, value: np.ndarray, ex: dict) -> bool:
    spec = schema.POINT_KEYS[key]
    n = len(ex[schema.cloud_keys(spec.cloud)["xyz"]])
    return value.shape == (n,) + tuple(spec.tail_shape) and value.dtype == np.dtype(spec.dtype)


def save_part(path: str, part: dict) -> None:
    """One pair's result (arrays by name: its fields and the job's own bookkeeping), written atomically."""
    buffer = io.BytesIO()
    np.savez(buffer, **part)
    with tf.io.gfile.GFile(path + ".partial", "wb") as f:
        f.write(buffer.getvalue())
    tf.io.gfile.rename(path + ".partial", path, overwrite=True)


def load_part(path: str, ex: dict, fields: tuple[str, ...]) -> dict | None:
    """A pair's result kept before, or None if missing, unreadable or not of the record's points (then computed
    again)."""
    if not tf.io.gfile.exists(path):
        return None
    try:
        with tf.io.gfile.GFile(path, "rb") as f:
            with np.load(io.BytesIO(f.read()), allow_pickle=False) as stored:
                part = {k: stored[k] for k in stored.files}
    except (ValueError, KeyError, OSError):
        return None
    if not all(k in part and _field_shape_ok(k, part[k], ex) for k in fields):
        return None
    return part


@dataclasses.dataclass(frozen=True)
class PairJob:
    """A per-pair enrichment: `compute(index, ex, where) -> part` (the fields of `fields` as NumPy in their schema
    dtypes, and any bookkeeping arrays of the job's own), run for the pairs not yet done; `on_pair(index, ex, part,
    fresh, progress_line)` for every pair written, `fresh` False for a part kept from an earlier run."""
    fields: tuple[str, ...]
    compute: Callable[[int, dict, str], dict]
    on_pair: Callable[[int, dict, dict, bool, str], None] = lambda *_: None


def enrich_pairs(in_path: str, out_dir: str, job: PairJob, manifest: pair_records.Manifest,
                 out_manifest: pair_records.Manifest, counts: dict, skip_bad_records: bool = False) -> dict:
    """`job`'s fields of every pair of `in_path` into `out_dir` (same file name), resumable per pair (module
    docstring). Returns `counts` (updated by the job's hooks and the reader) with the file's `seconds`, or
    {"already_done": 1}."""
    out_path = os.path.join(out_dir, os.path.basename(in_path))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    t0 = time.time()
    parts = out_path + PARTS_SUFFIX
    tf.io.gfile.makedirs(parts)
    progress = beam_job.Progress(count_records(in_path, manifest), "pairs")

    def records():
        for index, ex in read_examples(in_path, manifest, skip_bad_records, counts, leave_out=job.fields):
            part_path = os.path.join(parts, f"{index:06d}.npz")
            where = record_where(in_path, index, ex)
            part = load_part(part_path, ex, job.fields)
            fresh = part is None
            if fresh:
                part = job.compute(index, ex, where)
                if not all(_field_shape_ok(k, np.asarray(part[k]), ex) for k in job.fields):
                    raise ValueError(f"{where}: the job's fields {list(job.fields)} do not match the record's points")
                save_part(part_path, part)
            job.on_pair(index, ex, part, fresh, progress.step())
            ex.update({k: part[k] for k in job.fields})
            yield pair_records.serialize_pair(ex, out_manifest.precision, out_manifest.extras, out_manifest.num_frames)

    pair_records.write_records_atomically(out_path, records(), out_manifest.compression)
    tf.io.gfile.rmtree(parts)
    counts["seconds"] = time.time() - t0
    return counts


def enrich_whole_file(in_path: str, out_dir: str, fields: tuple[str, ...],
                      compute: Callable[[str, list[tuple[int, dict]]], list[dict]], manifest: pair_records.Manifest,
                      out_manifest: pair_records.Manifest, counts: dict, skip_bad_records: bool = False) -> dict:
    """`fields` of every record of `in_path` into `out_dir` (same file name) from the whole file at once:
    `compute(in_path, [(index, ex), ...]) -> [fields of each record, in order]` (module docstring). Returns `counts`,
    or {"already_done": 1}."""
    out_path = os.path.join(out_dir, os.path.basename(in_path))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    examples = list(read_examples(in_path, manifest, skip_bad_records, counts, leave_out=fields))
    added = compute(in_path, examples)

    def records():
        for (index, ex), new in zip(examples, added, strict=True):
            if not all(_field_shape_ok(k, np.asarray(new[k]), ex) for k in fields):
                raise ValueError(f"{record_where(in_path, index, ex)}: the job's fields {list(fields)} do not match "
                                 "the record's points")
            ex.update({k: new[k] for k in fields})
            yield pair_records.serialize_pair(ex, out_manifest.precision, out_manifest.extras, out_manifest.num_frames)

    pair_records.write_records_atomically(out_path, records(), out_manifest.compression)
    return counts


def run_job(files: list[str], out_dir: str, out_manifest: pair_records.Manifest, process: Callable[[str], dict],
            job_name: str, beam_args: list[str] | None = None) -> dict:
    """Writes (or checks) `out_dir`'s manifest, then runs `process(file) -> counts` for every file as a Beam job
    (`beam_job.run_per_input`, its counts JSON `<out_dir>/<job_name>_counts.json`); returns the summed counts.
    `process` must be picklable (a `functools.partial` of a module-level function)."""
    pair_records.write_manifest(out_dir, out_manifest)  # before any work: a directory of other records fails here
    return beam_job.run_per_input(list(files), process, out_dir, job_name, beam_args)
