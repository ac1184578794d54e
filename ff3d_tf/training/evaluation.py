"""Evaluation over validation records: the model and the zero-flow baseline side by side.

The one evaluation path of any `ff3d_tf.predictor.Predictor` (a checkpoint, a SavedModel, an ONNX file, a portable
XLA export): `evaluate` (the paper's tables), `evaluate_av2` (the Argoverse 2 challenge), and the Trainer's periodic
evaluation (`evaluate` on a few pairs, `write_summaries` to TensorBoard).
"""
from __future__ import annotations

import json
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf import metrics_av2, schema
from ff3d_tf.config import ExperimentConfig, replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.metrics import AV2_MAX_DISTANCE_M, CROP_PREFIX, SceneFlowMetrics, published_epe_keys
from ff3d_tf.predictor import Predictor

# What the Trainer's periodic evaluation writes to TensorBoard (`write_summaries`).
SUMMARY_KEYS = ("all/all/mean_l2_mps", "all/moving/mean_l2_mps", "all/stationary/mean_l2_mps",
                "vehicle/moving/mean_l2_mps", "pedestrian/moving/mean_l2_mps", "cyclist/moving/mean_l2_mps",
                "background/all/mean_l2_mps", "three_way/mean_epe_m")


def count_pairs(files: list[str]) -> int:
    """Upper bound of pairs (records - 1 per segment file, one per pair records file), read without decoding, for
    progress and ETA."""
    total = 0
    for f in files:
        n = int(tf.data.TFRecordDataset(f, compression_type=_compression(f)).reduce(
            np.int64(0), lambda c, _: c + 1).numpy())
        total += n if f.endswith(pair_records.FILE_SUFFIX) else max(n - 1, 0)
    return total


def _compression(path: str) -> str:
    if not path.endswith(pair_records.FILE_SUFFIX):
        return ""
    return "ZLIB" if pair_records.read_manifest(os.path.dirname(path)).compression == "zlib" else ""


def _log_progress(done: int, total: int, t0: float, log_fn) -> None:
    """Every 5 pairs and at the last: pairs done, rate and time left."""
    if done % 5 == 0 or done == total:
        rate = done / max(time.time() - t0, 1e-9)
        log_fn(f"eval {done}/{total} pairs {rate:.2f} pairs/s ETA {max(total - done, 0) / max(rate, 1e-9):.0f}s")


def evaluate(cfg: ExperimentConfig, files: list[str], predictor: Predictor, max_pairs: int = 0,
             log_fn=print) -> tuple[dict, dict]:
    """(model metrics, zero-flow metrics) over every pair of `files`, or the first `max_pairs` (points with a
    prediction only). `log_fn` gets the progress (None: silent, and the pairs are not counted first).

    Each dict also holds the three-way and bucketed EPE within the Argoverse 2 evaluator's 35 m crop, under
    `metrics.CROP_PREFIX`, to set beside published numbers.
    """
    metric, zero = SceneFlowMetrics(), SceneFlowMetrics()
    metric_crop, zero_crop = (SceneFlowMetrics(max_distance_m=AV2_MAX_DISTANCE_M) for _ in range(2))
    total = 0 if log_fn is None else count_pairs(files)
    if max_pairs and log_fn is not None:
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
            if log_fn is not None:
                _log_progress(done, total, t0, log_fn)
    if done == 0:
        raise ValueError(f"no frame pairs in {files}")
    return tuple({**full.result(), **{CROP_PREFIX + k: v for k, v in published_epe_keys(crop.result()).items()}}
                 for full, crop in ((metric, metric_crop), (zero, zero_crop)))


def challenge_flow_m(flow_mps, example: dict) -> np.ndarray:
    """[N,3] metres over the pair, the challenge's forward flow of the t0 (first) sweep's points, from the model's
    quantity in m/s of an Argoverse 2 challenge record (partner = next sweep: flow_mps = (p_t0 - p_next) / dt)."""
    dt_s = (int(example[pair_records.PARTNER_TIMESTAMP_KEY]) - int(example[pair_records.TIMESTAMP_KEY])) * 1e-9
    return -np.asarray(flow_mps, np.float64) * dt_s


