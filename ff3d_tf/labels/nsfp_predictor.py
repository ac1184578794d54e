"""Flow without a trained model: NSFP fitted to each pair, as a `ff3d_tf.predictor.Predictor`, for `tools/predict.py
--method nsfp` and `tools/eval.py --method nsfp`.

Each pair is fitted as the pseudo-label job fits it (`pseudo_records.fit_pair`: the config's `nsfp` section, by default
the measured fit `nsfp.MEASURED_FIT_OPTIONS`; a bad fit retried with the next seed), its ground removed from both
clouds by the job's rule (`nsfp.ground`): the pair's own masks where it carries both (Argoverse 2's map), else
(`auto`, `height`) the local height rule of `ff3d_tf.labels.ground`, which needs no map, applied here to the union of
the two clouds (`joint_height_ground_masks`): both are in the t0 vehicle frame, where their static ground coincides,
so one ground surface serves both and a ground point is ground in both clouds alike; its columns are wider than the
rule's default (`JOINT_GROUND_CELL_M`). (The pseudo-label job's rule, each cloud's surface on its own in the
default columns, calls more of the Argoverse 2 sample pair's points ground that the map does not:
benchmarks/own_records_cpu.json, `av2_sample_as_files.ground`; such points leave the fit. Where the map's ground is
known, as in Argoverse 2 records, it is used.) What the predictor returns for the pair's t0 points:
- a fitted point: its NSFP flow (m/s, t0 vehicle frame, motion from the partner cloud to t0 over the pair's gap);
- a ground point inside the fitted region: flow 0, a prediction (ground does not move);
- a point outside the fitted region (the crop: by default |x|, |y| <= 35 m and z in [-3, 3] m), faster than
  `nsfp.max_speed_mps`, or of a pair whose fit stayed implausible: no prediction (point_valid False, flow 0).

The gap: the pair's timestamps where its example carries them (`pair_records.METADATA_KEYS`: records read with
metadata, a sweeps directory's times), else `default_gap_s` (`--sweep_period_s`). NSFP takes seconds to minutes a
pair on a CPU where a trained model takes milliseconds (docs/label_free.md): use it where no model was trained for the
sensor, or to label.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pair_records
from ff3d_tf.labels import pseudo_records
from ff3d_tf.labels.ground import GROUND_ABOVE_M, height_ground_mask
from ff3d_tf.labels.nsfp import keep_mask
from ff3d_tf.predictor import Predictor


# The height rule's columns for the joint surface: longer than a car (so a column rarely holds an object and no road),
# where the rule's default (`ground.GROUND_CELL_M`) counts the lower parts of objects and curbs as ground more often.
JOINT_GROUND_CELL_M = 8.0


def joint_height_ground_masks(points_xyz_t0: np.ndarray, points_xyz_tm1_in_t0: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray]:
    """(ground of the t0 cloud, ground of the t-1 cloud): the height rule (`height_ground_mask`, columns of
    `JOINT_GROUND_CELL_M`, ground within its `GROUND_ABOVE_M` of the surface) on the union of both clouds, in the t0
    vehicle frame."""
    both = height_ground_mask(np.concatenate([points_xyz_t0, points_xyz_tm1_in_t0]), cell_m=JOINT_GROUND_CELL_M,
                              above_m=GROUND_ABOVE_M)
    return both[: len(points_xyz_t0)], both[len(points_xyz_t0):]


class NsfpPredictor(Predictor):
    """NSFP's flow of each pair (module docstring). `log(line)` gets the fit's progress and a line per pair."""

    def __init__(self, job: pseudo_records.JobOptions = pseudo_records.JobOptions(), default_gap_s: float = 0.1,
                 log: Callable[[str], None] | None = None):
        if not (np.isfinite(default_gap_s) and default_gap_s > 0):
            raise ValueError(f"default_gap_s must be a finite number > 0, got {default_gap_s!r}")
        self.job, self.default_gap_s, self.log = job, float(default_gap_s), log
        self.pairs_fitted = 0

    def gap_s(self, example: dict) -> float:
        if pair_records.TIMESTAMP_KEY in example and pair_records.PARTNER_TIMESTAMP_KEY in example:
            return pair_records.pair_gap_s({k: int(np.asarray(example[k])) for k in
                                            (pair_records.TIMESTAMP_KEY, pair_records.PARTNER_TIMESTAMP_KEY)})
        return self.default_gap_s

    def predict(self, batch: dict, example: dict) -> tuple[np.ndarray, np.ndarray]:
        del batch  # NSFP reads the unpadded clouds
        n0, n1 = int(np.asarray(example["num_points_t0"])), int(np.asarray(example["num_points_tm1"]))
        gap_s = self.gap_s(example)
        ex = {"points_xyz_t0": np.asarray(example["points_xyz_t0"], np.float32)[:n0],
              "points_xyz_tm1_in_t0": np.asarray(example["points_xyz_tm1_in_t0"], np.float32)[:n1],
              pair_records.TIMESTAMP_KEY: int(round(gap_s * 1e9)), pair_records.PARTNER_TIMESTAMP_KEY: 0}
        for key, n in (("is_ground_t0", n0), ("is_ground_tm1", n1)):
            if key in example:
                ex[key] = np.asarray(example[key], bool)[:n]
        job, ground_rule = self.job, self.job.ground
        if ground_rule == "height" or (ground_rule == "auto" and not ("is_ground_t0" in ex and "is_ground_tm1" in ex)):
            ex["is_ground_t0"], ex["is_ground_tm1"] = joint_height_ground_masks(ex["points_xyz_t0"],
                                                                                ex["points_xyz_tm1_in_t0"])
            job, ground_rule = dataclasses.replace(job, ground="records"), "height (one surface for both clouds)"
        elif ground_rule == "auto":
            job, ground_rule = dataclasses.replace(job, ground="records"), "records"
        started, index = time.perf_counter(), self.pairs_fitted

        def progress(steps, loss):
            if self.log is not None:
                self.log(f"nsfp pair {index}: {steps} of at most {self.job.nsfp.max_iterations} steps, best loss "
                         f"{loss:.5f}, {time.perf_counter() - started:.0f} s")
        fit = pseudo_records.fit_pair(ex, job, progress)
        flow, valid = fit.flow_mps, fit.valid.copy()
        if not fit.problem and "is_ground_t0" in ex and job.ground != "none":  # ground in the fitted region: static
            valid |= ex["is_ground_t0"] & keep_mask(ex["points_xyz_t0"], job.nsfp)
        self.pairs_fitted += 1
        if self.log is not None:
            r = fit.result
            self.log(f"nsfp pair {index}: {r.num_iterations} steps, loss {r.loss:.5f}, {r.grid_s + r.fit_s:.1f} s, "
                     f"ground by {ground_rule}, gap {gap_s:.4f} s, {int(fit.valid.sum())} of {n0} points fitted"
                     + (f"; NO FLOW: {fit.problem}" if fit.problem else ""))
        return flow, valid


def predictor_from_config(cfg: ExperimentConfig, default_gap_s: float = 0.1,
                          log: Callable[[str], None] | None = None) -> NsfpPredictor:
    """The NSFP predictor of `cfg`'s `nsfp` section (`pseudo_records.job_from_config`)."""
    return NsfpPredictor(pseudo_records.job_from_config(cfg), default_gap_s, log)
