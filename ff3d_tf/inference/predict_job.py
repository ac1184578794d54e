"""A saved model's flow on pairs of clouds, written to a folder: the job of `tools/predict.py`.

Inputs, each a source of `PairToPredict`s in order:
- `WodSegment`: every pair of consecutive frames of a WOD segment TFRecord (`ff3d_tf.data.pairs.pair_dataset` under the
  config given, its studies included); a segment without flow labels is predicted without ground truth;
- `ExampleDataset`: the model input examples of a `tf.data.Dataset` that the caller makes (an Argoverse 2 log's
  labelled pair comes from the labels pipeline, which this pipeline does not import);
- `SweepsDirectory`: each two consecutive sweeps of a directory of the user's point files, with the directory's poses
  if it has any (`ff3d_tf.data.files.point_files`: formats, intensity rule, poses);
- `PointFilePair`: one pair of the user's point files, with both poses or neither.
The user's clouds are paired under `pairs.raw_pair_config` (every study off, no crop): each point of a t0 file gets
one output row, in the file's order (points outside the grid: point_valid false, flow 0). Without poses the t-1 cloud
is taken as already in the t0 vehicle frame. Their examples carry the pair's times (`pair_records.TIMESTAMP_KEY` and
`PARTNER_TIMESTAMP_KEY`, ns): a sweeps directory's `timestamps.txt` (`ff3d_tf.data.files.sequences`), else one sweep
every `sweep_period_s`; a predictor that needs the gap (NSFP's, whose flow is its motion over the gap) reads them.

`predict` runs a predictor over the pairs of a source (the model at a path, `load_predictor`, or any `Predictor` the
caller gives: the labels pipeline's NSFP fit, which this pipeline does not import) and writes to `out_dir`, per pair:
- from a dataset: `frame_<NNNN>.npz` (points_xyz_t0, flow_mps_pred, point_valid, flow_mps_true, class_id_t0);
- from the user's clouds: `<t0 sweep name>.npz` and `.feather` (`point_files.write_predictions`);
- `<name>_bev.png` every `png_every` pairs (the first included): the prediction and, where the pair has labels, the
  ground truth (`ff3d_tf.viz.bev_flow_png`);
and, given `rerun_path`, a Rerun recording of both clouds and the flow arrows of every pair on a `sweep` time line
(`ff3d_tf.viz3d.FlowRecording`). A line of progress per file written and per pair goes to `log`.
"""
from __future__ import annotations

import collections
import dataclasses
import os
from typing import Callable, Iterator

import numpy as np
import tensorflow as tf

from ff3d_tf import viz, viz3d
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.files import point_files, sequences
from ff3d_tf.data.wod import waymo
from ff3d_tf.data.wod_errors import MissingFlowLabelsError
from ff3d_tf.inference.predictor import load_predictor
from ff3d_tf.predictor import Predictor

Log = Callable[[str], None]


def print_line(line: str) -> None:
    """The default `log`: the line on stdout, flushed (a tool's progress shows as it happens)."""
    print(line, flush=True)


@dataclasses.dataclass(frozen=True)
class PairToPredict:
    name: str  # stem of the pair's output files
    sweep_index: int  # index of the pair's t0 sweep (frame) in its input: its time step in a recording
    batch: dict  # the pair padded to its point bucket, a batch of one (model input, tensors)
    example: dict  # the same pair unpadded, NumPy (`ff3d_tf.schema` pair keys)


def _dataset_pairs(source: str, make_examples: Callable[[], tf.data.Dataset], cfg: ExperimentConfig
                   ) -> Iterator[PairToPredict]:
    """`frame_<i>` pairs of a dataset of examples; a bad record of `source` raises a FrameDecodeError naming it."""
    with pairs.input_errors_named([source]):
        for i, (batch, ex) in enumerate(pairs.padded_singletons(make_examples(), cfg.data.point_bucket_base)):
            yield PairToPredict(f"frame_{i:04d}", i + 1, batch, {k: v.numpy() for k, v in ex.items()})


@dataclasses.dataclass(frozen=True)
class WodSegment:
    """Every consecutive pair of frames of one WOD segment TFRecord."""
    path: str
    user_clouds = False  # outputs of a dataset's pairs

    @property
    def label(self) -> str:
        return self.path

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line) -> Iterator[PairToPredict]:
        def examples():
            first = next(waymo.iterate_records(self.path))[1]
            try:
                waymo.decode_frame(first, laser_names=cfg.data.laser_names, source=self.path)
                inference_only = False
            except MissingFlowLabelsError:
                inference_only = True
                log(f"{self.path}: no flow labels; predicting without ground truth")
            return pairs.pair_dataset([self.path], cfg, inference_only=inference_only)
        return _dataset_pairs(self.path, examples, cfg)


