"""The measurements behind `benchmarks/own_records_cpu.json`: records of your own sweeps written per second per core,
and the real-data checks of the own-files path on the Argoverse 2 sample log.

python -m lab.labels.own_records_bench --out benchmarks/own_records_cpu.json [--nsfp_out DIR]

- `records_speed`: a sequence of synthetic sweeps of `points` points each (uniform in a 100 m square, 4 m tall) with
  `boxes` tracked boxes moving through it, written as KITTI `.bin` files with poses and timestamps; then
  `own_records.write_sequence_records` in this process, with the box table (labelled) and without (`--no_labels`).
  Records per second per core: pairs over the process's CPU seconds (every thread counted), beside the wall time.
- `sample_labels`: the sample log written as files (`av2_sequences.write_log_as_sequence`), its own records against
  the Argoverse 2 path's labelled pair (`av2.labelled_pair`): the share of points with the same class and flow
  within 1 mm/s.
- `sample_nsfp`: `tools/predict.py --method nsfp` on the pair as two point files with their poses (t0: sweep 0, its
  partner sweep 1, as the challenge pairs them; no map), scored by the challenge's arithmetic over its 35 m box
  (`av2_sequences.challenge_scores`). `--nsfp_out DIR` scores a run made before (its DIR/000000.npz and
  DIR/predict_log.txt) instead of running the tool. Where its error lies (`where_the_error_lies`): the same score with
  the true flow put in place of the prediction on every evaluated point the fit did not predict (the points without
  prediction, above the fit's crop, and those the ground rule gave flow 0), and again on the fitted points: what is
  left of the error in each case is the other set's.
- `sample_ground`: the pair's ground without a map against Argoverse 2's map ground (the challenge's), inside the
  fit's crop (`nsfp.keep_mask`), both clouds: points called ground that the map does not (removed from the fit; given
  flow 0) and map ground left in the fit, for the rule of the predictor and the pseudo-label job
  (`ground.pair_ground_masks`).
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from ff3d_tf import cpu, geometry
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pair_records
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.files import box_table, sequences
from ff3d_tf.labels import av2, av2_sequences, ground, nsfp, own_records
from lab import bench
from lab.paths import ROOT

AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")


def write_speed_sequence(directory: str, num_sweeps: int, points: int, boxes: int, seed: int = 0) -> str:
    """The synthetic sequence `records_speed` reads (module docstring)."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform([-45, -45, 0.8], [45, 45, 0.8], (boxes, 3))
    velocity = rng.uniform(-10, 10, (boxes, 2))
    clouds, poses, table = [], [], {}
    for k in range(num_sweeps):
        xyz = rng.uniform([-50, -50, -2], [50, 50, 2], (points, 3))
        moved = centres + np.concatenate([velocity * 0.1 * k, np.zeros((boxes, 1))], 1)
        inside = rng.integers(0, boxes, points // 10)  # a tenth of the points on the boxes
        xyz[: len(inside)] = moved[inside] + rng.uniform([-2, -1, -0.7], [2, 1, 0.7], (len(inside), 3))
        stem = f"{k:06d}"
        clouds.append((stem, xyz.astype(np.float32), rng.uniform(0, 1, points).astype(np.float32)))
        poses.append(geometry.box_matrices_np(np.array([[0.8 * k, 0.0, 0.0]]), np.array([0.01 * k]))[0])
        table[stem] = {"center": moved, "size": np.tile([4.0, 2.0, 1.4], (boxes, 1)), "heading": np.zeros(boxes),
                       "track_id": np.array([f"t{j}" for j in range(boxes)]),
                       "class_id": np.ones(boxes, np.int32)}
    return sequences.write_sequence(directory, clouds, poses, [k * 100_000_000 for k in range(num_sweeps)], table)


def records_speed(work_dir: str, num_sweeps: int = 11, points: int = 100_000, boxes: int = 40,
                  cfg: ExperimentConfig | None = None) -> dict:
    """Pairs written per CPU second and per wall second, with and without the box table (module docstring)."""
    cfg = cfg or ExperimentConfig()
    seq = write_speed_sequence(os.path.join(work_dir, "speed"), num_sweeps, points, boxes)
    out = {"points_per_sweep": points, "boxes_per_sweep": boxes, "sweeps": num_sweeps, "pairs": num_sweeps - 1}
    for name, labels in (("with_boxes", True), ("without_boxes", False)):
        options = own_records.OwnRecordsOptions(labels=labels)
        target = os.path.join(work_dir, name)
        manifest = own_records.records_manifest(cfg, labels)
        pair_records.write_manifest(target, manifest)
        warm = os.path.join(work_dir, name + "_warmup")  # TensorFlow's first ops traced outside the timing
        pair_records.write_manifest(warm, manifest)
        own_records.write_sequence_records(seq, warm, cfg, manifest, options)
        cpu_start, wall_start = time.process_time(), time.perf_counter()
        counts = own_records.write_sequence_records(seq, target, cfg, manifest, options)
        cpu_s, wall_s = time.process_time() - cpu_start, time.perf_counter() - wall_start
        out[name] = {"cpu_s": cpu_s, "wall_s": wall_s, "pairs_per_cpu_s": counts["pairs"] / cpu_s,
                     "pairs_per_wall_s": counts["pairs"] / wall_s, "bytes_per_pair": counts["bytes"] / counts["pairs"]}
    return out


def sample_labels(work_dir: str, log_dir: str = AV2_LOG) -> dict:
    """The sample log as files, labelled from its box table, against the Argoverse 2 path (module docstring)."""
    seq = av2_sequences.write_log_as_sequence(log_dir, os.path.join(work_dir, "log"))
    class_map = box_table.read_class_map(os.path.join(seq, av2_sequences.CLASS_MAP_NAME))
    options = own_records.OwnRecordsOptions(class_map=tuple(class_map.items()))
    cfg = ExperimentConfig()
    (ex,) = list(own_records.sequence_examples(own_records.check_sequence(seq, options), cfg, options))
    _, f_t0 = av2.labelled_pair(log_dir, 1)
    same = (ex["class_id_t0"] == f_t0["class_id"]) & (np.linalg.norm(ex["flow_mps_t0"] - f_t0["flow_mps"], axis=1)
                                                      < 1e-3)
    objects = f_t0["class_id"] > 0
    return {"points": int(len(same)), "same_label_share": float(same.mean()), "object_points": int(objects.sum()),
            "same_label_share_of_object_points": float(same[objects].mean())}


def sample_nsfp(work_dir: str, log_dir: str = AV2_LOG, nsfp_out: str | None = None) -> dict:
    """NSFP without a model on the sample pair as files, scored (module docstring)."""
    pair = os.path.join(work_dir, "pair")
    av2_sequences.write_log_as_sequence(log_dir, pair, with_boxes=False, pose_files=True)
    stamps = argoverse2.sweep_timestamps(log_dir)
    gap_s = (stamps[1] - stamps[0]) * 1e-9
    command = ["tools/predict.py", "--method", "nsfp", "--points_tm1", "PAIR/000001.npy", "--points_t0",
               "PAIR/000000.npy", "--pose_tm1", "PAIR/000001.pose.txt", "--pose_t0", "PAIR/000000.pose.txt",
               "--out_dir", "OUT"]
    if nsfp_out is None:
        nsfp_out = os.path.join(work_dir, "nsfp")
        os.makedirs(nsfp_out, exist_ok=True)
        args = [a.replace("PAIR", pair).replace("OUT", nsfp_out) for a in command]
        start = time.perf_counter()
        run = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, check=True)
        seconds = time.perf_counter() - start
        log = run.stdout
        with open(os.path.join(nsfp_out, "predict_log.txt"), "w") as f:
            f.write(log)
    else:
        with open(os.path.join(nsfp_out, "predict_log.txt")) as f:
            log = f.read()
        seconds = None
    with np.load(os.path.join(nsfp_out, "000000.npz")) as z:
        flow, valid = z["flow_mps"], z["point_valid"]
    # predict's gap: --sweep_period_s, 0.1 s by default (the flow is its motion over that gap)
    scores = av2_sequences.challenge_scores(log_dir, 0, flow, valid, sequences.DEFAULT_SWEEP_PERIOD_S)
    fit = re.search(r"nsfp pair 0: (\d+) steps, loss ([\d.]+), ([\d.]+) s, ground by (\w+)", log)
    p, z = scores["prediction"], scores["zero_flow"]
    return {"where_the_error_lies": _where_the_error_lies(log_dir, flow, valid),
            "command": " ".join(["python"] + command), "true_gap_s": gap_s, "tool_seconds": seconds,
            "fit_steps": int(fit.group(1)) if fit else None, "fit_seconds": float(fit.group(3)) if fit else None,
            "ground_rule": fit.group(4) if fit else None, "evaluated_points": scores["evaluated_points"],
            "evaluated_points_without_prediction": scores["evaluated_points_without_prediction"],
            "three_way_epe_m": p["three_way/mean_epe_m"], "fg_dynamic_epe_m": p["three_way/fg_dynamic_epe_m"],
            "bucketed_dynamic_norm_epe": p["bucketed/mean_dynamic_norm_epe"],
            "zero_flow_three_way_epe_m": z["three_way/mean_epe_m"], "nsfp": p, "zero_flow": z}


