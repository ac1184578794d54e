"""Pseudo-labels at scale (ZeroFlow's recipe): NSFP flow (`ff3d_tf.labels.nsfp`) of every pair of a directory of pair
records, written as pair records again with `flow_mps_pseudo_t0` beside whatever the input held (human labels, ground
masks, categories), so that `data.labels=pseudo` trains on them and evaluation still scores the human labels.

Input: records of any source (`tools/write_pair_records.py`, WOD or Argoverse 2, labelled or raw with `--no_labels`).
One Beam element per records file (`ff3d_tf.data.beam_job`). NSFP takes seconds to minutes per pair, so each pair's
flow is kept as soon as it is fitted (`<out>.parts/<index>.npy`, float32, written atomically) and a rerun after a kill
fits only the pairs not yet done; the output file is assembled from the parts and written atomically, then the parts
are removed. The fit is deterministic for a seed, so a resumed run writes the same bytes as an uninterrupted one.
Convention: the project's (`ff3d_tf.schema`): motion of each t0 point from its partner cloud to t0, divided by the
gap, in m/s in the t0 vehicle frame; points NSFP does not fit (ground, outside the crop) get 0.
"""
from __future__ import annotations

import dataclasses
import functools
import io
import logging
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf.data import beam_job, pair_records, wod_errors
from ff3d_tf.labels.nsfp import NsfpOptions, nsfp_flow

_LOG = logging.getLogger(__name__)
PSEUDO_KEY = "flow_mps_pseudo_t0"


def output_manifest(manifest: pair_records.Manifest, written_by: str = "") -> pair_records.Manifest:
    """The input's manifest with the pseudo-labels among its extras."""
    extras = tuple(k for k in manifest.extras if k != PSEUDO_KEY) + (PSEUDO_KEY,)
    return dataclasses.replace(manifest, extras=extras, written_by=written_by)


def _records(path: str, manifest: pair_records.Manifest) -> tf.data.TFRecordDataset:
    """The serialized records of one records file."""
    return tf.data.TFRecordDataset(path, compression_type="ZLIB" if manifest.compression == "zlib" else "")


def _raw_examples(path: str, manifest: pair_records.Manifest, skip_bad_records: bool, counts: dict):
    """(record index, every stored field of the record as NumPy) of each record of `path`, in file order. A record
    that does not parse raises a FrameDecodeError naming file, record and field (`ff3d_tf.data.wod_errors`), or with
    `skip_bad_records` is logged, counted (`skipped_records`) and left out; a corrupt TFRecord framing ends the file
    there (nothing after it can be read) in the same two ways."""
    extras = tuple(k for k in manifest.extras if k != PSEUDO_KEY)
    parse = pair_records.record_parser(manifest, extras)
    iterator, index = iter(_records(path, manifest)), -1
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
            counts["skipped_records"] += 1
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
            counts["skipped_records"] += 1
            continue
        yield index, {k: v.numpy() for k, v in example.items()}


def _save_part(path: str, flow: np.ndarray) -> None:
    buffer = io.BytesIO()
    np.save(buffer, flow.astype(np.float32), allow_pickle=False)
    with tf.io.gfile.GFile(path + ".partial", "wb") as f:
        f.write(buffer.getvalue())
    tf.io.gfile.rename(path + ".partial", path, overwrite=True)


def _load_part(path: str, n: int) -> np.ndarray | None:
    """The saved flow of a pair, or None if it is missing or not a [n, 3] float32 array (then it is fitted again)."""
    if not tf.io.gfile.exists(path):
        return None
    try:
        with tf.io.gfile.GFile(path, "rb") as f:
            flow = np.load(io.BytesIO(f.read()), allow_pickle=False)
    except ValueError:
        return None
    return flow if flow.shape == (n, 3) and flow.dtype == np.float32 else None


