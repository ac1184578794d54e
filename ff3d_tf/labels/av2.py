"""Argoverse 2 pairs labelled by the paper's rule: flow of each t0 point from the cuboids of two sweeps
(`ff3d_tf.labels.box_flow.bootstrap_flow`), read through `ff3d_tf.data.av2.argoverse2`; and the job that writes them as
pair records (`ff3d_tf.data.pair_records`) for training and for the Argoverse 2 challenge's evaluation.

Records for the challenge pair each sweep t (the t0 cloud) with the NEXT sweep t+1 (its partner, in the t-1 slot):
the challenge scores the points of sweep t with their displacement to sweep t+1. The label is the model's quantity,
the motion from the partner cloud to the t0 cloud divided by the gap, (p_t - p_t+1) / dt, so it is minus the
velocity; the challenge's flow (metres to the next sweep) is -flow_mps_t0 * dt. Each record also holds the ground
masks of every cloud (`schema.ground_keys`: the log's ground raster), the Argoverse category of every point
(`category_t0`, the `classes` values of Argoverse's own flow labels; 0 = in no cuboid) and its cuboid (`instance_id_t0`:
the index of the cuboid among the sweep's, the box that labelled the point; -1 = in no cuboid), for DeltaFlow's class
and instance terms (`ff3d_tf.model.losses`). The last sweep of a log has no partner.

Logs without `annotations.feather` (the test split) are written unlabelled (`labels=False`, `--no_labels`): the same
points in the same order and the same pairs as labelled records (so the official masks match), the map's ground masks
(`AV2_UNLABELLED_EXTRAS`), flow 0 and class -1 everywhere, and a manifest saying `human_labels: false` (as
`ff3d_tf.labels.own_records` does): input for a submission (`tools/av2_submission.py`) or for the pseudo-label job.
A labelled job over a log without annotations stops before any work, naming it (`NO_ANNOTATIONS`).
"""
from __future__ import annotations

import functools
import logging
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import beam_job, pair_records, pairs
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.pairs import make_pair
from ff3d_tf.labels.box_flow import bootstrap_flow

_LOG = logging.getLogger(__name__)
AV2_EXTRAS = schema.AV2_RECORD_EXTRAS
AV2_UNLABELLED_EXTRAS = ("is_ground_t0", "is_ground_tm1")  # the map's ground masks: no cuboid is read
ANNOTATIONS_NAME = "annotations.feather"
NO_ANNOTATIONS = ("no {name}: labelled records need the log's cuboids. Logs of the test split have none: write them "
                  "with --no_labels (unlabelled records, for a test submission or tools/pseudo_label.py)")


def labelled_pair(log_dir: str, index: int = 1) -> tuple[dict, dict]:
    """(frame t-1, frame t0) for sweeps index-1 and index, the t0 frame labelled by `bootstrap_flow` (paper convention)."""
    stamps = argoverse2.sweep_timestamps(log_dir)
    if not 1 <= index < len(stamps):
        raise argoverse2.Argoverse2FormatError(os.path.join(log_dir, "sensors", "lidar"), "file",
                                               f"a pair needs sweeps {index - 1} and {index}; the log has {len(stamps)}")
    ts_tm1, ts_t0 = stamps[index - 1], stamps[index]
    f_tm1, f_t0 = argoverse2.read_sweep(log_dir, ts_tm1), argoverse2.read_sweep(log_dir, ts_t0)
    flow, cls = bootstrap_flow(f_t0["points_xyz"], argoverse2.cuboids(log_dir, ts_t0),
                               argoverse2.cuboids(log_dir, ts_tm1), f_t0["pose"], f_tm1["pose"], (ts_t0 - ts_tm1) * 1e-9)
    f_t0["flow_mps"], f_t0["class_id"] = flow, cls
    return f_tm1, f_t0