def _sample_pair(log_dir: str) -> dict:
    return av2.challenge_pair(log_dir, 0, ExperimentConfig())


def _where_the_error_lies(log_dir: str, flow: np.ndarray, valid: np.ndarray) -> dict:
    """Three-way EPE with the truth put in on the points the fit did not predict, and on those it did (module
    docstring)."""
    ex = _sample_pair(log_dir)
    ground_t0, _ = ground.pair_ground_masks(ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"])
    fitted = valid & ~(ground_t0 & nsfp.keep_mask(ex["points_xyz_t0"], nsfp.MEASURED_FIT_OPTIONS))
    # the truth as predict's flow: m/s over the gap the scores read it with
    truth = ex["flow_mps_t0"] * pair_records.pair_gap_s(ex) / sequences.DEFAULT_SWEEP_PERIOD_S
    out = {"fitted_points": int(fitted.sum())}
    for name, replaced in (("truth_where_not_fitted", ~fitted), ("truth_where_fitted", fitted)):
        scores = av2_sequences.challenge_scores(log_dir, 0, np.where(replaced[:, None], truth, flow),
                                                valid | replaced, sequences.DEFAULT_SWEEP_PERIOD_S)
        out[name + "_three_way_epe_m"] = scores["prediction"]["three_way/mean_epe_m"]
    return out


def sample_ground(log_dir: str = AV2_LOG) -> dict:
    """The no-map ground rules against the map's ground on the sample pair (module docstring)."""
    ex = _sample_pair(log_dir)
    clouds = (("t0", ex["points_xyz_t0"], ex["is_ground_t0"]), ("tm1", ex["points_xyz_tm1_in_t0"], ex["is_ground_tm1"]))
    rules = {"height_rule_of_the_pair": ground.pair_ground_masks(ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"])}
    out = {"map_ground_in_crop": {}}
    for name, xyz, on_map in clouds:
        keep = nsfp.keep_mask(xyz, nsfp.MEASURED_FIT_OPTIONS)
        out["map_ground_in_crop"][name] = {"points_in_crop": int(keep.sum()), "map_ground": int((keep & on_map).sum())}
    for rule, masks in rules.items():
        out[rule] = {}
        for (name, xyz, on_map), called in zip(clouds, masks):
            keep = nsfp.keep_mask(xyz, nsfp.MEASURED_FIT_OPTIONS)
            out[rule][name] = {"ground_not_on_map": int((keep & called & ~on_map).sum()),
                               "map_ground_not_called_ground": int((keep & ~called & on_map).sum())}
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--nsfp_out", help="score this finished `tools/predict.py --method nsfp` run instead of running it")
    p.add_argument("--skip_nsfp", action="store_true")
    args = p.parse_args(argv)
    work = tempfile.mkdtemp(prefix="own_records_bench_")
    try:
        result = {"machine": cpu.describe(), "load_average_at_start": bench.load_average(),
                  "records_speed": records_speed(work),
                  "av2_sample_as_files": {"labels": sample_labels(work)}}
        result["av2_sample_as_files"]["ground"] = sample_ground()
        if not args.skip_nsfp:
            result["av2_sample_as_files"]["nsfp"] = sample_nsfp(work, nsfp_out=args.nsfp_out)
        bench.write_json(args.out, result, sort_keys=True)
        print(f"wrote {args.out}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
