"""Flow without a trained model: NSFP fitted to each pair, as a `ff3d_tf.predictor.Predictor`, for `tools/predict.py
--method nsfp` and `tools/eval.py --method nsfp`.

Each pair is fitted as the pseudo-label job fits it (`pseudo_records.fit_pair`: the config's `nsfp` section, by default
the measured fit `nsfp.MEASURED_FIT_OPTIONS`; a bad fit retried with the next seed), its ground removed from both
clouds by the job's rule (`nsfp.ground`, `pseudo_records.ground_masks`): the pair's own masks where it carries both
(Argoverse 2's map), else (`auto`, `height`) the local height rule for the pair, which needs no map
(`ground.pair_ground_masks`). What the predictor returns for the pair's t0 points:
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
from ff3d_tf.labels.nsfp import keep_mask
from ff3d_tf.predictor import Predictor



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
        job = self.job
        ground_t0, ground_tm1, ground_rule = pseudo_records.ground_masks(ex, job.ground)  # the job's rule
        if ground_t0 is not None:
            ex["is_ground_t0"], ex["is_ground_tm1"] = ground_t0, ground_tm1
            job = dataclasses.replace(job, ground="records")
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
