"""A saved model's flow on pairs of clouds, written to a folder: the job of `tools/predict.py`.

Inputs, each a source of `PairToPredict`s in order, each built in the order of the sweeps the model reads
(`ff3d_tf.inference.predictor.SweepOrder`: how many, and which sweep its t-1 slot holds) or refused before any work
when it cannot be (`predictor.check_order`):
- `WodSegment`: every pair of consecutive frames of a WOD segment TFRecord (`ff3d_tf.data.pairs.pair_dataset` under the
  config given, its studies included, read as WOD frames whatever `data.source` the model was trained on); a segment
  without flow labels is predicted without ground truth; WOD pairs each frame with the previous one;
- `ExampleDataset`: the model input examples of a `tf.data.Dataset` that the caller makes, in the order it says (an
  Argoverse 2 log's labelled examples come from the labels pipeline, which this pipeline does not import);
- `SweepsDirectory`: every sweep of a directory of the user's point files that has a partner, with the directory's
  poses if it has any (`ff3d_tf.data.files.point_files`: formats, intensity rule, poses): for a model of the previous
  sweep, each sweep after the first; for a model of the next sweep (Argoverse 2 challenge records), each sweep before
  the last (`sequence_examples`). The sweeps a model of N sweeps reads before them are the directory's; at its start
  the first sweep stands in for those it lacks (`schema.FULL_HISTORY_KEY` false), as evaluation reads a log. A sweep
  further than `data.max_frame_gap_s` after the one before it (by `timestamps.txt`, else `sweep_period_s`) is an
  error naming it, as `tools/write_pair_records.py --source files` says; with `data.skip_bad_records` the sweeps
  each side of it are read as two sequences (the examples across it skipped and counted);
- `PointFilePair`: one pair of the user's point files, with both poses or neither, for a model of 2 sweeps.
The user's clouds are paired under `pairs.raw_pair_config` (every study off, no crop): each point of a t0 file gets
one output row, in the file's order (points outside the grid: point_valid false, flow 0). Without poses the past clouds
are taken as already in the t0 vehicle frame. Their examples carry the pair's times (`pair_records.TIMESTAMP_KEY` and
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
Every flow written is the velocity of the t0 points (m/s, t0 vehicle frame): a model of the next sweep predicts the
motion from t+1 to t0 per second, minus the velocity, so its flow (and its examples' labels) are written negated.
"""
from __future__ import annotations

import dataclasses
import os
from typing import Callable, Iterator

import numpy as np
import tensorflow as tf

from ff3d_tf import viz, viz3d
from ff3d_tf.config import ConfigError, ExperimentConfig, replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.files import point_files, sequences
from ff3d_tf.data.files.point_file_errors import PointFileError
from ff3d_tf.data.wod import waymo
from ff3d_tf.data.wod_errors import MissingFlowLabelsError
from ff3d_tf.inference.predictor import SweepOrder, check_order, load_predictor, sweep_order
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
    partner: str = "previous"  # the sweep its t-1 slot holds (`schema.PARTNERS`)


def _dataset_pairs(source: str, make_examples: Callable[[], tf.data.Dataset], cfg: ExperimentConfig,
                   partner: str) -> Iterator[PairToPredict]:
    """`frame_<i>` pairs of a dataset of examples; a bad record of `source` raises a FrameDecodeError naming it."""
    with pairs.input_errors_named([source]):
        for i, (batch, ex) in enumerate(pairs.padded_singletons(make_examples(), cfg.data.point_bucket_base,
                                                                cfg.data.drop_ground)):
            yield PairToPredict(f"frame_{i:04d}", i + 1, batch, {k: v.numpy() for k, v in ex.items()}, partner)


@dataclasses.dataclass(frozen=True)
class WodSegment:
    """Every consecutive pair of frames of one WOD segment TFRecord."""
    path: str
    user_clouds = False  # outputs of a dataset's pairs

    @property
    def label(self) -> str:
        return self.path

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line, order: SweepOrder = SweepOrder()
              ) -> Iterator[PairToPredict]:
        check_order(order, "previous", self.path)  # WOD frames: each with the one before it
        # Frames decoded here, whatever the model was trained on (pair records of WOD segments, too).
        cfg = replace_config(cfg, {"data.source": "wod", "data.partner": None})

        def examples():
            first = next(waymo.iterate_records(self.path))[1]
            try:
                waymo.decode_frame(first, laser_names=cfg.data.laser_names, source=self.path)
                inference_only = False
            except MissingFlowLabelsError:
                inference_only = True
                log(f"{self.path}: no flow labels; predicting without ground truth")
            return pairs.pair_dataset([self.path], cfg, inference_only=inference_only)
        return _dataset_pairs(self.path, examples, cfg, "previous")


