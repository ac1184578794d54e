"""ZeroFlow's distillation measured on synthetic WOD data: FastFlow3D trained on NSFP pseudo-labels against the same
model trained on the human labels and against zero flow, scored on held-out human-labelled records.

python tools/benchmark_distillation.py [--out_dir distillation_out] [--json benchmarks/distillation_synthetic.json]
    [--steps 1000] [--train_segments 3 --eval_segments 2 --frames_per_segment 5 --lidar_scale 0.25]
    [--nsfp_max_iterations 400 --nsfp_patience 100 --nsfp_grid_cell_m 0.1 --nsfp_ground_below_z_m 0.3
     --nsfp_crop_m 32] [--config configs/synthetic_cpu.yaml] [--set key=value ...]

Stages (each one of the project's tools as a subprocess, as `tools/demo.py` runs them; its output streams through):
1. synthetic WOD segments, training and held-out (`tools/make_synthetic_data.py`, different seeds);
2. pair records of both (`tools/write_pair_records.py`, with the human labels);
3. NSFP pseudo-labels of the training records (`tools/pseudo_label.py`; the --nsfp_* flags set its config's nsfp
   section: max_iterations, patience, grid_cell_m, crop_xy_half_extent_m, remove_ground_below_z_m, seed);
4. FastFlow3D trained twice on the pseudo-labelled records, same config, seed, steps and input order, once with
   `data.labels=human` and once with `data.labels=pseudo` (ZeroFlow's speed-scaled loss) (`tools/train.py`);
5. both evaluated on the held-out records against their human labels, beside zero flow (`tools/eval.py`);
6. the pseudo-labels scored against the human labels of the training records (same metric, same points as
   training reads: the grid crop), and everything written to --json: EPE on moving / stationary points per class,
   the three-way EPE (foreground dynamic), the eval's full tables, the options, steps and timings.

Resumable (`ff3d_tf.stages`, as `tools/demo.py`): a finished stage leaves `OUT/stages/<stage>.json` (its command, a
hash of the project's code and configs, its outputs' files and sizes, and its seconds); a rerun with the same command
on the same code, its outputs untouched, skips it (its recorded seconds stay in the JSON) and reruns every later stage;
an interrupted stage resumes (the tools skip finished outputs, training restarts from its checkpoint). A stage whose
command or code changed (other NSFP options, another step count, a tool's new defaults) starts again from nothing:
its outputs are removed first.
"""
import argparse
import json
import math
import os
import sys
import time

import _common

from ff3d_tf.stages import StageError, Stages

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
MODELS = ("human", "pseudo")
CLASSES = ("background", "vehicle", "pedestrian", "sign", "cyclist", "all")
SUMMARY_KEYS = tuple(f"{c}/{s}/{stat}" for c in CLASSES for s in ("moving", "stationary")
                     for stat in ("mean_l2_mps", "count")) + (
    "three_way/fg_dynamic_epe_m", "three_way/fg_static_epe_m", "three_way/bg_static_epe_m", "three_way/mean_epe_m",
    "bucketed/mean_dynamic", "bucketed/mean_static")
PLAN = ("generate_train", "generate_eval", "records_train", "records_eval", "pseudo_label") + tuple(
    f"{stage}_{labels}" for stage in ("train", "eval") for labels in MODELS)


def _summary(metrics: dict) -> dict:
    return {k: metrics[k] for k in SUMMARY_KEYS if k in metrics}