def model_example(log_dir: str, cfg, index: int = 1) -> dict:
    """A model input example (NumPy, `ff3d_tf.schema` pair keys) of sweeps index-1 -> index, labelled by bootstrap."""
    f_tm1, f_t0 = labelled_pair(log_dir, index)
    ex = make_pair({k: tf.constant(v) for k, v in f_tm1.items()}, {k: tf.constant(v) for k, v in f_t0.items()}, cfg,
                   seed=tf.constant([1, 7]))
    return {k: v.numpy() for k, v in ex.items()}


def list_logs(path: str) -> list[str]:
    """The log directories under `path` (an Argoverse 2 split directory, or one log directory)."""
    if os.path.isdir(os.path.join(path, "sensors", "lidar")):
        return [path]
    if not os.path.isdir(path):
        raise FileNotFoundError(f"{path}: no such directory (expected an Argoverse 2 split or log directory)")
    logs = sorted(os.path.join(path, d) for d in os.listdir(path)
                  if os.path.isdir(os.path.join(path, d, "sensors", "lidar")))
    if not logs:
        raise FileNotFoundError(f"{path}: no Argoverse 2 logs (<log_id>/sensors/lidar/*.feather) in it")
    return logs


def check_log(log_dir: str, labels: bool = True) -> None:
    """Argoverse2FormatError naming `log_dir`'s annotations file when `labels` and the log has none
    (`NO_ANNOTATIONS`)."""
    path = os.path.join(log_dir, ANNOTATIONS_NAME)
    if labels and not os.path.isfile(path):
        raise argoverse2.Argoverse2FormatError(path, "file", NO_ANNOTATIONS.format(name=ANNOTATIONS_NAME))


def challenge_pair(log_dir: str, index: int, cfg: ExperimentConfig, labels: bool = True) -> dict:
    """The pair record contents (NumPy) of sweep `index` (t0) and sweep `index + 1` (its partner), labelled by the
    cuboids with Argoverse's margin, with `AV2_EXTRAS` and `pair_records.METADATA_KEYS`; every point kept. Without
    `labels`: the same points and pair, flow 0 and class -1, `AV2_UNLABELLED_EXTRAS` only (no cuboid is read).

    With `data.num_frames` = N > 2 the example also holds the N - 2 sweeps before t0 (newest first, as "tm2", ...:
    the partner is the next sweep, the history the earlier ones, as the DeltaFlow authors read AV2), each in the t0
    frame; where the log has fewer, its first sweep stands in (`schema.FULL_HISTORY_KEY` False)."""
    stamps = argoverse2.sweep_timestamps(log_dir)
    if not 0 <= index < len(stamps) - 1:
        raise argoverse2.Argoverse2FormatError(os.path.join(log_dir, "sensors", "lidar"), "file",
                                               f"sweep {index} has no next sweep; the log has {len(stamps)}")
    ts_t0, ts_next = stamps[index], stamps[index + 1]
    f_t0, f_next = argoverse2.read_sweep(log_dir, ts_t0), argoverse2.read_sweep(log_dir, ts_next)
    ts_history = [stamps[max(index - k, 0)] for k in range(1, cfg.data.num_frames - 1)]
    history = [argoverse2.read_sweep(log_dir, ts) for ts in ts_history]
    for ts, f in ((ts_t0, f_t0), (ts_next, f_next), *zip(ts_history, history)):
        if len(f["points_xyz"]) == 0:
            raise argoverse2.Argoverse2FormatError(os.path.join(log_dir, "sensors", "lidar", f"{ts}.feather"),
                                                   "x", "empty sweep: no points")
    if labels:
        check_log(log_dir)
        boxes_t0 = argoverse2.cuboids(log_dir, ts_t0)
        dt_s = (ts_next - ts_t0) * 1e-9
        flow, cls, owner = bootstrap_flow(f_t0["points_xyz"], boxes_t0, argoverse2.cuboids(log_dir, ts_next),
                                          f_t0["pose"], f_next["pose"], dt_s, enlarge_m=argoverse2.CUBOID_MARGIN_M,
                                          with_instances=True)
        f_t0["flow_mps"], f_t0["class_id"] = flow, cls
    ex = pairs.make_example([{k: tf.constant(v) for k, v in f.items()} for f in (f_t0, f_next, *history)],
                            pairs.raw_pair_config(cfg))
    ex = {k: v.numpy() for k, v in ex.items()}
    if history:
        ex[schema.FULL_HISTORY_KEY] = index >= len(history)
    if labels:
        categories = np.array([argoverse2.scene_flow_category_index(str(c)) for c in boxes_t0["category"]] + [0],
                              np.int32)
        ex["category_t0"] = categories[owner]  # owner -1 (no cuboid) reads the appended 0
        ex["instance_id_t0"] = owner  # the cuboid (track) of each point, by its index among the sweep's cuboids
    for key, f in zip(schema.ground_keys(cfg.data.num_frames), (f_t0, f_next, *history)):  # every sweep's, slot order
        ex[key] = argoverse2.is_ground(log_dir, f["points_xyz"], f["pose"])
    ex[pair_records.TIMESTAMP_KEY], ex[pair_records.PARTNER_TIMESTAMP_KEY] = ts_t0, ts_next
    ex[pair_records.SEQUENCE_KEY] = os.path.basename(os.path.normpath(log_dir))
    return ex