@dataclasses.dataclass(frozen=True)
class ExampleDataset:
    """The examples of `make_examples()` (called when the pairs are read), shown and named as `label` (a path), their
    t-1 slot holding the `partner` sweep."""
    label: str
    make_examples: Callable[[], tf.data.Dataset]
    partner: str = "previous"
    user_clouds = False

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line, order: SweepOrder = SweepOrder()
              ) -> Iterator[PairToPredict]:
        del log
        check_order(order, self.partner, self.label)
        return _dataset_pairs(self.label, self.make_examples, cfg, self.partner)


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


@dataclasses.dataclass(frozen=True)
class SequenceExample:
    """One example of a sequence of sweeps: the sweep it predicts (`t0`) and the sweep of each slot, t0 first
    (`schema.sweep_clouds`), with whether every past slot holds its own sweep (`schema.FULL_HISTORY_KEY`)."""
    t0: int
    slots: tuple[int, ...]
    full_history: bool


def sequence_examples(num_sweeps: int, num_frames: int, partner: str, breaks: tuple[int, ...] = ()
                      ) -> list[SequenceExample]:
    """The examples of a sequence of `num_sweeps` sweeps (0 the oldest) for a model of `num_frames` sweeps whose t-1
    slot holds the `partner` sweep, every sweep that has one within its run: the sequence is read as separate runs
    split before each index of `breaks` (a missing sweep). A run's first sweep stands in for the past sweeps it lacks.

    partner "previous": sweep i in t0, i-1 in tm1, i-2, i-3, ... in tm2, tm3, ... (the first sweep of a run has none);
    partner "next": sweep i in t0, i+1 in tm1, i-1, i-2, ... in tm2, tm3, ... (the last sweep of a run has none)."""
    bounds = sorted({0, num_sweeps, *(b for b in breaks if 0 < b < num_sweeps)})
    out = []
    for start, stop in zip(bounds[:-1], bounds[1:]):
        for i in range(start, stop):
            partner_index = i - 1 if partner == "previous" else i + 1
            if not start <= partner_index < stop:
                continue
            first_past = 2 if partner == "previous" else 1  # how far back the slot after the partner reaches
            past = [i - k for k in range(first_past, first_past + num_frames - 2)]
            out.append(SequenceExample(i, (i, partner_index, *(max(k, start) for k in past)),
                                       all(k >= start for k in past)))
    return out


def _user_cloud_pairs(sweeps: list[str], poses: list[np.ndarray] | None, intensity_scale: float | None,
                      cfg: ExperimentConfig, log: Log, timestamps_ns: list[int], plan: list[SequenceExample],
                      partner: str) -> Iterator[PairToPredict]:
    """The examples of `plan` (`sequence_examples`) over the point files `sweeps`, named after their t0 file, under
    `raw_pair_config`, with the pair's times (`timestamps_ns`, one per sweep)."""
    if poses is None:
        pair = bool(plan) and len(plan[0].slots) == 2
        log(f"no poses: the {'t-1 cloud of each pair is' if pair else 'past clouds of each example are'} taken as "
            "already in the t0 vehicle frame (no ego-motion compensation)")
    if cfg.data.drop_ground:
        raise ConfigError("this model reads no ground point of any sweep (data.drop_ground=true), and point files "
                          "carry no ground masks: remove each sweep's ground before serving them, or write pair "
                          "records, add the masks (tools/add_ground_masks.py) and evaluate them (tools/eval.py)")
    raw_cfg = pairs.raw_pair_config(cfg)
    notes, frames = _Notes(log), {}
    for item in plan:
        for k in sorted(set(item.slots) - set(frames)):
            frames[k] = _read_sweep(sweeps[k], None if poses is None else poses[k], intensity_scale, notes)
        for k in [k for k in frames if k < min(item.slots)]:  # the plan only moves forward
            del frames[k]
        ex = pairs.make_example([{key: tf.constant(v) for key, v in frames[k].items()} for k in item.slots],
                                raw_cfg, seed=tf.constant([1, 7]))
        ex[pair_records.TIMESTAMP_KEY] = tf.constant(timestamps_ns[item.t0], tf.int64)
        ex[pair_records.PARTNER_TIMESTAMP_KEY] = tf.constant(timestamps_ns[item.slots[1]], tf.int64)
        for batch, example in pairs.padded_singletons(tf.data.Dataset.from_tensors(ex),
                                                      cfg.data.point_bucket_base):
            name = os.path.splitext(os.path.basename(sweeps[item.t0]))[0]
            yield PairToPredict(name, item.t0, batch, {k: v.numpy() for k, v in example.items()}, partner)