@dataclasses.dataclass(frozen=True)
class ExampleDataset:
    """The examples of `make_examples()` (called when the pairs are read), shown and named as `label` (a path)."""
    label: str
    make_examples: Callable[[], tf.data.Dataset]
    user_clouds = False

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line) -> Iterator[PairToPredict]:
        del log
        return _dataset_pairs(self.label, self.make_examples, cfg)


class _Notes:
    """Logs each remark about the user's files once (a log of many sweeps repeats the same ones)."""

    def __init__(self, log: Log):
        self.log, self.seen = log, set()

    def say(self, key: str, text: str) -> None:
        if key not in self.seen:
            self.seen.add(key)
            self.log(text)


def _read_sweep(path: str, pose: np.ndarray | None, intensity_scale: float | None, notes: _Notes) -> dict:
    """The frame of one point file (`point_files.frame_from_columns`), its remarks logged once each."""
    cols = point_files.read_point_file(path)
    for note in cols.notes:
        notes.say(note, f"{path}: {note}")
    if cols.ignored:
        notes.say("ignored " + ",".join(cols.ignored), f"{path}: columns not used: {', '.join(cols.ignored)}")
    if cols.intensity is None:
        notes.say("no intensity", f"{path}: no intensity column ({'/'.join(point_files.INTENSITY_FIELDS)}): "
                                  "intensity 0")
    else:
        factor = point_files.intensity_scale_of(cols.intensity_dtype, intensity_scale)
        rule = "--intensity_scale" if intensity_scale is not None else \
            "auto: integer types / their maximum, floats as stored"
        notes.say(f"scale {cols.intensity_dtype} {factor}", f"{path}: intensity stored as {cols.intensity_dtype}, "
                                                            f"multiplied by {factor:.6g} ({rule})")
    return point_files.frame_from_columns(cols, pose, intensity_scale)


def _user_cloud_pairs(sweeps: list[str], poses: list[np.ndarray] | None, intensity_scale: float | None,
                      cfg: ExperimentConfig, log: Log, timestamps_ns: list[int]) -> Iterator[PairToPredict]:
    """An example of each `data.num_frames` consecutive point files of `sweeps` (a pair of each two for the paper's
    model), named after its t0 (newest) file, under `raw_pair_config`, with the pair's times (`timestamps_ns`, one
    per sweep). With N sweeps per example, the first N - 1 files get no prediction of their own."""
    num_frames = cfg.data.num_frames
    if poses is None:
        log(f"no poses: the {'t-1 cloud of each pair is' if num_frames == 2 else 'past clouds of each example are'} "
            "taken as already in the t0 vehicle frame (no ego-motion compensation)")
    if num_frames > 2:
        log(f"data.num_frames={num_frames}: each prediction reads its sweep and the {num_frames - 1} before it; the "
            f"first {num_frames - 1} sweeps get none of their own")
    raw_cfg = pairs.raw_pair_config(cfg)
    notes, previous = _Notes(log), collections.deque(maxlen=num_frames - 1)  # newest first
    for i, path in enumerate(sweeps):
        frame_t0 = _read_sweep(path, None if poses is None else poses[i], intensity_scale, notes)
        if len(previous) == num_frames - 1:
            ex = pairs.make_example([{k: tf.constant(v) for k, v in f.items()} for f in (frame_t0, *previous)],
                                    raw_cfg, seed=tf.constant([1, 7]))
            ex[pair_records.TIMESTAMP_KEY] = tf.constant(timestamps_ns[i], tf.int64)
            ex[pair_records.PARTNER_TIMESTAMP_KEY] = tf.constant(timestamps_ns[i - 1], tf.int64)
            for batch, example in pairs.padded_singletons(tf.data.Dataset.from_tensors(ex),
                                                          cfg.data.point_bucket_base):
                name = os.path.splitext(os.path.basename(path))[0]
                yield PairToPredict(name, i, batch, {k: v.numpy() for k, v in example.items()})
        previous.appendleft(frame_t0)


@dataclasses.dataclass(frozen=True)
class SweepsDirectory:
    """Each two consecutive sweeps (by name) of a directory of the user's point files, with its poses if any."""
    path: str
    intensity_scale: float | None = None  # None: the stored-type rule (`point_files.intensity_scale_of`)
    sweep_period_s: float = sequences.DEFAULT_SWEEP_PERIOD_S  # the sweep times without D/timestamps.txt
    user_clouds = True

    @property
    def label(self) -> str:
        return self.path

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line) -> Iterator[PairToPredict]:
        sweeps = point_files.list_sweeps(self.path)
        poses = point_files.sweep_poses(self.path, sweeps)
        stamps, origin = sequences.sweep_times_ns(self.path, len(sweeps), self.sweep_period_s)
        n = cfg.data.num_frames
        examples = f"{len(sweeps) - 1} pairs" if n == 2 else f"{max(len(sweeps) - n + 1, 0)} examples of {n} sweeps"
        log(f"{self.path}: {len(sweeps)} sweeps, {examples}, {'poses given' if poses is not None else 'no poses'}")
        log(f"{self.path}: sweep times from {origin}")
        return _user_cloud_pairs(sweeps, poses, self.intensity_scale, cfg, log, stamps)


