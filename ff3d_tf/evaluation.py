"""Evaluation over validation records: the model and the zero-flow baseline side by side."""
from __future__ import annotations

import json
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data import pairs
from ff3d_tf.metrics import SceneFlowMetrics
from ff3d_tf.training import model_inputs, predict_function


def count_pairs(files: list[str]) -> int:
    """Upper bound of pairs (records - 1 per file), read without decoding, for progress and ETA."""
    total = 0
    for f in files:
        n = int(tf.data.TFRecordDataset(f).reduce(np.int64(0), lambda c, _: c + 1).numpy())
        total += max(n - 1, 0)
    return total


def raw_tm1_points(example: dict) -> np.ndarray:
    """The t-1 cloud back in its own vehicle frame ([N1,5] with features), for SavedModel serving input."""
    t = np.linalg.inv(np.linalg.inv(example["pose_t0"]) @ example["pose_tm1"])
    xyz = example["points_xyz_tm1_in_t0"].astype(np.float64) @ t[:3, :3].T + t[:3, 3]
    return np.concatenate([xyz.astype(np.float32), example["point_features_tm1"]], -1)


def evaluate(cfg: ExperimentConfig, files: list[str], model=None, saved_model=None, max_pairs: int = 0,
             log_fn=print) -> tuple[dict, dict]:
    """(model metrics, zero-flow metrics) over every pair of `files` (points with a prediction only)."""
    metric, zero = SceneFlowMetrics(), SceneFlowMetrics()
    total = count_pairs(files)
    if max_pairs:
        total = min(total, max_pairs)
    ds = pairs.pair_dataset(files, cfg)
    if max_pairs:
        ds = ds.take(max_pairs)
    predict = predict_function(model, cfg.model.jit_compile) if model is not None else None
    t0, done = time.time(), 0
    with pairs.input_errors_named(files):  # a bad record: FrameDecodeError naming file, record and field
        for batch, ex in pairs.padded_singletons(ds, cfg.data.point_bucket_base):
            if predict is not None:
                n = int(ex["num_points_t0"])
                out = predict(model_inputs(batch))
                flow_pred, valid = out["flow_mps"][0, :n], out["point_valid"][0, :n]
            else:
                exn = {k: v.numpy() for k, v in ex.items()}
                points_t0 = np.concatenate([exn["points_xyz_t0"], exn["point_features_t0"]], -1)
                out = saved_model(raw_tm1_points(exn), points_t0, exn["pose_tm1"], exn["pose_t0"])
                flow_pred, valid = out["flow_mps"], out["point_valid"]
            metric.update_state(ex["flow_mps_t0"], flow_pred, ex["class_id_t0"], point_valid=valid)
            zero.update_state(ex["flow_mps_t0"], tf.zeros_like(ex["flow_mps_t0"]), ex["class_id_t0"],
                              point_valid=valid)
            done += 1
            if done % 5 == 0 or done == total:
                rate = done / max(time.time() - t0, 1e-9)
                log_fn(f"eval {done}/{total} pairs {rate:.2f} pairs/s "
                       f"ETA {max(total - done, 0) / max(rate, 1e-9):.0f}s")
    if done == 0:
        raise ValueError(f"no frame pairs in {files}")
    return metric.result(), zero.result()


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