def records_manifest(cfg: ExperimentConfig, precision: str = "exact", compression: str = "none",
                     written_by: str = "", labels: bool = True) -> pair_records.Manifest:
    """Both lidars, first returns, paired with the next sweep; `AV2_EXTRAS` and `human_labels` when labelled, else
    `AV2_UNLABELLED_EXTRAS` and `human_labels: false`; with more than 2 sweeps also the past sweeps' ground masks."""
    return pair_records.Manifest(source="av2", laser_names=(1, 2), returns=(1,), max_frame_gap_s=cfg.data.max_frame_gap_s,
                                 precision=precision, compression=compression,
                                 extras=(AV2_EXTRAS if labels else AV2_UNLABELLED_EXTRAS) +
                                 schema.ground_keys(cfg.data.num_frames)[2:], human_labels=labels,
                                 partner="next", num_frames=cfg.data.num_frames,
                                 written_by=written_by).validate("<manifest>")


def write_log_records(log_dir: str, out_dir: str, cfg: ExperimentConfig, manifest: pair_records.Manifest) -> dict:
    """Pair records of one log (`challenge_pair` of every sweep but the last) into `<out_dir>/<log_id>.pairs.tfrecord`
    (atomically; an existing output is kept: resumable), labelled as `manifest.human_labels` says. Returns counts.
    A sweep further than `data.max_frame_gap_s` from the one before it (a missing sweep) fails the log before any
    work, naming it; with `data.skip_bad_records` the examples across the gap are skipped and counted."""
    labels = manifest.human_labels
    log_id = os.path.basename(os.path.normpath(log_dir))
    out_path = os.path.join(out_dir, pair_records.records_file_name(log_id))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    t0 = time.time()
    counts = {"pairs": 0, "points_t0": 0, "skipped_pairs": 0}
    if manifest.num_frames > 2:  # the examples written whose history reaches before the log's first sweep
        counts["pairs_without_full_history"] = 0
    stamps = argoverse2.sweep_timestamps(log_dir)
    num_sweeps = len(stamps)
    max_gap_ns = cfg.data.max_frame_gap_s * 1e9

    gaps = [(a, b) for a, b in zip(stamps[:-1], stamps[1:]) if b - a > max_gap_ns]
    if gaps and not cfg.data.skip_bad_records:  # before any work: nothing is half-written
        before_ns, time_ns = gaps[0]
        raise argoverse2.Argoverse2FormatError(
            os.path.join(log_dir, "sensors", "lidar", f"{time_ns}.feather"), "timestamp_ns",
            pair_records.missing_sweep(time_ns, before_ns, f"{before_ns}.feather", cfg.data.max_frame_gap_s))

    def history_gap(index: int) -> bool:
        """Whether a real past sweep of sweep `index`'s example is further than the gap from the one after it."""
        real = stamps[max(index - cfg.data.num_frames + 2, 0):index + 1]
        return any(b - a > max_gap_ns for a, b in zip(real[:-1], real[1:]))

    def records():
        for index in range(num_sweeps - 1):
            try:
                ex = challenge_pair(log_dir, index, cfg, labels)
            except argoverse2.Argoverse2FormatError as err:
                if not cfg.data.skip_bad_records:
                    raise
                _LOG.warning("skipped: %s", err)
                counts["skipped_pairs"] += 1
                continue
            if ex[pair_records.PARTNER_TIMESTAMP_KEY] - ex[pair_records.TIMESTAMP_KEY] > max_gap_ns or \
                    history_gap(index):
                counts["skipped_pairs"] += 1  # across a gap in the log (data.skip_bad_records)
                continue
            counts["pairs"] += 1
            counts["points_t0"] += int(ex["num_points_t0"])
            if manifest.num_frames > 2 and not ex[schema.FULL_HISTORY_KEY]:
                counts["pairs_without_full_history"] += 1
            yield pair_records.serialize_pair(ex, manifest.precision, manifest.extras, manifest.num_frames)

    pair_records.write_records_atomically(out_path, records(), manifest.compression)
    counts["bytes"] = tf.io.gfile.stat(out_path).length
    counts["seconds"] = time.time() - t0
    return counts