@dataclasses.dataclass(frozen=True)
class PointFilePair:
    """One pair of the user's point files; `pose_tm1` and `pose_t0` (pose files) both or neither."""
    points_tm1: str
    points_t0: str
    pose_tm1: str | None = None
    pose_t0: str | None = None
    intensity_scale: float | None = None  # None: the stored-type rule (`point_files.intensity_scale_of`)
    sweep_period_s: float = sequences.DEFAULT_SWEEP_PERIOD_S  # the pair's gap
    user_clouds = True

    def __post_init__(self):
        if (self.pose_tm1 is None) != (self.pose_t0 is None):
            raise ValueError("pose_tm1 and pose_t0 go together (or give neither)")

    @property
    def label(self) -> str:
        return self.points_t0

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line) -> Iterator[PairToPredict]:
        if cfg.data.num_frames != 2:
            raise ValueError(f"{self.points_t0}: a pair of point files serves a model of 2 sweeps; this one reads "
                             f"data.num_frames={cfg.data.num_frames}: give a directory of sweeps (--sweeps_dir)")
        poses = None if self.pose_t0 is None else [point_files.read_pose(self.pose_tm1),
                                                   point_files.read_pose(self.pose_t0)]
        gap_ns = int(round(sequences.check_sweep_period(self.sweep_period_s) * 1e9))
        return _user_cloud_pairs([self.points_tm1, self.points_t0], poses, self.intensity_scale, cfg, log,
                                 [0, gap_ns])


PairSource = WodSegment | ExampleDataset | SweepsDirectory | PointFilePair


def _write_pair(out_dir: str, pair: PairToPredict, flow_mps: np.ndarray, point_valid: np.ndarray,
                user_clouds: bool, log: Log) -> bool:
    """Writes the pair's prediction file(s); True when the pair has ground-truth labels."""
    ex = pair.example
    if user_clouds:
        written = point_files.write_predictions(os.path.join(out_dir, pair.name), ex["points_xyz_t0"], flow_mps,
                                                point_valid)
        log(f"wrote {', '.join(written)}")
        return False
    np.savez_compressed(os.path.join(out_dir, pair.name + ".npz"), points_xyz_t0=ex["points_xyz_t0"],
                        flow_mps_pred=flow_mps, point_valid=point_valid, flow_mps_true=ex["flow_mps_t0"],
                        class_id_t0=ex["class_id_t0"])
    return bool(np.any(ex["class_id_t0"] >= 0))


def predict(cfg: ExperimentConfig, checkpoint: str | None, source: PairSource, out_dir: str, png_every: int = 10,
            rerun_path: str | None = None, log: Log = print_line, predictor: Predictor | None = None) -> int:
    """Predicts every pair of `source` with `predictor`, or else the model at `checkpoint` (`load_predictor`), and
    writes the outputs of the module docstring; returns the number of pairs predicted. A missing Rerun extra raises
    `viz3d.Viz3dUnavailableError` before any work; a bad point file raises `PointFileError` before the model loads."""
    if predictor is None and not checkpoint:
        raise ValueError("predict needs a checkpoint (a model) or a predictor")
    if png_every < 1:
        raise ValueError(f"png_every must be at least 1, got {png_every}")
    recording = None
    if rerun_path:
        recording = viz3d.FlowRecording(rerun_path,
                                        recording_name=os.path.basename(os.path.normpath(source.label)))
    os.makedirs(out_dir, exist_ok=True)
    if predictor is None and not source.user_clouds:
        predictor = load_predictor(cfg, checkpoint)
    count = 0
    for i, pair in enumerate(source.pairs(cfg, log)):
        if predictor is None:  # the user's clouds: loaded once the first pair is read, so a bad file fails first
            predictor = load_predictor(cfg, checkpoint)
        flow, valid = predictor.predict(pair.batch, pair.example)
        has_labels = _write_pair(out_dir, pair, flow, valid, source.user_clouds, log)
        ex = pair.example
        if i % png_every == 0:
            panels = {"prediction": np.where(valid[:, None], flow, 0.0)}
            if has_labels:
                panels["ground truth"] = np.where((ex["class_id_t0"] >= 0)[:, None], ex["flow_mps_t0"], 0.0)
            png = viz.bev_flow_png(os.path.join(out_dir, pair.name + "_bev.png"), ex["points_xyz_t0"], panels,
                                   title=f"{source.label} pair {i}: colour = direction, brightness = speed")
            log(f"wrote {png}")
        if recording is not None:
            recording.log_pair(pair.sweep_index, ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"], flow, valid,
                               ex["pose_t0"])
        count += 1
        log(f"predicted pair {i}: {int(valid.sum())}/{len(valid)} points with a prediction")
    if recording is not None:
        log(f"wrote {recording.close()} (open it with: rerun {rerun_path})")
    log(f"wrote {count} frames to {out_dir}")
    return count