def sequence_breaks(sweeps: list[str], timestamps_ns: list[int], origin: str, cfg: ExperimentConfig, log: Log
                    ) -> tuple[int, ...]:
    """The indices of the sweeps further than `data.max_frame_gap_s` after the one before them (a missing sweep):
    a PointFileError naming the first (its file, "timestamp") unless `data.skip_bad_records`, then each logged."""
    max_gap_ns = cfg.data.max_frame_gap_s * 1e9
    breaks = tuple(i for i in range(1, len(sweeps)) if timestamps_ns[i] - timestamps_ns[i - 1] > max_gap_ns)
    for i in breaks:
        err = PointFileError(sweeps[i], "timestamp", pair_records.missing_sweep(
            timestamps_ns[i], timestamps_ns[i - 1], f"{os.path.basename(sweeps[i - 1])} ({origin})",
            cfg.data.max_frame_gap_s))
        if not cfg.data.skip_bad_records:
            raise err
        log(f"skipped: {err}")
    return breaks


@dataclasses.dataclass(frozen=True)
class SweepsDirectory:
    """Every sweep with a partner of a directory of the user's point files (by name), with its poses if any."""
    path: str
    intensity_scale: float | None = None  # None: the stored-type rule (`point_files.intensity_scale_of`)
    sweep_period_s: float = sequences.DEFAULT_SWEEP_PERIOD_S  # the sweep times without D/timestamps.txt
    user_clouds = True

    @property
    def label(self) -> str:
        return self.path

    def check(self, cfg: ExperimentConfig, log: Log = print_line) -> tuple:
        """(sweeps, poses, times in ns, where the times come from, breaks): the directory's listing, its poses and
        times checked (`sequence_breaks`) before any model is loaded or any point file read."""
        sweeps = point_files.list_sweeps(self.path)
        poses = point_files.sweep_poses(self.path, sweeps)
        stamps, origin = sequences.sweep_times_ns(self.path, len(sweeps), self.sweep_period_s)
        return sweeps, poses, stamps, origin, sequence_breaks(sweeps, stamps, origin, cfg, lambda line: None)

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line, order: SweepOrder = SweepOrder()
              ) -> Iterator[PairToPredict]:
        sweeps, poses, stamps, origin, breaks = self.check(cfg)
        log(f"{self.path}: sweep times from {origin}")
        sequence_breaks(sweeps, stamps, origin, cfg, log)  # (each break, logged)
        partner = order.partner if order.partner_matters else "previous"  # the pair reads either side alike
        plan = sequence_examples(len(sweeps), order.num_frames, partner, breaks)
        n = order.num_frames
        examples = f"{len(plan)} pairs" if n == 2 else f"{len(plan)} examples of {n} sweeps"
        log(f"{self.path}: {len(sweeps)} sweeps, {examples}, {'poses given' if poses is not None else 'no poses'}")
        without = sorted(set(range(len(sweeps))) - {e.t0 for e in plan})
        if without:
            why = "no earlier sweep" if partner == "previous" else \
                "no next sweep: the model reads each sweep with the next one (Argoverse 2 challenge records)"
            log(f"{self.path}: {len(without)} sweeps without a prediction of their own ({why}"
                + (f"; {len(breaks)} of them beside a missing sweep" if breaks else "") + "): "
                + ", ".join(os.path.basename(sweeps[i]) for i in without[:5]) + (" ..." if len(without) > 5 else ""))
        if n > 2:
            log(f"{self.path}: {sum(not e.full_history for e in plan)} examples read the sequence's first sweep for "
                "past sweeps it lacks")
        return _user_cloud_pairs(sweeps, poses, self.intensity_scale, cfg, log, stamps, plan, partner)


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

    def check(self, cfg: ExperimentConfig, log: Log = print_line) -> None:
        """Both files and poses read and checked before any model is loaded (a bad file: `PointFileError`)."""
        del cfg, log
        for path in (self.points_tm1, self.points_t0):
            point_files.read_point_file(path)
        for pose in (self.pose_tm1, self.pose_t0):
            if pose is not None:
                point_files.read_pose(pose)

    def pairs(self, cfg: ExperimentConfig, log: Log = print_line, order: SweepOrder = SweepOrder()
              ) -> Iterator[PairToPredict]:
        if order.num_frames != 2:
            raise ConfigError(f"{self.points_t0}: a pair of point files serves a model of 2 sweeps; this one reads "
                              f"{order.num_frames}: give a directory of sweeps (--sweeps_dir)")
        if order.partner_matters and order.partner != "previous":
            raise ConfigError(f"{self.points_t0}: the model reads each sweep with the NEXT one in its t-1 slot "
                              f"(data.partner=next, {order.describe()}); a pair of files gives the sweep before "
                              "t0: give a directory of sweeps (--sweeps_dir), which is read in the model's order")
        poses = None if self.pose_t0 is None else [point_files.read_pose(self.pose_tm1),
                                                   point_files.read_pose(self.pose_t0)]
        gap_ns = int(round(sequences.check_sweep_period(self.sweep_period_s) * 1e9))
        return _user_cloud_pairs([self.points_tm1, self.points_t0], poses, self.intensity_scale, cfg, log,
                                 [0, gap_ns], sequence_examples(2, 2, "previous"), "previous")


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


