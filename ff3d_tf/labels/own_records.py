"""Pair records of a user's own sequences of sweeps (`tools/write_pair_records.py --source files`), labelled from the
user's tracked boxes by the paper's rule, or unlabelled for the NSFP pseudo-label job.

Input: sequence directories (`ff3d_tf.data.files.sequences`: point files sorted by name, their poses, optional
`timestamps.txt`, optional box table `boxes.csv` / `boxes.feather`). Each two consecutive sweeps make a pair as WOD's
do (`ff3d_tf.data.pairs.make_pair` under `pairs.raw_pair_config`: every point kept, the t-1 cloud moved into the t0
vehicle frame with the two poses); a sweep further than `data.max_frame_gap_s` from the one before it is an error
naming it (a missing sweep), or with `data.skip_bad_records` the pairs across the gap are skipped and counted.

Labels (`OwnRecordsOptions.labels`): from the sequence's box table, each t0 point gets the flow and class of the paper's
box rule (`ff3d_tf.labels.box_flow.bootstrap_flow`: rigid boxes of the track at t-1 and t0, ego motion removed; a box
without a t-1 box of its track gives its points class -1; every other point is background, flow 0), with the boxes'
length and width grown by `box_margin_m` (Argoverse 2's labels use 0.2 m); and `instance_id_t0`, the index of the t0
box the point is in among that sweep's boxes (the table's row order; -1 for none). Without labels
(`--no_labels`): flow 0 and class -1 everywhere, the manifest says `human_labels: false`, and the records are the
pseudo-label job's input (`ff3d_tf.labels.pseudo_records`), whose defaults fit the pairs of any sweep range (the
fitted region is the Argoverse 2 box, 35 m, and z in [-3, 3] m; ground by the height rule without a map).

Pairs need poses: a sequence without them is refused before any work, saying how to give them (`NO_POSES`).
The job: one Beam element per sequence (`ff3d_tf.data.beam_job`), each writing `<sequence>.pairs.tfrecord`
atomically; an existing output is kept, so a rerun resumes. The manifest's source is `OWN_SOURCE`.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import beam_job, pair_records, pairs
from ff3d_tf.data.files import point_files, sequences
from ff3d_tf.data.files.point_file_errors import PointFileError
from ff3d_tf.labels.box_flow import bootstrap_flow

_LOG = logging.getLogger(__name__)
OWN_SOURCE = "files"  # `pair_records.Manifest.source` of these records
OWN_EXTRAS = ("instance_id_t0",)  # what labelled records carry beside the pair
NO_POSES = ("no poses: pair records need each sweep's vehicle -> world pose to move the t-1 cloud into the t0 frame "
            "(training and evaluation read ego-motion-compensated pairs). Give them as {directory}/poses.txt (one pose "
            "per line in sweep order: the 3x4 or 4x4 matrix row by row, 12 or 16 numbers) or as "
            "{directory}/<sweep name>.pose.txt|.pose.npy beside each sweep; a lidar odometry or SLAM run gives them "
            "where the vehicle logged none. (tools/predict.py --sweeps_dir predicts without poses.)")
NO_BOXES = ("no box table (boxes.csv or boxes.feather, one row per box per sweep: docs/datasets.md, 'Your own "
            "sequences'): give one, or write unlabelled records with --no_labels (for tools/pseudo_label.py)")


@dataclasses.dataclass(frozen=True)
class OwnRecordsOptions:
    """How the sequences are read and labelled (module docstring)."""
    labels: bool = True  # False: unlabelled records (--no_labels), for the pseudo-label job
    sweep_period_s: float = sequences.DEFAULT_SWEEP_PERIOD_S  # sweep times without timestamps.txt
    intensity_scale: float | None = None  # None: the stored-type rule (`point_files.intensity_scale_of`)
    box_margin_m: float = 0.0  # added to every box's length and width before the inside test
    class_map: tuple[tuple[str, int | None], ...] = ()  # your class names -> flow class (None: boxes dropped)

    def __post_init__(self):
        sequences.check_sweep_period(self.sweep_period_s)
        if not (np.isfinite(self.box_margin_m) and self.box_margin_m >= 0):
            raise ValueError(f"box margin {self.box_margin_m!r} m: must be a finite number >= 0")


def records_manifest(cfg: ExperimentConfig, labelled: bool, precision: str = "exact", compression: str = "none",
                     written_by: str = "") -> pair_records.Manifest:
    """One lidar (the files hold one cloud a sweep: laser name 1), first returns, `OWN_EXTRAS` when labelled."""
    return pair_records.Manifest(source=OWN_SOURCE, laser_names=(1,), returns=(1,),
                                 max_frame_gap_s=cfg.data.max_frame_gap_s, precision=precision,
                                 compression=compression, extras=OWN_EXTRAS if labelled else (),
                                 human_labels=labelled, num_frames=cfg.data.num_frames,
                                 written_by=written_by).validate("<manifest>")


def check_sequence(directory: str, options: OwnRecordsOptions) -> sequences.SweepSequence:
    """The sequence, refused (`PointFileError` naming it) without poses, or without a box table when labelled; a
    labelled sequence's box table is read and checked here too (before any work)."""
    seq = sequences.read_sequence(directory, options.sweep_period_s)
    if seq.poses is None:
        raise PointFileError(directory, "pose", NO_POSES.format(directory=directory))
    if options.labels:
        if seq.box_table is None:
            raise PointFileError(directory, "boxes", NO_BOXES)
        sequences.read_boxes(seq, dict(options.class_map))
    return seq


