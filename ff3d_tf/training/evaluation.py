"""Evaluation over validation records: the model and the zero-flow baseline side by side."""
from __future__ import annotations

import json
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pairs
from ff3d_tf.metrics import AV2_MAX_DISTANCE_M, CROP_PREFIX, SceneFlowMetrics, published_epe_keys
from ff3d_tf.model.forward import Predictor


def count_pairs(files: list[str]) -> int:
    """Upper bound of pairs (records - 1 per file), read without decoding, for progress and ETA."""
    total = 0
    for f in files:
        n = int(tf.data.TFRecordDataset(f).reduce(np.int64(0), lambda c, _: c + 1).numpy())
        total += max(n - 1, 0)
    return total


def evaluate(cfg: ExperimentConfig, files: list[str], predictor: Predictor, max_pairs: int = 0,
             log_fn=print) -> tuple[dict, dict]:
    """(model metrics, zero-flow metrics) over every pair of `files` (points with a prediction only).

    Each dict also holds the three-way and bucketed EPE within the Argoverse 2 evaluator's 35 m crop, under
    `metrics.CROP_PREFIX`, to set beside published numbers.
    """
    metric, zero = SceneFlowMetrics(), SceneFlowMetrics()
    metric_crop, zero_crop = (SceneFlowMetrics(max_distance_m=AV2_MAX_DISTANCE_M) for _ in range(2))
    total = count_pairs(files)
    if max_pairs:
        total = min(total, max_pairs)
    ds = pairs.pair_dataset(files, cfg)
    if max_pairs:
        ds = ds.take(max_pairs)
    t0, done = time.time(), 0
    with pairs.input_errors_named(files, pairs.decode_options(cfg)):  # a bad record: file, record and field named
        for batch, ex in pairs.padded_singletons(ds, cfg.data.point_bucket_base):
            flow_pred, valid = predictor.predict(batch, ex)
            zero_flow = tf.zeros_like(ex["flow_mps_t0"])
            for m, flow in ((metric, flow_pred), (zero, zero_flow), (metric_crop, flow_pred), (zero_crop, zero_flow)):
                m.update_state(ex["flow_mps_t0"], flow, ex["class_id_t0"], point_valid=valid,
                               points_xyz=ex["points_xyz_t0"])
            done += 1
            if done % 5 == 0 or done == total:
                rate = done / max(time.time() - t0, 1e-9)
                log_fn(f"eval {done}/{total} pairs {rate:.2f} pairs/s "
                       f"ETA {max(total - done, 0) / max(rate, 1e-9):.0f}s")
    if done == 0:
        raise ValueError(f"no frame pairs in {files}")
    return tuple({**full.result(), **{CROP_PREFIX + k: v for k, v in published_epe_keys(crop.result()).items()}}
                 for full, crop in ((metric, metric_crop), (zero, zero_crop)))


def write_results(out_dir: str, result: dict, zero: dict, cfg: ExperimentConfig) -> None:
    tf.io.gfile.makedirs(out_dir)
    for name, r in (("metrics.json", result), ("metrics_zero_flow.json", zero)):
        with tf.io.gfile.GFile(os.path.join(out_dir, name), "w") as f:
            json.dump(r, f, indent=1, sort_keys=True)
    with tf.io.gfile.GFile(os.path.join(out_dir, "metrics.csv"), "w") as f:
        f.write("metric,model,zero_flow\n")
        for k in sorted(result):
            f.write(f"{k},{result[k]:.6g},{zero[k]:.6g}\n")
    cfg.save(os.path.join(out_dir, "config.yaml"))