def av2_challenge_examples(cfg: ExperimentConfig, files: list[str], predictor: Predictor, max_pairs: int = 0,
                           log_fn=print):
    """(example, predicted m/s, prediction valid, eval mask) per pair of Argoverse 2 challenge records, in order.

    Every point is kept (no grid crop: the challenge scores every eval-mask point; a point the model cannot see gets
    flow 0). Raises ValueError unless `files` are Argoverse 2 records paired with the next sweep
    (`tools/write_pair_records.py --source av2`).
    """
    if cfg.data.source != "pair_records":
        raise ValueError("the Argoverse 2 protocol reads pair records: --set data.source=pair_records and "
                         "--data_dir of `tools/write_pair_records.py --source av2`")
    manifest = pair_records.manifest_of_files(list(files))
    if manifest.source != "av2" or manifest.partner != "next":
        raise ValueError(f"{os.path.dirname(files[0])}: records of {manifest.source} paired with the "
                         f"{manifest.partner} sweep; the Argoverse 2 protocol needs Argoverse 2 records paired with "
                         "the next sweep (tools/write_pair_records.py --source av2)")
    cfg = replace_config(cfg, {"data.crop_to_grid": False, "data.labels": "human"})
    total = count_pairs(files) if not max_pairs else min(count_pairs(files), max_pairs)
    ds = pairs.pair_dataset(files, cfg, extras=schema.AV2_EVAL_KEYS, metadata=True)
    if max_pairs:
        ds = ds.take(max_pairs)
    t0, done = time.time(), 0
    with pairs.input_errors_named(files):
        for batch, ex in pairs.padded_singletons(ds, cfg.data.point_bucket_base):
            flow_pred, valid = predictor.predict(batch, ex)
            ex = {k: v.numpy() for k, v in ex.items()}
            valid = np.asarray(valid)
            mask = metrics_av2.eval_mask(ex["points_xyz_t0"], ex["is_ground_t0"])
            yield ex, np.where(valid[:, None], np.asarray(flow_pred), 0.0), valid, mask
            done += 1
            _log_progress(done, total, t0, log_fn)
    if done == 0:
        raise ValueError(f"no pairs in {files}")


def evaluate_av2(cfg: ExperimentConfig, files: list[str], predictor: Predictor, max_pairs: int = 0,
                 log_fn=print) -> dict:
    """The Argoverse 2 2024 challenge's numbers (`metrics_av2`: three-way EPE, bucketed normalized EPE; metres per
    frame) of the model and of zero flow over the eval-mask points of every pair, and the paper's tables (m/s) on
    the same points. Returns {"model": ..., "zero_flow": ..., "paper_model": ..., "paper_zero_flow": ...,
    "points_without_prediction": n (eval-mask points outside the model's grid, scored with flow 0)}."""
    acc, acc_zero = metrics_av2.AV2FlowAccumulator(), metrics_av2.AV2FlowAccumulator()
    paper, paper_zero = SceneFlowMetrics(), SceneFlowMetrics()
    unseen = 0
    for ex, flow_pred, valid, mask in av2_challenge_examples(cfg, files, predictor, max_pairs, log_fn):
        true_m = challenge_flow_m(ex["flow_mps_t0"], ex)
        acc.update(true_m, challenge_flow_m(flow_pred, ex), ex["category_t0"], mask)
        acc_zero.update(true_m, np.zeros_like(true_m), ex["category_t0"], mask)
        for m, flow in ((paper, flow_pred), (paper_zero, np.zeros_like(flow_pred))):
            m.update_state(ex["flow_mps_t0"], flow.astype(np.float32), ex["class_id_t0"], point_valid=mask)
        unseen += int(np.sum(mask & ~valid))
    return {"model": acc.result(), "zero_flow": acc_zero.result(), "paper_model": paper.result(),
            "paper_zero_flow": paper_zero.result(), "points_without_prediction": unseen}


def write_summaries(log_dir: str, step: int, result: dict) -> None:
    """The `SUMMARY_KEYS` of an `evaluate` result (those that are not NaN) as TensorBoard scalars at `step`."""
    writer = tf.summary.create_file_writer(log_dir)
    with writer.as_default(step=step):
        for key in SUMMARY_KEYS:
            if not np.isnan(result[key]):
                tf.summary.scalar(key, result[key])
    writer.flush()


EVAL_CONFIG_NAME = "eval_config.yaml"  # not config.yaml: results often go into the model dir, whose config that is


def write_results(out_dir: str, result: dict, zero: dict, cfg: ExperimentConfig) -> None:
    """metrics.json, metrics_zero_flow.json, metrics.csv and the evaluation's config (`EVAL_CONFIG_NAME`)."""
    tf.io.gfile.makedirs(out_dir)
    for name, r in (("metrics.json", result), ("metrics_zero_flow.json", zero)):
        with tf.io.gfile.GFile(os.path.join(out_dir, name), "w") as f:
            json.dump(r, f, indent=1, sort_keys=True)
    with tf.io.gfile.GFile(os.path.join(out_dir, "metrics.csv"), "w") as f:
        f.write("metric,model,zero_flow\n")
        for k in sorted(result):
            f.write(f"{k},{result[k]:.6g},{zero[k]:.6g}\n")
    cfg.save(os.path.join(out_dir, EVAL_CONFIG_NAME))
