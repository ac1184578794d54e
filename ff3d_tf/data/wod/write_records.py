"""Pair records of WOD segments (`ff3d_tf.data.pair_records`): the decode-once path's writer.

One output file per segment (`<segment>.pairs.tfrecord`), written atomically, skipped when it exists (resumable); the
pairs are those of `ff3d_tf.data.pairs.pair_dataset` under `pairs.raw_pair_config` (every point, no study), so that
reading them with any config gives the examples the decoding path gives with that config. Extras that the decoded
frames do not hold (each point's labelled box, `instance_id_t0`) come from a caller's `add_extras`
(`ff3d_tf.labels.pipeline.run_wod_records_job`: the box labels are the labelling pipeline's business).

Counts of each segment, summed in the job's summary: `pairs` written; `skipped_pairs`, the examples the segment's
frames would give (one per frame after the first) that `data.skip_bad_records` left out (across a missing or
reordered frame, or beside a bad record); with `data.num_frames` > 2, `pairs_without_full_history`, the examples
written whose history reaches before the segment's first frame (`schema.FULL_HISTORY_KEY` false: evaluation reads
them, training does not).
"""
from __future__ import annotations

import functools
import logging
import os
import time
from typing import Callable

import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import beam_job, pair_records, pairs

_LOG = logging.getLogger(__name__)


def wod_manifest(cfg: ExperimentConfig, precision: str = "exact", compression: str = "none",
                 written_by: str = "", human_labels: bool = True, extras: tuple[str, ...] = ()
                 ) -> pair_records.Manifest:
    """`human_labels=False`: segments without scene-flow labels (raw LiDAR, e.g. for pseudo-labelling); `extras`:
    the optional point keys every record will hold (given by `write_segment`'s `add_extras`)."""
    d = cfg.data
    return pair_records.Manifest(source="wod", laser_names=tuple(d.laser_names), returns=tuple(d.returns),
                                 max_frame_gap_s=d.max_frame_gap_s, precision=precision, compression=compression,
                                 extras=tuple(extras), human_labels=human_labels, num_frames=d.num_frames,
                                 written_by=written_by).validate("<manifest>")


# add_extras(segment path) -> fn(pair example, NumPy) -> {extra key: [N0 or N1, ...] array}
AddExtras = Callable[[str], Callable[[dict], dict]]


def write_segment(in_path: str, out_dir: str, cfg: ExperimentConfig, manifest: pair_records.Manifest,
                  add_extras: AddExtras | None = None) -> dict:
    """Writes the pair records of one segment; returns counts (pairs, skipped_pairs, points, bytes, seconds; with
    more than 2 sweeps pairs_without_full_history; already_done: see the module docstring). `add_extras(in_path)`
    gives each pair its `manifest.extras` (needed when the manifest lists any)."""
    out_path = os.path.join(out_dir, pair_records.records_file_name(in_path))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    t0 = time.time()
    counts = {"pairs": 0, "skipped_pairs": 0, "points_t0": 0, "points_tm1": 0}
    if manifest.num_frames > 2:
        counts["pairs_without_full_history"] = 0
    raw_cfg = pairs.raw_pair_config(cfg)
    if manifest.extras and add_extras is None:
        raise ValueError(f"the manifest lists extras {manifest.extras}: write_segment needs add_extras to give them")
    extras_of = add_extras(in_path) if manifest.extras else None

    def records():
        unlabelled = not manifest.human_labels
        with pairs.input_errors_named([in_path], pairs.decode_options(raw_cfg, unlabelled)):
            for ex in pairs.pair_dataset([in_path], raw_cfg, metadata=True, inference_only=unlabelled):
                ex = {k: v.numpy() for k, v in ex.items()}
                if extras_of is not None:
                    ex.update(extras_of(ex))
                counts["pairs"] += 1
                if manifest.num_frames > 2 and not ex[schema.FULL_HISTORY_KEY]:
                    counts["pairs_without_full_history"] += 1
                counts["points_t0"] += int(ex["num_points_t0"])
                counts["points_tm1"] += int(ex["num_points_tm1"])
                yield pair_records.serialize_pair(ex, manifest.precision, manifest.extras, manifest.num_frames)

    pair_records.write_records_atomically(out_path, records(), manifest.compression)
    if cfg.data.skip_bad_records:  # (without it, a missing frame or a bad record stops the job)
        counts["skipped_pairs"] = max(_readable_records(in_path) - 1 - counts["pairs"], 0)
        if counts["skipped_pairs"]:
            _LOG.warning("%s: %d examples skipped (data.skip_bad_records: across a missing or reordered frame, or "
                         "beside a bad record)", in_path, counts["skipped_pairs"])
    counts["bytes"] = tf.io.gfile.stat(out_path).length
    counts["seconds"] = time.time() - t0
    _LOG.info("%s: %d pairs, %.1f MB, %.2f pairs/s", out_path, counts["pairs"], counts["bytes"] / 1e6,
              counts["pairs"] / max(counts["seconds"], 1e-9))
    return counts


def _readable_records(path: str) -> int:
    """The records of a TFRecord file that can be framed (a damaged file: those before the damage)."""
    count = 0
    try:
        for _ in tf.data.TFRecordDataset(path):
            count += 1
    except tf.errors.OpError:
        pass
    return count


def run_wod_job(files: list[str], out_dir: str, cfg: ExperimentConfig, precision: str = "exact",
                compression: str = "none", beam_args: list[str] | None = None, written_by: str = "",
                human_labels: bool = True, extras: tuple[str, ...] = (), add_extras: AddExtras | None = None) -> dict:
    """Pair records of every segment in `files` into `out_dir` (a Beam job, `ff3d_tf.data.beam_job`), with the
    `extras` that `add_extras` gives (see `write_segment`; a picklable function for multi-process runners)."""
    manifest = wod_manifest(cfg, precision, compression, written_by, human_labels, extras)
    pair_records.write_manifest(out_dir, manifest)  # before any work: a directory of other records fails here
    return beam_job.run_per_input(list(files), functools.partial(write_segment, out_dir=out_dir, cfg=cfg,
                                                                 manifest=manifest, add_extras=add_extras),
                                  out_dir, "write_pair_records", beam_args)