def score_pseudo_labels(cfg, files: list[str]) -> tuple[dict, dict, dict]:
    """(pseudo-labels vs human labels, zero flow vs human labels, counts) over the pairs of pseudo-labelled records
    `files`, on the points training reads (`cfg`'s grid crop), with the evaluation's metric."""
    from ff3d_tf.data import pairs
    from ff3d_tf.labels.pseudo_records import PSEUDO_KEY
    from ff3d_tf.metrics import SceneFlowMetrics
    import numpy as np
    pseudo, zero = SceneFlowMetrics(), SceneFlowMetrics()
    counts = {"pairs": 0, "points": 0, "points_with_pseudo_flow": 0}
    for ex in pairs.pair_dataset(files, cfg, extras=(PSEUDO_KEY,)):
        flow_true, flow_pseudo, class_id = ex["flow_mps_t0"], ex[PSEUDO_KEY], ex["class_id_t0"]
        pseudo.update_state(flow_true, flow_pseudo, class_id)
        zero.update_state(flow_true, np.zeros_like(flow_true), class_id)
        counts["pairs"] += 1
        counts["points"] += int(class_id.shape[0])
        counts["points_with_pseudo_flow"] += int(np.any(flow_pseudo.numpy() != 0, axis=1).sum())
    if not counts["pairs"]:
        raise ValueError(f"no pairs in {files}")
    return pseudo.result(), zero.result(), counts


