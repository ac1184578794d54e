"""An Argoverse 2 log written in the layout of a user's own sweeps (`ff3d_tf.data.files.sequences`), and the
challenge's score of a flow predicted on such files: the real-data check of `tools/write_pair_records.py --source
files` and `tools/predict.py --method nsfp` (`tests/labels/test_own_records_av2.py`, `benchmarks/own_records_cpu.json`),
and a worked example of converting a dataset with tracked boxes.

`write_log_as_sequence`: each sweep as `<NNNNNN>.npy`, a structured array of x, y, z (float32, ego frame, m) and
intensity (uint8, as Argoverse stores it: the intensity rule divides it by 255, as the Argoverse 2 reader does),
`poses.txt` (ego -> city), `timestamps.txt` (the sweeps' times) and `boxes.csv` of the annotated cuboids (centre, size,
yaw about +z from +x: Argoverse's cuboid conventions are the table's; class = the Argoverse category, mapped by
`AV2_CLASS_MAP`, also written beside as `class_map.yaml`: `argoverse2.AV2_CLASS`'s classes, and every other category
`background`, as the Argoverse 2 reader labels them).
"""
from __future__ import annotations

import os

import numpy as np

from ff3d_tf import metrics_av2, schema
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pair_records
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.files import box_table, point_files, sequences
from ff3d_tf.labels import av2

CLASS_MAP_NAME = "class_map.yaml"
AV2_CLASS_MAP = {c: schema.CLASS_NAMES[argoverse2.AV2_CLASS.get(c, schema.CLASS_BACKGROUND)]
                 for c in argoverse2.ANNOTATION_CATEGORIES}


def write_log_as_sequence(log_dir: str, directory: str, with_boxes: bool = True, pose_files: bool = False) -> str:
    """Writes the log's sweeps as a sequence directory (module docstring); returns it. `pose_files`: each pose as
    `<NNNNNN>.pose.txt` beside its sweep instead of `poses.txt` (a pair of files takes them as --pose_tm1/--pose_t0)."""
    os.makedirs(directory, exist_ok=True)
    stamps = argoverse2.sweep_timestamps(log_dir)
    poses, boxes = [], {}
    for k, ts in enumerate(stamps):
        frame = argoverse2.read_sweep(log_dir, ts)
        stem = f"{k:06d}"
        cloud = np.zeros(len(frame["points_xyz"]), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "u1")])
        for i, axis in enumerate("xyz"):
            cloud[axis] = frame["points_xyz"][:, i]
        cloud["intensity"] = np.rint(frame["intensity"].astype(np.float64) * 255).astype(np.uint8)
        np.save(os.path.join(directory, stem + ".npy"), cloud)
        poses.append(frame["pose"])
        boxes[stem] = argoverse2.cuboids(log_dir, ts)
    rows = [" ".join(repr(float(v)) for v in p[:3].reshape(-1)) + "\n" for p in poses]
    if pose_files:
        for k, row in enumerate(rows):
            with open(os.path.join(directory, f"{k:06d}{point_files.SWEEP_POSE_SUFFIXES[0]}"), "w") as f:
                f.write(row)
    else:
        with open(os.path.join(directory, point_files.POSES_FILE), "w") as f:
            f.write("".join(rows))
    with open(os.path.join(directory, sequences.TIMESTAMPS_FILE), "w") as f:
        f.write("".join(f"{t // 10 ** 9}.{t % 10 ** 9:09d}\n" for t in stamps))
    if with_boxes:
        box_table.write_box_table(os.path.join(directory, box_table.BOX_TABLE_NAMES[0]), boxes)
        with open(os.path.join(directory, CLASS_MAP_NAME), "w") as f:
            f.write("".join(f"{c}: {name}\n" for c, name in AV2_CLASS_MAP.items()))
    return directory


def challenge_scores(log_dir: str, index: int, flow_mps: np.ndarray, point_valid: np.ndarray, gap_s: float) -> dict:
    """The challenge's numbers (`metrics_av2`: three-way EPE, bucketed normalized EPE; metres per frame) of a flow
    predicted for sweep `index`'s points (in the sweep's file order) with sweep `index + 1` as the partner: m/s, the
    motion from the partner to sweep `index` over `gap_s` (the project's convention), no prediction where
    `point_valid` is False (scored as zero flow). The truth, categories and ground are the Argoverse 2 records'
    (`av2.challenge_pair`: Argoverse's labels by its box rule and margin, the map's ground); the points scored are
    the challenge's (`metrics_av2.eval_mask`: not ground, 35 m box). Adds `zero_flow` and the point counts."""
    ex = av2.challenge_pair(log_dir, index, ExperimentConfig())
    flow_mps, point_valid = np.asarray(flow_mps, np.float64), np.asarray(point_valid, bool)
    if flow_mps.shape != ex["points_xyz_t0"].shape or point_valid.shape != (len(flow_mps),):
        raise ValueError(f"a flow of {flow_mps.shape} and validity of {point_valid.shape} for sweep {index}'s "
                         f"{len(ex['points_xyz_t0'])} points")
    true_m = -ex["flow_mps_t0"].astype(np.float64) * pair_records.pair_gap_s(ex)
    pred_m = -np.where(point_valid[:, None], flow_mps, 0.0) * gap_s
    mask = metrics_av2.eval_mask(ex["points_xyz_t0"], ex["is_ground_t0"])
    acc, zero = metrics_av2.AV2FlowAccumulator(), metrics_av2.AV2FlowAccumulator()
    acc.update(true_m, pred_m, ex["category_t0"], mask)
    zero.update(true_m, np.zeros_like(true_m), ex["category_t0"], mask)
    return {"prediction": acc.result(), "zero_flow": zero.result(), "evaluated_points": int(mask.sum()),
            "evaluated_points_without_prediction": int((mask & ~point_valid).sum())}