def velocity_sign(partner: str) -> float:
    """The factor that makes an example's flow (the motion from its partner cloud to t0 per second) the velocity of
    the t0 points: 1 with the previous sweep, -1 with the next."""
    return 1.0 if partner == "previous" else -1.0


def predict(cfg: ExperimentConfig, checkpoint: str | None, source: PairSource, out_dir: str, png_every: int = 10,
            rerun_path: str | None = None, log: Log = print_line, predictor: Predictor | None = None) -> int:
    """Predicts every pair of `source` with `predictor`, or else the model at `checkpoint` (`load_predictor`, loaded
    first: the source's examples are built in its order), and writes the outputs of the module docstring; returns
    the number of pairs predicted. A missing Rerun extra raises `viz3d.Viz3dUnavailableError` before any work; a
    source of another order than the model's a ConfigError (`check_order`); a bad point file `PointFileError`."""
    if predictor is None and not checkpoint:
        raise ValueError("predict needs a checkpoint (a model) or a predictor")
    if png_every < 1:
        raise ValueError(f"png_every must be at least 1, got {png_every}")
    recording = None
    if rerun_path:
        recording = viz3d.FlowRecording(rerun_path,
                                        recording_name=os.path.basename(os.path.normpath(source.label)))
    if hasattr(source, "check"):  # what can be checked before the model loads
        source.check(cfg, log)
    if predictor is None:  # the model's own sweep order, whatever the config says (its restore checks the rest)
        predictor = load_predictor(replace_config(cfg, {"data.partner": None}), checkpoint)
    order = sweep_order(predictor)
    os.makedirs(out_dir, exist_ok=True)
    count = 0
    for i, pair in enumerate(source.pairs(cfg, log, order)):
        flow, valid = predictor.predict(pair.batch, pair.example)
        sign = velocity_sign(pair.partner)
        if sign < 0 and count == 0:
            log("the model reads each sweep with the next one: its flow (the motion from t+1 to t0 per second) is "
                "written negated, the velocity of the t0 points")
        flow = sign * np.asarray(flow)
        ex = {**pair.example, "flow_mps_t0": sign * np.asarray(pair.example["flow_mps_t0"])}
        pair = dataclasses.replace(pair, example=ex)
        has_labels = _write_pair(out_dir, pair, flow, valid, source.user_clouds, log)
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