def run_records_job(logs: list[str], out_dir: str, cfg: ExperimentConfig, precision: str = "exact",
                    compression: str = "none", beam_args: list[str] | None = None, written_by: str = "",
                    labels: bool = True) -> dict:
    """Pair records of every log into `out_dir` (a Beam job, one element per log; `ff3d_tf.data.beam_job`); without
    `labels`, unlabelled records (module docstring). A labelled job checks every log's annotations before any work."""
    for log_dir in logs:
        check_log(log_dir, labels)
    manifest = records_manifest(cfg, precision, compression, written_by, labels)
    pair_records.write_manifest(out_dir, manifest)
    return beam_job.run_per_input(list(logs), functools.partial(write_log_records, out_dir=out_dir, cfg=cfg,
                                                                manifest=manifest),
                                  out_dir, "write_pair_records", beam_args)


def log_examples(log_dir: str, cfg: ExperimentConfig, num_frames: int, partner: str):
    """The model examples (NumPy) of every sweep of an Argoverse 2 log that has a partner, in the order of a model of
    `num_frames` sweeps whose t-1 slot holds the `partner` sweep: with "next" the challenge's pairs (`challenge_pair`,
    labelled where the log has annotations), else each sweep with the ones before it (`labelled_pair`, the t-1 sweep,
    and the log's earlier sweeps, its first standing in for those it lacks)."""
    stamps = argoverse2.sweep_timestamps(log_dir)
    if partner == "next":
        labels = os.path.isfile(os.path.join(log_dir, ANNOTATIONS_NAME))
        for index in range(len(stamps) - 1):
            ex = challenge_pair(log_dir, index, cfg, labels)
            yield {k: v for k, v in ex.items() if k not in pair_records.METADATA_KEYS}
        return
    for index in range(1, len(stamps)):
        f_tm1, f_t0 = labelled_pair(log_dir, index)
        history = [argoverse2.read_sweep(log_dir, stamps[max(index - k, 0)]) for k in range(2, num_frames)]
        ex = pairs.make_example([{k: tf.constant(v) for k, v in f.items()} for f in (f_t0, f_tm1, *history)], cfg,
                                seed=tf.constant([1, 7]))
        yield {k: v.numpy() for k, v in ex.items()}