def _fit_pair(ex: dict, options: NsfpOptions):
    """NSFP of one record's pair: (flow_mps_pseudo_t0 [N,3] float32, 0 where not fitted; the fit's NsfpResult). The
    record's ground mask (`is_ground_t0`, Argoverse 2 records) keeps t0's ground out of the fit."""
    dt_s = abs(int(ex[pair_records.PARTNER_TIMESTAMP_KEY]) - int(ex[pair_records.TIMESTAMP_KEY])) * 1e-9
    keep_t0 = ~ex["is_ground_t0"] if "is_ground_t0" in ex else None
    result = nsfp_flow(ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"], dt_s, options, keep_t0=keep_t0)
    return np.where(result.valid_t0[:, None], result.flow_mps_t0, 0.0).astype(np.float32), result


def _count_records(path: str, manifest: pair_records.Manifest) -> int:
    """Records in the file (for the progress line); the readable ones when its framing is corrupt."""
    count = 0
    try:
        for _ in _records(path, manifest):
            count += 1
    except tf.errors.DataLossError:
        return count  # the framing breaks here: the records before it are those the job reads
    return count


def pseudo_label_file(in_path: str, out_dir: str, options: NsfpOptions, manifest: pair_records.Manifest,
                      out_manifest: pair_records.Manifest, skip_bad_records: bool = False) -> dict:
    """Pseudo-labels of one records file into `out_dir` (same file name); resumable per pair. Returns counts."""
    out_path = os.path.join(out_dir, os.path.basename(in_path))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    parts = out_path + ".parts"
    tf.io.gfile.makedirs(parts)
    counts = {"pairs": 0, "fitted_pairs": 0, "skipped_records": 0, "points_t0": 0, "pseudo_labelled_points": 0,
              "nsfp_iterations": 0, "nsfp_seconds": 0.0}
    progress = beam_job.Progress(_count_records(in_path, manifest), "pairs")
    t0 = time.time()

    def records():
        for index, ex in _raw_examples(in_path, manifest, skip_bad_records, counts):
            part = os.path.join(parts, f"{index:06d}.npy")
            flow = _load_part(part, len(ex["points_xyz_t0"]))
            if flow is None:
                flow, result = _fit_pair(ex, options)
                _save_part(part, flow)
                counts["fitted_pairs"] += 1
                counts["nsfp_iterations"] += result.num_iterations
                counts["nsfp_seconds"] += result.grid_s + result.fit_s
                _LOG.info("%s pair %d: %d iterations, loss %.5f, %.1f s; %s", os.path.basename(in_path), index,
                          result.num_iterations, result.loss, result.grid_s + result.fit_s, progress.step())
            else:
                progress.step()
            counts["pairs"] += 1
            counts["points_t0"] += len(flow)
            counts["pseudo_labelled_points"] += int(np.any(flow != 0, axis=1).sum())
            ex[PSEUDO_KEY] = flow
            yield pair_records.serialize_pair(ex, out_manifest.precision, out_manifest.extras)

    pair_records.write_records_atomically(out_path, records(), out_manifest.compression)
    tf.io.gfile.rmtree(parts)
    counts["seconds"] = time.time() - t0
    return counts


def run_pseudo_label_job(files: list[str], out_dir: str, options: NsfpOptions, beam_args: list[str] | None = None,
                         written_by: str = "", skip_bad_records: bool = False) -> dict:
    """Pseudo-labels of every records file in `files` into `out_dir` (a Beam job, one element per file; progress
    with rate and ETA per pair and per file; bad records named, or skipped and counted with `skip_bad_records`)."""
    manifest = pair_records.manifest_of_files(list(files))
    out_manifest = output_manifest(manifest, written_by)
    pair_records.write_manifest(out_dir, out_manifest)  # before any work: a directory of other records fails here
    return beam_job.run_per_input(list(files), functools.partial(
        pseudo_label_file, out_dir=out_dir, options=options, manifest=manifest, out_manifest=out_manifest,
        skip_bad_records=skip_bad_records),
        out_dir, "pseudo_label", beam_args)