def _clean(value):
    """JSON without NaN: an empty cell (NaN) is written as null."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _run_stages(args, stages: Stages, out: str, config: list[str]) -> None:
    data, records = f"{out}/data", f"{out}/records"
    for split, count, seed in (("train", args.train_segments, 100), ("eval", args.eval_segments, 900)):
        stages.run(f"generate_{split}", [os.path.join(HERE, "make_synthetic_data.py"), "--out_dir", f"{data}/{split}",
                                         "--num_segments", str(count), "--frames_per_segment",
                                         str(args.frames_per_segment), "--seed", str(seed), "--lidar_scale",
                                         str(args.lidar_scale)], [f"{data}/{split}"])
    for split in ("train", "eval"):
        stages.run(f"records_{split}", [os.path.join(HERE, "write_pair_records.py"), "--source", "wod", "--config",
                                        args.config, "--input", f"{data}/{split}", "--out_dir",
                                        f"{records}/{split}"], [f"{records}/{split}"])
    # The job's options are the config's nsfp section (tools/pseudo_label.py takes them as --set nsfp.KEY=VALUE).
    nsfp_sets = {"max_iterations": args.nsfp_max_iterations, "patience": args.nsfp_patience,
                 "grid_cell_m": args.nsfp_grid_cell_m, "crop_xy_half_extent_m": args.nsfp_crop_m,
                 "seed": args.nsfp_seed}
    if args.nsfp_ground_below_z_m >= 0:
        nsfp_sets["remove_ground_below_z_m"] = args.nsfp_ground_below_z_m
    nsfp = [a for key, value in nsfp_sets.items() for a in ("--set", f"nsfp.{key}={value}")] + args.nsfp_arg
    stages.run("pseudo_label", [os.path.join(HERE, "pseudo_label.py"), "--input", f"{records}/train", "--out_dir",
                                f"{records}/train_pseudo", *nsfp], [f"{records}/train_pseudo"])
    # Both models read the same pseudo-labelled records (which keep the human labels beside the pseudo ones): same
    # files, same shuffle, same seed; only data.labels differs.
    for labels in MODELS:
        stages.run(f"train_{labels}", [os.path.join(HERE, "train.py"), *config, "--set", f"data.labels={labels}",
                                       "--data_dir", f"{records}/train_pseudo", "--model_dir",
                                       f"{out}/model_{labels}"], [f"{out}/model_{labels}"])
    for labels in MODELS:
        stages.run(f"eval_{labels}", [os.path.join(HERE, "eval.py"), *config, "--data_dir", f"{records}/eval",
                                      "--checkpoint", f"{out}/model_{labels}", "--out_dir", f"{out}/eval_{labels}"],
                   [f"{out}/eval_{labels}"])


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out_dir", default="distillation_out", help="segments, records, models, metrics")
    p.add_argument("--json", default="benchmarks/distillation_synthetic.json")
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for both trainings and the evaluations (repeatable)")
    p.add_argument("--steps", type=int, default=1000, help="training steps of each model")
    p.add_argument("--seed", type=int, default=0, help="train.seed of both models")
    p.add_argument("--train_segments", type=int, default=3)
    p.add_argument("--eval_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=5)
    p.add_argument("--lidar_scale", type=float, default=0.25, help="< 1 shrinks the range images (fewer points)")
    p.add_argument("--nsfp_max_iterations", type=int, default=400, help="NSFP step cap per pair")
    p.add_argument("--nsfp_patience", type=int, default=100, help="NSFP early stopping")
    p.add_argument("--nsfp_grid_cell_m", type=float, default=0.1, help="NSFP distance transform cell")
    p.add_argument("--nsfp_ground_below_z_m", type=float, default=0.3,
                   help="NSFP drops points below this z (vehicle frame); they get pseudo-flow 0 (< 0: keep all)")
    p.add_argument("--nsfp_crop_m", type=float, default=32.0, help="NSFP fits |x|, |y| <= this; the rest gets 0")
    p.add_argument("--nsfp_seed", type=int, default=0)
    p.add_argument("--nsfp_arg", action="append", default=[], metavar="ARG",
                   help="one more argument for tools/pseudo_label.py (repeatable; write "
                        "--nsfp_arg=--set=nsfp.KEY=VALUE)")
    args = p.parse_args()
    out = os.path.abspath(args.out_dir)
    json_path = os.path.abspath(args.json)
    t0 = time.time()
    # point_bucket_base 8192: the default lidar_scale's ~23K points a cloud padded to a near bucket (the CPU config's
    # 65536 would triple the work); --set overrides it.
    sets = ["data.point_bucket_base=8192", "data.source=pair_records", f"train.num_steps={args.steps}",
            f"train.seed={args.seed}", "train.eval_every_steps=0"] + list(args.set)
    config = ["--config", args.config] + [a for s in sets for a in ("--set", s)]
    records = f"{out}/records"

    stages = Stages(f"{out}/stages", PLAN, cwd=ROOT)
    try:
        _run_stages(args, stages, out, config)
    except StageError as e:
        sys.exit(f"benchmark_distillation: {e}")

    print("\n=== scoring the pseudo-labels against the human labels of the training records", flush=True)
    from ff3d_tf.config import load_config
    from ff3d_tf.data.pairs import list_segment_files
    cfg = load_config(args.config, sets)
    t = time.time()
    pseudo_vs_human, zero_train, label_counts = score_pseudo_labels(cfg, list_segment_files(f"{records}/train_pseudo"))
    score_s = time.time() - t

    metrics = {}
    for labels in MODELS:
        with open(f"{out}/eval_{labels}/metrics.json") as f:
            metrics[labels] = json.load(f)
        with open(f"{out}/eval_{labels}/metrics_zero_flow.json") as f:
            metrics[f"zero_flow_{labels}"] = json.load(f)
    # Zero flow does not depend on the model: both evaluations must give the same figures.
    zero_same = json.dumps(_clean(metrics["zero_flow_human"]), sort_keys=True) == json.dumps(
        _clean(metrics["zero_flow_pseudo"]), sort_keys=True)
    metrics["zero_flow"] = metrics.pop("zero_flow_human")
    del metrics["zero_flow_pseudo"]
    with open(f"{records}/train_pseudo/pseudo_label_counts.json") as f:
        nsfp_counts = json.load(f)
    histories = {}
    for labels in MODELS:
        with open(f"{out}/model_{labels}/train_history.json") as f:
            histories[labels] = json.load(f)

    moving = {k: metrics[k]["all/moving/mean_l2_mps"] for k in ("human", "pseudo", "zero_flow")}
    stationary = {k: metrics[k]["all/stationary/mean_l2_mps"] for k in ("human", "pseudo", "zero_flow")}
    fitted = max(nsfp_counts.get("fitted_pairs", 0), 1)
    result = {
        "what": "FastFlow3D trained on NSFP pseudo-labels (tools/pseudo_label.py, ZeroFlow's loss) vs the same model "
                "trained on the human labels (same config, seed, steps, input records) vs zero flow, on held-out "
                "synthetic WOD records scored against their human labels (tools/eval.py; m/s unless _m)",
        "command": " ".join(["tools/benchmark_distillation.py"] + sys.argv[1:]),
        "verdict": {
            "pseudo_beats_zero_flow_on_moving": bool(moving["pseudo"] < moving["zero_flow"]),
            "all_moving_mean_l2_mps": moving,
            "all_stationary_mean_l2_mps": stationary,
            "pseudo_over_human_moving": moving["pseudo"] / moving["human"] if moving["human"] else None,
            "pseudo_over_zero_flow_moving": moving["pseudo"] / moving["zero_flow"] if moving["zero_flow"] else None,
            "fg_dynamic_epe_m": {k: metrics[k].get("three_way/fg_dynamic_epe_m") for k in metrics},
        },
        "eval_summary": {k: _summary(v) for k, v in metrics.items()},
        "pseudo_labels": {
            "what": "the pseudo-labels (flow_mps_pseudo_t0) against the human labels of the training records, on "
                    "the points training reads; zero flow on the same points for scale",
            "summary": _summary(pseudo_vs_human),
            "zero_flow_summary": _summary(zero_train),
            "points": label_counts,
            "metrics": pseudo_vs_human,
        },
        "eval_metrics": metrics,
        "zero_flow_same_in_both_evaluations": zero_same,
        "options": {
            "config": args.config, "set": sets, "steps": args.steps, "seed": args.seed,
            "train_segments": args.train_segments, "eval_segments": args.eval_segments,
            "frames_per_segment": args.frames_per_segment, "lidar_scale": args.lidar_scale,
            "nsfp": {"max_iterations": args.nsfp_max_iterations, "patience": args.nsfp_patience,
                     "grid_cell_m": args.nsfp_grid_cell_m, "crop_m": args.nsfp_crop_m,
                     "ground_below_z_m": args.nsfp_ground_below_z_m if args.nsfp_ground_below_z_m >= 0 else None,
                     "seed": args.nsfp_seed, "more_pseudo_label_args": args.nsfp_arg,
                     "other": "the config's nsfp defaults (the pseudo-labelled records' config.yaml holds the "
                              "job's whole nsfp section)"},
        },
        "nsfp_job": {**nsfp_counts, "seconds_per_fitted_pair": nsfp_counts.get("nsfp_seconds", 0) / fitted,
                     "iterations_per_fitted_pair": nsfp_counts.get("nsfp_iterations", 0) / fitted},
        "training": {k: {"last_logged_step": h["loss"][-1][0] if h.get("loss") else None,
                         "first_logged_loss": h["loss"][0] if h.get("loss") else None,
                         "last_logged_loss": h["loss"][-1] if h.get("loss") else None}
                     for k, h in histories.items()},
        "timings_s": {**stages.seconds, "score_pseudo_labels": score_s, "total_this_run": time.time() - t0},
        "stages_skipped_this_run": stages.skipped,
        "machine": {"cpus": os.cpu_count(), "load_average_1_5_15": list(os.getloadavg())},
    }
    os.makedirs(os.path.dirname(json_path) or ".", exist_ok=True)
    with open(json_path + ".partial", "w") as f:
        json.dump(_clean(result), f, indent=1, sort_keys=True)
    os.replace(json_path + ".partial", json_path)

    print(f"\n{'on held-out records (human labels), m/s':<44}{'moving':>10}{'stationary':>12}{'fg dyn (m)':>12}")
    for k in ("human", "pseudo", "zero_flow"):
        name = {"human": "FastFlow3D, human labels", "pseudo": "FastFlow3D, NSFP pseudo-labels",
                "zero_flow": "zero flow"}[k]
        print(f"{name:<44}{moving[k]:>10.3f}{stationary[k]:>12.3f}"
              f"{metrics[k].get('three_way/fg_dynamic_epe_m', float('nan')):>12.3f}")
    print(f"{'pseudo-labels vs human, training records':<44}{pseudo_vs_human['all/moving/mean_l2_mps']:>10.3f}"
          f"{pseudo_vs_human['all/stationary/mean_l2_mps']:>12.3f}"
          f"{pseudo_vs_human.get('three_way/fg_dynamic_epe_m', float('nan')):>12.3f}")
    print(f"pseudo-trained beats zero flow on moving points: {result['verdict']['pseudo_beats_zero_flow_on_moving']}")
    print(f"wrote {json_path} ({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    _common.run(main)
