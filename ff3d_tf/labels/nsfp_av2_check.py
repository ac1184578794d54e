"""Pseudo-labels scored against human labels by the Argoverse 2 2024 challenge's arithmetic (`ff3d_tf.metrics_av2`),
beside zero flow: `score_pseudo_records` reads what the pseudo-label job wrote (`ff3d_tf.labels.pseudo_records`, run
on Argoverse 2 records, which carry Argoverse's labels, ground masks and categories), so the score is of the labels
that train the model, made by the job users run (`tools/pseudo_label.py` writes it beside them).

Per pair: the challenge's flow (metres over the pair) of the t0 sweep's points is -flow_mps * gap for the records'
human flow and for the pseudo-labels alike (`ff3d_tf.labels.av2`: records pair each sweep with the next one); the
points scored are the challenge's (`metrics_av2.eval_mask`: not ground, within the 35 m box); an evaluated point
without a pseudo-label (outside the fitted region, or its pair's fit given up) is scored with flow 0 and counted.
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import metrics_av2, schema
from ff3d_tf.data import pair_records, pairs

SCORE_EXTRAS = schema.AV2_EVAL_KEYS + (schema.PSEUDO_FLOW_KEY,)


def scorable(manifest: pair_records.Manifest) -> str:
    """"" if pseudo-label records of this manifest can be scored here, else why not."""
    if manifest.source != "av2" or manifest.partner != "next":
        return "scores are computed for Argoverse 2 records (tools/write_pair_records.py --source av2)"
    if not manifest.human_labels:
        return "the records hold no human labels to score against"
    missing = [k for k in SCORE_EXTRAS if k not in manifest.extras]
    return f"the records hold no {missing}" if missing else ""


def reading_records(cfg, manifest: pair_records.Manifest) -> dict:
    """The config changes that read records of `manifest` whatever the job's config says of the model's input: the
    records' sweeps per example (`data.num_frames`; the pseudo-label job reads a records directory, not the config,
    for it), and a temporal model that reads that many (the model is not run here: only the pair is scored)."""
    changes = {"data.num_frames": manifest.num_frames}
    if manifest.num_frames > 2 and cfg.model.temporal == "pair":
        changes["model.temporal"] = "stack"
    return changes


def score_pseudo_records(files: list[str], cfg) -> dict:
    """{"nsfp": challenge scores of the pseudo-labels, "zero_flow": of zero flow, "pairs", "evaluated_points",
    "evaluated_points_without_pseudo_label", "pairs_without_pseudo_labels"} over every pair of `files` (pseudo-label
    records of Argoverse 2; `cfg` an ExperimentConfig, whose studies are turned off here: every point is scored)."""
    from ff3d_tf.config import replace_config
    manifest = pair_records.manifest_of_files(list(files))
    why = scorable(manifest)
    if why:
        raise ValueError(why)
    has_valid = schema.PSEUDO_VALID_KEY in manifest.extras
    cfg = replace_config(cfg, {"data.source": "pair_records", "data.labels": "human", "data.crop_to_grid": False,
                               "data.remove_ground_below_z_m": None, "data.point_keep_fraction": 1.0,
                               "data.class_ablation": "none", **reading_records(cfg, manifest)})
    extras = SCORE_EXTRAS + ((schema.PSEUDO_VALID_KEY,) if has_valid else ())
    acc, acc_zero = metrics_av2.AV2FlowAccumulator(), metrics_av2.AV2FlowAccumulator()
    count = {"pairs": 0, "evaluated_points": 0, "evaluated_points_without_pseudo_label": 0,
             "pairs_without_pseudo_labels": 0}
    with pairs.input_errors_named(list(files)):
        for ex in pairs.pair_dataset(list(files), cfg, extras=extras, metadata=True):
            ex = {k: v.numpy() for k, v in ex.items()}
            gap_s = pair_records.pair_gap_s(ex)
            valid = ex[schema.PSEUDO_VALID_KEY] if has_valid else np.ones(len(ex["points_xyz_t0"]), bool)
            mask = metrics_av2.eval_mask(ex["points_xyz_t0"], ex["is_ground_t0"])
            true_m = -ex["flow_mps_t0"].astype(np.float64) * gap_s
            pseudo_m = -np.where(valid[:, None], ex[schema.PSEUDO_FLOW_KEY], 0.0).astype(np.float64) * gap_s
            acc.update(true_m, pseudo_m, ex["category_t0"], mask)
            acc_zero.update(true_m, np.zeros_like(true_m), ex["category_t0"], mask)
            count["pairs"] += 1
            count["evaluated_points"] += int(mask.sum())
            count["evaluated_points_without_pseudo_label"] += int((mask & ~valid).sum())
            count["pairs_without_pseudo_labels"] += int(not valid.any())
    if not count["pairs"]:
        raise ValueError(f"no pairs in {files}")
    return {"nsfp": acc.result(), "zero_flow": acc_zero.result(), **count}
