"""The NSFP pseudo-labels (`ff3d_tf.labels.nsfp`) of an Argoverse 2 log's first pair scored against Argoverse's own flow
labels of it by the 2024 challenge's arithmetic (`ff3d_tf.metrics_av2`), beside zero flow: `av2_sample_check`, the
options it uses (`AV2_NSFP_OPTIONS`: the challenge's 35 m box, ZeroFlow's z crop and the fit settings measured best
on the sample pair) and the label columns it reads."""
from __future__ import annotations

import dataclasses
import os
from typing import Callable

import numpy as np

from ff3d_tf import geometry, metrics_av2
from ff3d_tf.data import argoverse2
from ff3d_tf.labels.nsfp import MEASURED_FIT_OPTIONS, NsfpOptions, keep_mask, nsfp_flow

# The challenge's 35 m box and ZeroFlow's z crop, with the fit measured best on this pair.
AV2_NSFP_OPTIONS = dataclasses.replace(MEASURED_FIT_OPTIONS, crop_xy_half_extent_m=metrics_av2.MAX_DISTANCE_M,
                                       crop_z_range_m=(-3.0, 3.0))


def _av2_label_columns(log_dir: str, num_points: int) -> dict[str, np.ndarray]:
    """`classes` (label index, `ff3d_tf.metrics_av2`) and `is_ground_0` of flow_labels.feather, one row per sweep-0
    point."""
    import pyarrow.feather as feather
    path = os.path.join(log_dir, "flow_labels.feather")
    table = feather.read_table(path)
    out = {}
    for name in ("classes", "is_ground_0"):
        if name not in table.schema.names:
            raise argoverse2.Argoverse2FormatError(path, name, f"missing; the file has {table.schema.names}")
        column = table.column(name)
        if column.null_count:
            raise argoverse2.Argoverse2FormatError(path, name, f"{column.null_count} null values")
        out[name] = column.to_numpy(zero_copy_only=False)
        if len(out[name]) != num_points:
            raise argoverse2.Argoverse2FormatError(path, name, f"{len(out[name])} rows for a sweep of {num_points} "
                                                   "points")
    return {"label_index": out["classes"].astype(np.int64), "is_ground_0": out["is_ground_0"].astype(bool)}


def _av2_pair(log_dir: str) -> dict:
    """The log's first two sweeps as the challenge records pair them: sweep 0 (t0), sweep 1 moved into sweep 0's frame
    (t-1), the map's ground rule on each, Argoverse's flow of sweep 0 (paper convention, m) and its label columns."""
    stamps = argoverse2.sweep_timestamps(log_dir)
    if len(stamps) < 2:
        raise argoverse2.Argoverse2FormatError(os.path.join(log_dir, "sensors", "lidar"), "file",
                                               f"needs two sweeps, found {len(stamps)}")
    sweep0, sweep1 = (argoverse2.read_sweep(log_dir, s) for s in stamps[:2])
    true_m, points_xyz_t0 = argoverse2.argoverse_flow_in_paper_convention(log_dir)
    return {
        "points_xyz_t0": sweep0["points_xyz"], "points_xyz_t0_f64": points_xyz_t0, "true_m": true_m,
        "points_xyz_tm1_in_t0": geometry.transform_points_np(
            sweep1["points_xyz"], geometry.t0_from_tm1_np(sweep0["pose"], sweep1["pose"])),
        "ground_t0": argoverse2.is_ground(log_dir, sweep0["points_xyz"], sweep0["pose"]),
        "ground_tm1": argoverse2.is_ground(log_dir, sweep1["points_xyz"], sweep1["pose"]),
        "dt_s": (stamps[1] - stamps[0]) * 1e-9,
        **_av2_label_columns(log_dir, len(points_xyz_t0)),
    }


def av2_sample_check(log_dir: str, options: NsfpOptions = AV2_NSFP_OPTIONS, subsample: int = 1,
                     progress: Callable[[int, float], None] | None = None) -> dict:
    """NSFP pseudo-labels of an Argoverse 2 log's sweep 0 scored against Argoverse's own flow labels of it, by the
    challenge's arithmetic (`ff3d_tf.metrics_av2`: metres per frame, eval mask = not `is_ground_0` and
    max(|x|, |y|) < 35 m, three-way and bucketed normalized EPE), beside zero flow.

    As the challenge records pair them (`ff3d_tf.labels.av2`): t0 := sweep 0 and "t-1" := sweep 1 moved into sweep
    0's frame, so the pseudo-label is (p_0 - p_1) / dt and the challenge's flow (ego motion removed,
    `argoverse2.argoverse_flow_in_paper_convention`) is -flow_mps_t0 * dt. NSFP sees the non-ground points of both
    sweeps by the map's ground rule (`argoverse2.is_ground`, what the records hold).

    `subsample` = k keeps every k-th point of each sweep (index % k == 0), a sparser pair that fits k times faster:
    NSFP is fitted to the kept points of both sweeps and ONLY the kept sweep-0 points are scored (for NSFP and zero
    flow alike), `evaluated_points` of them in the eval mask; `evaluated_points_full_density` counts the eval mask
    over every point. Scores at k > 1 are of the sparser pair, not of the full-density labels."""
    if isinstance(subsample, bool) or not isinstance(subsample, int) or subsample < 1:
        raise ValueError(f"av2_sample_check: subsample must be an integer >= 1, got {subsample!r}")
    pair = _av2_pair(log_dir)
    evaluated_full = metrics_av2.eval_mask(pair["points_xyz_t0_f64"], pair["is_ground_0"])
    every = slice(None, None, subsample)  # the kept points of either sweep
    points_xyz_tm1_in_t0, ground_tm1 = pair["points_xyz_tm1_in_t0"][every], pair["ground_tm1"][every]
    ground_t0, true_m, is_ground_0 = pair["ground_t0"][every], pair["true_m"][every], pair["is_ground_0"][every]
    dt_s = pair["dt_s"]
    result = nsfp_flow(pair["points_xyz_t0"][every], points_xyz_tm1_in_t0, dt_s, options, keep_t0=~ground_t0,
                       keep_tm1=~ground_tm1, progress=progress)
    predicted_m = -result.flow_mps_t0.astype(np.float64) * dt_s  # the challenge's flow, sweep 0 -> sweep 1
    evaluated = evaluated_full[every]
    scores = {}
    for name, flow_m in (("nsfp", predicted_m), ("zero_flow", np.zeros_like(true_m))):
        acc = metrics_av2.AV2FlowAccumulator()
        acc.update(true_m, flow_m, pair["label_index"][every], evaluated)
        scores[name] = acc.result()
    return {
        **scores,
        "subsample": subsample,
        "evaluated_points": int(evaluated.sum()),
        "evaluated_points_full_density": int(evaluated_full.sum()),
        "evaluated_points_not_optimised_flow_0": int((evaluated & ~result.valid_t0).sum()),
        "optimised_points_t0": int(result.valid_t0.sum()),
        "optimised_points_tm1": int((keep_mask(points_xyz_tm1_in_t0.astype(np.float32), options) & ~ground_tm1).sum()),
        "map_ground_agreement_with_is_ground_0": float((ground_t0 == is_ground_0).mean()),
        "sweep_interval_s": dt_s,
        "iterations": result.num_iterations,
        "loss": result.loss,
        "grid_s": result.grid_s,
        "fit_s": result.fit_s,
    }
