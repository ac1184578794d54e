"""Evaluation over validation records: the model and the zero-flow baseline side by side.

The one evaluation path of any `ff3d_tf.predictor.Predictor` (a checkpoint, a SavedModel, an ONNX file, a portable
XLA export): `evaluate` (the paper's tables), `evaluate_av2` (the Argoverse 2 challenge, on its official masks when
given), `write_av2_submission` (an Argoverse 2 leaderboard archive, `ff3d_tf.data.av2.av2_submission`), and the
Trainer's periodic evaluation (`evaluate` on a few pairs, `write_summaries` to TensorBoard).
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time

import numpy as np
import tensorflow as tf

from ff3d_tf import geometry, metrics_av2, schema
from ff3d_tf.config import ConfigError, ExperimentConfig, replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.av2 import av2_submission
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
        for batch, ex in pairs.padded_singletons(ds, cfg.data.point_bucket_base, cfg.data.drop_ground):
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


def _check_av2_records(cfg: ExperimentConfig, files: list[str]) -> None:
    """Raises ConfigError unless `files` are Argoverse 2 records paired with the next sweep, read as pair records."""
    if cfg.data.source != "pair_records":
        raise ConfigError("the Argoverse 2 protocol reads pair records: --set data.source=pair_records and "
                         "--data_dir of `tools/write_pair_records.py --source av2`")
    manifest = pair_records.manifest_of_files(list(files))
    if manifest.source != "av2" or manifest.partner != "next":
        raise ConfigError(f"{os.path.dirname(files[0])}: records of {manifest.source} paired with the "
                         f"{manifest.partner} sweep; the Argoverse 2 protocol needs Argoverse 2 records paired with "
                         "the next sweep (tools/write_pair_records.py --source av2)")


def list_av2_record_sweeps(cfg: ExperimentConfig, files: list[str]) -> list[av2_submission.RecordSweep]:
    """The first sweep of every pair record of `files` (log, timestamp, next sweep's timestamp, point count, file),
    read from the records' scalar fields only (no point array is decoded), in file order."""
    _check_av2_records(cfg, files)
    spec = {pair_records.SEQUENCE_KEY: tf.io.FixedLenFeature([], tf.string),
            **{k: tf.io.FixedLenFeature([], tf.int64) for k in (pair_records.TIMESTAMP_KEY,
                                                                pair_records.PARTNER_TIMESTAMP_KEY, "num_points_t0")}}
    out = []
    with pairs.input_errors_named(files):
        for path in files:
            ds = tf.data.TFRecordDataset(path, compression_type=_compression(path)).map(
                lambda record: tf.io.parse_single_example(record, spec))
            for f in ds.as_numpy_iterator():
                out.append(av2_submission.RecordSweep(
                    f[pair_records.SEQUENCE_KEY].decode(), int(f[pair_records.TIMESTAMP_KEY]),
                    int(f[pair_records.PARTNER_TIMESTAMP_KEY]), int(f["num_points_t0"]), path))
    if not out:
        raise ValueError(f"no pairs in {files}")
    return out


def _sweep_name(log_id, timestamp_ns):
    """A sweep's key as one string, <log_id>/<timestamp_ns> (of tensors or of Python values)."""
    if isinstance(log_id, str):
        return f"{log_id}/{int(timestamp_ns)}"
    return tf.strings.join([log_id, "/", tf.strings.as_string(timestamp_ns)])


def av2_challenge_examples(cfg: ExperimentConfig, files: list[str], predictor: Predictor, max_pairs: int = 0,
                           log_fn=print, sweeps: set[tuple[str, int]] | None = None, inference_only: bool = False):
    """(example, predicted m/s, prediction valid, 35 m eval mask) per pair of Argoverse 2 challenge records, in order;
    with `sweeps` ({(log_id, timestamp_ns)}) only those pairs (the others are never given to the predictor).

    Every point is kept (no grid crop: the challenge scores every eval-mask point; a point the model cannot see gets
    flow 0). Raises ValueError unless `files` are Argoverse 2 records paired with the next sweep
    (`tools/write_pair_records.py --source av2`). `inference_only` (a submission): unlabelled records
    (`--no_labels`, the test split) serve too; their examples hold no `category_t0` and flow 0.
    """
    _check_av2_records(cfg, files)
    labelled = pair_records.manifest_of_files(list(files)).human_labels
    if sweeps is not None and not sweeps:
        return
    cfg = replace_config(cfg, {"data.crop_to_grid": False, "data.labels": "human"})
    total = count_pairs(files) if sweeps is None else len(sweeps)
    total = min(total, max_pairs) if max_pairs else total
    ds = pairs.pair_dataset(files, cfg, extras=schema.AV2_EVAL_KEYS if labelled else ("is_ground_t0",),
                            metadata=True, inference_only=inference_only)
    if sweeps is not None:
        names = sorted(_sweep_name(*k) for k in sweeps)
        table = tf.lookup.StaticHashTable(tf.lookup.KeyValueTensorInitializer(
            tf.constant(names), tf.ones(len(names), tf.int32)), default_value=0)
        ds = ds.filter(lambda ex: table.lookup(_sweep_name(ex[pair_records.SEQUENCE_KEY],
                                                           ex[pair_records.TIMESTAMP_KEY])) == 1)
    if max_pairs:
        ds = ds.take(max_pairs)
    t0, done = time.time(), 0
    with pairs.input_errors_named(files):
        for batch, ex in pairs.padded_singletons(ds, cfg.data.point_bucket_base, cfg.data.drop_ground):
            flow_pred, valid = predictor.predict(batch, ex)
            ex = {k: v.numpy() for k, v in ex.items()}
            valid = np.asarray(valid)
            mask = metrics_av2.eval_mask(ex["points_xyz_t0"], ex["is_ground_t0"])
            yield ex, np.where(valid[:, None], np.asarray(flow_pred), 0.0), valid, mask
            done += 1
            _log_progress(done, total, t0, log_fn)
    if done == 0 and sweeps is None:
        raise ValueError(f"no pairs in {files}")


def _sweep_key(example: dict) -> tuple[str, int]:
    log_id = example[pair_records.SEQUENCE_KEY]
    return (log_id.decode() if isinstance(log_id, bytes) else str(log_id)), int(example[pair_records.TIMESTAMP_KEY])


def evaluate_av2(cfg: ExperimentConfig, files: list[str], predictor: Predictor, max_pairs: int = 0,
                 log_fn=print, masks: str | None = None) -> dict:
    """The Argoverse 2 2024 challenge's numbers (`metrics_av2`: three-way EPE, bucketed normalized EPE; metres per
    frame) of the model and of zero flow, and the paper's tables (m/s) on the same points.

    The points: without `masks`, those of `metrics_av2.eval_mask` (not ground, 35 m box) of every pair; with `masks`
    (the official `{val,test}-masks.zip`, `av2_submission.MaskArchive`), exactly the archive's sweeps and the points
    its masks select, as the leaderboard scores them (every sweep of the archive needs a record of as many points).
    Returns {"model": ..., "zero_flow": ..., "paper_model": ..., "paper_zero_flow": ..., "points_without_prediction":
    n (scored points outside the model's grid, scored with flow 0), "points": what chose the points}."""
    acc, acc_zero = metrics_av2.AV2FlowAccumulator(), metrics_av2.AV2FlowAccumulator()
    paper, paper_zero = SceneFlowMetrics(), SceneFlowMetrics()
    unseen = 0
    archive, records, sweeps = None, {}, None
    if masks is not None:
        archive = av2_submission.MaskArchive(masks)
        plan = av2_submission.plan_submission(av2_submission.LAYOUTS["v1"], list_av2_record_sweeps(cfg, files),
                                              archive)  # every sweep of the masks has a record of its length
        records = {(p.log_id, p.timestamp_ns): p for p in plan}
        sweeps = set(records)
    try:
        for ex, flow_pred, valid, mask in av2_challenge_examples(cfg, files, predictor, max_pairs, log_fn, sweeps):
            if archive is not None:
                key = _sweep_key(ex)
                mask = archive.checked_mask(key, len(ex["points_xyz_t0"]), records[key].where)
            true_m = challenge_flow_m(ex["flow_mps_t0"], ex)
            acc.update(true_m, challenge_flow_m(flow_pred, ex), ex["category_t0"], mask)
            acc_zero.update(true_m, np.zeros_like(true_m), ex["category_t0"], mask)
            for m, flow in ((paper, flow_pred), (paper_zero, np.zeros_like(flow_pred))):
                m.update_state(ex["flow_mps_t0"], flow.astype(np.float32), ex["class_id_t0"], point_valid=mask)
            unseen += int(np.sum(mask & ~valid))
    finally:
        if archive is not None:
            archive.close()
    return {"model": acc.result(), "zero_flow": acc_zero.result(), "paper_model": paper.result(),
            "paper_zero_flow": paper_zero.result(), "points_without_prediction": unseen,
            "points": f"official masks {masks}" if masks else "metrics_av2.eval_mask (not ground, 35 m box)"}


def _submission_selection(lay, masks: str | None, archive) -> tuple[str, list[str]]:
    """What chooses a submission's sweeps and rows in layout `lay`, in words, and the notes a user must read."""
    if not lay.masks_choose_sweeps:
        return "the 2024 evaluator's sweeps (indices 0, 5, 10, ... of each log), every point" + (
            f"; logs and point counts checked against {masks}" if masks else ""), []
    if archive is not None:
        return f"the sweeps{' and rows' if lay.mask_rows else ''} of the official masks {masks}", []
    rows = " and rows (|x|, |y| <= 50 m, not ground)" if lay.mask_rows else ""
    return "av2-api's rule as this project computes it, for local validation only", [
        f"NOTE: no --masks: the sweeps (every 5th pair){rows} follow av2-api's rule as this project computes it, for "
        f"local validation only; a leaderboard checks the official masks' sweeps and row counts "
        f"({av2_submission.MASKS_SOURCE})"]


def _submission_resume_state(plan, parts: str, lay) -> tuple[dict, dict]:
    """The plan's sweeps sorted by what an interrupted run of the same fingerprint left under `parts`: (expected
    {entry: rows} of those written, the plan's rows where it knows them, else the file's; todo {(log id, timestamp):
    sweep} of those not written yet)."""
    expected, todo = {}, {}
    for p in plan:
        path = os.path.join(parts, *p.entry.split("/"))
        if not os.path.exists(path):
            todo[(p.log_id, p.timestamp_ns)] = p
        else:  # the rows of av2-api's rule are the same for the same records: the fingerprint says they are
            expected[p.entry] = p.rows if p.rows is not None else \
                len(av2_submission.read_sweep_file(path, lay)[lay.columns[0]])
    return expected, todo


def _write_submission_sweeps(cfg, files, predictor, lay, archive, parts: str, todo: dict, expected: dict,
                             log_fn) -> None:
    """Predicts and writes every sweep of `todo` under `parts`, adding each one's entry and rows to `expected`; a
    planned sweep whose record is not read back is an error."""
    for ex, flow_pred, _, _ in av2_challenge_examples(cfg, files, predictor, 0, log_fn, set(todo),
                                                      inference_only=True):
        key = _sweep_key(ex)
        points = ex["points_xyz_t0"]
        p = todo.pop(key)
        rows = None
        if lay.mask_rows:
            rows = archive.checked_mask(key, len(points), p.where) if archive is not None else \
                av2_submission.av2_api_rule_mask(points, ex["is_ground_t0"])
        ego1_from_ego0 = geometry.t0_from_tm1_np(ex["pose_tm1"], ex["pose_t0"])  # partner (next sweep) <- t0
        columns = av2_submission.sweep_columns(lay, points, challenge_flow_m(flow_pred, ex), ego1_from_ego0, rows)
        av2_submission.write_sweep(parts, lay, p.entry, columns)
        expected[p.entry] = len(columns[lay.columns[0]])
    if todo:
        p = next(iter(todo.values()))
        raise ValueError(f"{p.where}: the record of {p.log_id}/{p.timestamp_ns} was listed but not read back")


def submission_fingerprint(cfg: ExperimentConfig, files: list[str], model: dict, leaderboard: str, split: str,
                           masks: str | None) -> dict:
    """What makes a submission's sweeps, as JSON (`av2_submission.claim_parts`): the model (`model`, the caller's
    description of what predicts: its kind and the hash of its files), the resolved config, the records (their
    manifest, and each file's name and size), the layout, the split and the masks (name and size)."""
    manifest = dataclasses.asdict(pair_records.manifest_of_files(list(files)))
    manifest.pop("written_by")
    return {"model": model, "config": cfg.to_dict(), "leaderboard": leaderboard, "split": split,
            "records": {"manifest": manifest,
                        "files": [[os.path.basename(f), tf.io.gfile.stat(f).length] for f in files]},
            "masks": None if masks is None else [os.path.basename(masks), os.path.getsize(masks)]}


def write_av2_submission(cfg: ExperimentConfig, files: list[str], predictor: Predictor, out_zip: str,
                         leaderboard: str, split: str, masks: str | None = None, format_json: str | None = None,
                         max_pairs: int = 0, supervised: bool = True, log_fn=print, model: dict | None = None
                         ) -> dict:
    """An Argoverse 2 scene-flow submission of `predictor` over the records `files`, in the layout of `leaderboard`
    ("v1", "v2", "v3": `av2_submission.LAYOUTS`), zipped to `out_zip`, read back and checked before it is returned.

    `masks`: the official `{split}-masks.zip`, which chooses the sweeps (v1, v3) and v1's rows; every sweep of it needs
    a record of as many points (errors name both). Without it a "test" split is refused; a "val" split falls back to
    av2-api's rule (`av2_submission.av2_api_rule_subset`, `av2_api_rule_mask`), for local validation only.
    `format_json`: av2-api's `{split}_submission_format.json`, whose entries (and, for v1, row counts) the archive
    must match. `supervised`: v2's metadata.json. `max_pairs`: the first planned sweeps only (a partial archive, a
    check of the pipeline, never a submission). `model`: what predicts, as JSON (the tool's: the model's kind and
    the hash of its files; default the predictor's class).

    The sweeps are written under `<out_zip>.parts/` with the run's fingerprint (`submission_fingerprint`): an
    interrupted run resumes there, keeping its sweeps; a folder left by a run of another model, config, records,
    layout or masks stops the job naming what differs (`av2_submission.claim_parts`). The folder is removed once
    the archive is checked.
    Returns the archive's summary ({"sweeps", "rows", "logs"}) with "leaderboard", "selection" (what chose sweeps
    and rows), "partial" and "notes"."""
    lay = av2_submission.layout(leaderboard)
    if split not in ("val", "test"):
        raise ConfigError(f"split {split!r}: expected val or test")
    if masks is None and split == "test":
        raise ConfigError("a test submission needs the official masks (--masks TEST_MASKS.zip): the leaderboards "
                         f"evaluate their points only; {av2_submission.MASKS_SOURCE}")
    archive = av2_submission.MaskArchive(masks) if masks else None
    try:
        plan = av2_submission.plan_submission(lay, list_av2_record_sweeps(cfg, files), archive)
        selection, notes = _submission_selection(lay, masks, archive)
        if max_pairs:
            plan = plan[:max_pairs]
            notes.append(f"NOTE: --max_pairs {max_pairs}: a partial archive of {len(plan)} sweeps, not a submission")
        for note in notes:
            log_fn(note)
        format_rows = None
        if format_json:
            format_rows = av2_submission.expected_counts_from_json(format_json)
            if max_pairs:
                format_rows = {e: n for e, n in format_rows.items() if e in {p.entry for p in plan}}
            av2_submission.check_against_format_json(lay, {p.entry: p.rows for p in plan}, format_rows, format_json)
        parts = out_zip + ".parts"
        av2_submission.claim_parts(parts, submission_fingerprint(
            cfg, files, model or {"predictor": type(predictor).__name__}, lay.name, split, masks))
        expected, todo = _submission_resume_state(plan, parts, lay)
        log_fn(f"{len(plan)} sweeps in layout {lay.name} ({lay.leaderboard}); {len(plan) - len(todo)} already "
               f"written under {parts} by an interrupted run of the same model, config and records")
        t0 = time.time()
        _write_submission_sweeps(cfg, files, predictor, lay, archive, parts, todo, expected, log_fn)
        log_fn(f"{len(plan)} sweeps written in {time.time() - t0:.0f} s; zipping and checking {out_zip}")
        if format_rows is not None and lay.mask_rows:
            expected = format_rows  # Argoverse's validator: every entry of the JSON with its row count
        summary = av2_submission.make_archive(parts, out_zip, lay, expected, supervised)
    finally:
        if archive is not None:
            archive.close()
    shutil.rmtree(parts)  # the archive holds them, checked
    return {**summary, "leaderboard": lay.name, "selection": selection, "partial": bool(max_pairs), "notes": notes}


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