def _frame(seq: sequences.SweepSequence, index: int, options: OwnRecordsOptions) -> dict:
    cols = point_files.read_point_file(seq.sweeps[index])
    return point_files.frame_from_columns(cols, seq.poses[index], options.intensity_scale,
                                          seq.timestamps_ns[index] // 1000)


def labelled_pair(frame_tm1: dict, frame_t0: dict, boxes_tm1: dict | None, boxes_t0: dict | None, dt_s: float,
                  box_margin_m: float = 0.0) -> tuple[dict, np.ndarray | None]:
    """(frame t0 with its flow and class from the boxes, its points' box index) by the paper's rule; without boxes the
    frame as it is (flow 0, class -1) and None."""
    if boxes_t0 is None:
        return frame_t0, None
    flow, cls, owner = bootstrap_flow(frame_t0["points_xyz"], boxes_t0, boxes_tm1, frame_t0["pose"], frame_tm1["pose"],
                                      dt_s, enlarge_m=(box_margin_m, box_margin_m, 0.0), with_instances=True)
    return {**frame_t0, "flow_mps": flow, "class_id": cls}, owner


def sequence_examples(seq: sequences.SweepSequence, cfg: ExperimentConfig, options: OwnRecordsOptions,
                      counts: dict | None = None):
    """The pair records' contents (NumPy: `schema.PAIR_KEYS`, `pair_records.METADATA_KEYS`, `OWN_EXTRAS` when
    labelled) of every pair of consecutive sweeps of `seq` not further apart than `data.max_frame_gap_s`, in order.
    A bad point file, or a sweep further than `data.max_frame_gap_s` from the one before it (a missing sweep), stops
    here naming it, or with `data.skip_bad_records` skips the pairs it is in (counted in `counts["skipped_pairs"]`).
    With `data.num_frames` = N > 2 each example also holds the N - 2 sweeps before t-1 (`pairs.make_example`); after
    the sequence's start, a gap or a skipped file, the oldest sweep since stands in for those missing
    (`schema.FULL_HISTORY_KEY` False)."""
    counts = counts if counts is not None else {}
    counts.setdefault("skipped_pairs", 0)
    boxes = sequences.read_boxes(seq, dict(options.class_map)) if options.labels else None
    raw_cfg = pairs.raw_pair_config(cfg)
    max_gap_ns = cfg.data.max_frame_gap_s * 1e9
    stems = seq.stems
    previous = []  # the sweeps since the last break, newest first, with their indices
    frame_tm1 = None
    for i in range(len(seq.sweeps)):
        try:
            frame_t0 = _frame(seq, i, options)
        except PointFileError as err:
            if not cfg.data.skip_bad_records:
                raise
            _LOG.warning("skipped: %s", err)
            counts["skipped_pairs"] += (frame_tm1 is not None) + (i + 1 < len(seq.sweeps))
            frame_tm1, previous = None, []
            continue
        if frame_tm1 is not None:
            gap_ns = seq.timestamps_ns[i] - seq.timestamps_ns[i - 1]
            if gap_ns > max_gap_ns:  # a missing sweep: the examples across it would pair sweeps too far apart
                err = PointFileError(seq.sweeps[i], "timestamp", pair_records.missing_sweep(
                    seq.timestamps_ns[i], seq.timestamps_ns[i - 1],
                    f"{os.path.basename(seq.sweeps[i - 1])} ({seq.timestamps_from})", cfg.data.max_frame_gap_s))
                if not cfg.data.skip_bad_records:
                    raise err
                _LOG.warning("skipped: %s", err)
                counts["skipped_pairs"] += 1
                previous = []
            else:
                labelled, owner = labelled_pair(frame_tm1, frame_t0, None if boxes is None else boxes[stems[i - 1]],
                                                None if boxes is None else boxes[stems[i]], gap_ns * 1e-9,
                                                options.box_margin_m)
                history = [previous[min(k, len(previous) - 1)] for k in range(1, cfg.data.num_frames - 1)]
                ex = pairs.make_example([{k: tf.constant(v) for k, v in f.items()}
                                         for f in (labelled, frame_tm1, *history)], raw_cfg)
                ex = {k: v.numpy() for k, v in ex.items()}
                if history:
                    ex[schema.FULL_HISTORY_KEY] = len(previous) >= cfg.data.num_frames - 1
                if owner is not None:
                    ex["instance_id_t0"] = owner
                ex[pair_records.TIMESTAMP_KEY] = seq.timestamps_ns[i]
                ex[pair_records.PARTNER_TIMESTAMP_KEY] = seq.timestamps_ns[i - 1]
                ex[pair_records.SEQUENCE_KEY] = seq.name
                yield ex
        frame_tm1 = frame_t0
        previous = [frame_t0] + previous[:schema.MAX_NUM_FRAMES]


def write_sequence_records(directory: str, out_dir: str, cfg: ExperimentConfig, manifest: pair_records.Manifest,
                           options: OwnRecordsOptions) -> dict:
    """The pair records of one sequence into `<out_dir>/<sequence>.pairs.tfrecord` (atomically; an existing output is
    kept: resumable). Returns counts."""
    seq = check_sequence(directory, options)
    out_path = os.path.join(out_dir, pair_records.records_file_name(seq.name))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    t0 = time.time()
    counts = {"pairs": 0, "points_t0": 0, "labelled_points_t0": 0, "skipped_pairs": 0}
    if manifest.num_frames > 2:  # the examples written whose history reaches before the sequence's first sweep
        counts["pairs_without_full_history"] = 0

    def records():
        for ex in sequence_examples(seq, cfg, options, counts):
            counts["pairs"] += 1
            if manifest.num_frames > 2 and not ex[schema.FULL_HISTORY_KEY]:
                counts["pairs_without_full_history"] += 1
            counts["points_t0"] += int(ex["num_points_t0"])
            counts["labelled_points_t0"] += int((ex["class_id_t0"] >= 0).sum()) if options.labels else 0
            yield pair_records.serialize_pair(ex, manifest.precision, manifest.extras, manifest.num_frames)

    pair_records.write_records_atomically(out_path, records(), manifest.compression)
    counts["bytes"] = tf.io.gfile.stat(out_path).length
    counts["seconds"] = time.time() - t0
    _LOG.info("%s: %d pairs (%s), %.1f MB, %.2f pairs/s", out_path, counts["pairs"], seq.timestamps_from,
              counts["bytes"] / 1e6, counts["pairs"] / max(counts["seconds"], 1e-9))
    return counts


def run_records_job(directories: list[str], out_dir: str, cfg: ExperimentConfig, options: OwnRecordsOptions,
                    precision: str = "exact", compression: str = "none", beam_args: list[str] | None = None,
                    written_by: str = "") -> dict:
    """Pair records of every sequence into `out_dir` (a Beam job, one element per sequence). Every sequence is
    checked first (`check_sequence`: poses, box tables): a bad one fails before any work."""
    for directory in directories:
        check_sequence(directory, options)
    manifest = records_manifest(cfg, options.labels, precision, compression, written_by)
    pair_records.write_manifest(out_dir, manifest)  # before any work: a directory of other records fails here
    return beam_job.run_per_input(list(directories), functools.partial(
        write_sequence_records, out_dir=out_dir, cfg=cfg, manifest=manifest, options=options),
        out_dir, "write_pair_records", beam_args)
