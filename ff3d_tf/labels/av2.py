"""Argoverse 2 pairs labelled by the paper's rule: flow of each t0 point from the cuboids of two sweeps
(`ff3d_tf.labels.box_flow.bootstrap_flow`), read through `ff3d_tf.data.argoverse2`."""
from __future__ import annotations

import os

import tensorflow as tf

from ff3d_tf.data import argoverse2
from ff3d_tf.data.pairs import make_pair
from ff3d_tf.labels.box_flow import bootstrap_flow


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
