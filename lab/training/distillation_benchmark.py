"""ZeroFlow's distillation measured on synthetic WOD data, the job of `lab/tools/benchmark_distillation.py`: FastFlow3D
trained on NSFP pseudo-labels against the same model trained on the human labels and against zero flow, scored on
held-out human-labelled records.

Stages (`stage_plan`), each one of the project's tools as a subprocess run by `ff3d_tf.stages` (resumable, its
output streaming through):
1. synthetic WOD segments, training and held-out (`tools/make_synthetic_data.py`, different seeds);
2. pair records of both (`tools/write_pair_records.py`, with the human labels);
3. NSFP pseudo-labels of the training records (`tools/pseudo_label.py`; `Options.nsfp_sets` set its config's nsfp
   section);
4. FastFlow3D trained twice on the pseudo-labelled records, same config, seed, steps and input order, once with
   `data.labels=human` and once with `data.labels=pseudo` (ZeroFlow's speed-scaled loss) (`tools/train.py`);
5. both evaluated on the held-out records against their human labels, beside zero flow (`tools/eval.py`).
Then `run` scores the pseudo-labels against the human labels of the training records (`score_pseudo_labels`), gathers
every figure into one result (`summary`: EPE on moving / stationary points per class, the three-way EPE, the eval's
full tables, the options, steps and timings), writes it as JSON (`write_json`) and returns it; `table` is its
headline. The runner process imports TensorFlow only to score the pseudo-labels, after every stage.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from typing import Callable

from ff3d_tf import cpu
from ff3d_tf.stages import Stages
from lab import bench
from lab.paths import ROOT, TOOLS_DIR

MODELS = ("human", "pseudo")  # the labels each model trains on (data.labels)
RUNS = MODELS + ("zero_flow",)  # the rows of the result: both models and zero flow
CLASSES = ("background", "vehicle", "pedestrian", "sign", "cyclist", "all")
SUMMARY_KEYS = tuple(f"{c}/{s}/{stat}" for c in CLASSES for s in ("moving", "stationary")
                     for stat in ("mean_l2_mps", "count")) + (
    "three_way/fg_dynamic_epe_m", "three_way/fg_static_epe_m", "three_way/bg_static_epe_m", "three_way/mean_epe_m",
    "bucketed/mean_dynamic", "bucketed/mean_static")
PLAN = ("generate_train", "generate_eval", "records_train", "records_eval", "pseudo_label") + tuple(
    f"{stage}_{labels}" for stage in ("train", "eval") for labels in MODELS)
RUN_NAMES = {"human": "FastFlow3D, human labels", "pseudo": "FastFlow3D, NSFP pseudo-labels",
             "zero_flow": "zero flow"}
SPLIT_SEEDS = {"train": 100, "eval": 900}  # make_synthetic_data.py --seed of each split


def print_line(line: str) -> None:
    """The default `log`: the line on stdout, flushed."""
    print(line, flush=True)


@dataclasses.dataclass(frozen=True)
class Options:
    """What the benchmark runs: the tool's flags."""
    config: str  # the config file of the trainings, evaluations and pair records ("" = built-in defaults)
    sets: tuple[str, ...]  # the user's config overrides (KEY=VALUE), applied after the benchmark's own
    steps: int  # training steps of each model
    seed: int  # train.seed of both models
    train_segments: int
    eval_segments: int
    frames_per_segment: int
    lidar_scale: float  # < 1 shrinks the synthetic range images (fewer points)
    nsfp_max_iterations: int  # NSFP step cap per pair
    nsfp_patience: int  # NSFP early stopping (steps)
    nsfp_grid_cell_m: float  # NSFP distance transform cell
    nsfp_ground_below_z_m: float  # NSFP drops points below this z (vehicle frame); < 0: keeps every point
    nsfp_crop_m: float  # NSFP fits |x|, |y| <= this
    nsfp_seed: int
    nsfp_args: tuple[str, ...] = ()  # more arguments of tools/pseudo_label.py

    def config_sets(self) -> list[str]:
        """The config overrides of both trainings and the evaluations: the benchmark's, then `sets`."""
        # point_bucket_base 8192: the default lidar_scale's ~23K points a cloud padded to a near bucket (the CPU
        # config's 65536 would triple the work); `sets` may override it.
        return ["data.point_bucket_base=8192", "data.source=pair_records", f"train.num_steps={self.steps}",
                f"train.seed={self.seed}", "train.eval_every_steps=0"] + list(self.sets)

    def nsfp_sets(self) -> dict:
        """{key: value} of the config's nsfp section that the pseudo-labelling job is given."""
        found = {"max_iterations": self.nsfp_max_iterations, "patience": self.nsfp_patience,
                 "grid_cell_m": self.nsfp_grid_cell_m, "crop_xy_half_extent_m": self.nsfp_crop_m,
                 "seed": self.nsfp_seed}
        if self.nsfp_ground_below_z_m >= 0:
            found["remove_ground_below_z_m"] = self.nsfp_ground_below_z_m
        return found

    def as_json(self) -> dict:
        """The options as the result's "options" records them."""
        return {
            "config": self.config, "set": self.config_sets(), "steps": self.steps, "seed": self.seed,
            "train_segments": self.train_segments, "eval_segments": self.eval_segments,
            "frames_per_segment": self.frames_per_segment, "lidar_scale": self.lidar_scale,
            "nsfp": {"max_iterations": self.nsfp_max_iterations, "patience": self.nsfp_patience,
                     "grid_cell_m": self.nsfp_grid_cell_m, "crop_m": self.nsfp_crop_m,
                     "ground_below_z_m": self.nsfp_ground_below_z_m if self.nsfp_ground_below_z_m >= 0 else None,
                     "seed": self.nsfp_seed, "more_pseudo_label_args": list(self.nsfp_args),
                     "other": "the config's nsfp defaults (the pseudo-labelled records' config.yaml holds the "
                              "job's whole nsfp section)"},
        }


@dataclasses.dataclass(frozen=True)
class Stage:
    name: str  # one of PLAN
    command: list[str]  # a tool's path and its arguments
    outputs: list[str]  # the files and folders it writes


def run_stages(plan: list[Stage], out_dir: str, log: Callable[[str], None]) -> Stages:
    """Runs (or resumes, `ff3d_tf.stages`) each stage of `plan` in order, recorded under `out_dir`/stages; returns the
    runner (its `seconds` and `skipped`). A stage that fails raises `ff3d_tf.stages.StageError`."""
    stages = Stages(f"{out_dir}/stages", [s.name for s in plan], cwd=ROOT, log=log)
    for stage in plan:
        stages.run(stage.name, stage.command, stage.outputs)
    return stages


def stage_plan(options: Options, out_dir: str, tools_dir: str = TOOLS_DIR) -> list[Stage]:
    """The stages of the module docstring, in `PLAN`'s order, writing under `out_dir`."""
    data, records = f"{out_dir}/data", f"{out_dir}/records"
    config = ["--config", options.config] + [a for s in options.config_sets() for a in ("--set", s)]

    def tool(name):
        return os.path.join(tools_dir, name)

    plan = [Stage(f"generate_{split}", [tool("make_synthetic_data.py"), "--out_dir", f"{data}/{split}",
                                        "--num_segments", str(count), "--frames_per_segment",
                                        str(options.frames_per_segment), "--seed", str(SPLIT_SEEDS[split]),
                                        "--lidar_scale", str(options.lidar_scale)], [f"{data}/{split}"])
            for split, count in (("train", options.train_segments), ("eval", options.eval_segments))]
    plan += [Stage(f"records_{split}", [tool("write_pair_records.py"), "--source", "wod", "--config", options.config,
                                        "--input", f"{data}/{split}", "--out_dir", f"{records}/{split}"],
                   [f"{records}/{split}"]) for split in ("train", "eval")]
    # The job's options are the config's nsfp section (tools/pseudo_label.py takes them as --set nsfp.KEY=VALUE).
    nsfp = [a for key, value in options.nsfp_sets().items() for a in ("--set", f"nsfp.{key}={value}")]
    plan.append(Stage("pseudo_label", [tool("pseudo_label.py"), "--input", f"{records}/train", "--out_dir",
                                       f"{records}/train_pseudo", *nsfp, *options.nsfp_args],
                      [f"{records}/train_pseudo"]))
    # Both models read the same pseudo-labelled records (which keep the human labels beside the pseudo ones): same
    # files, same shuffle, same seed; only data.labels differs.
    plan += [Stage(f"train_{labels}", [tool("train.py"), *config, "--set", f"data.labels={labels}", "--data_dir",
                                       f"{records}/train_pseudo", "--model_dir", f"{out_dir}/model_{labels}"],
                   [f"{out_dir}/model_{labels}"]) for labels in MODELS]
    plan += [Stage(f"eval_{labels}", [tool("eval.py"), *config, "--data_dir", f"{records}/eval", "--checkpoint",
                                      f"{out_dir}/model_{labels}", "--out_dir", f"{out_dir}/eval_{labels}"],
                   [f"{out_dir}/eval_{labels}"]) for labels in MODELS]
    return plan


def score_pseudo_labels(cfg, files: list[str]) -> tuple[dict, dict, dict]:
    """(pseudo-labels vs human labels, zero flow vs human labels, counts) over the pairs of pseudo-labelled records
    `files`, on the points training reads (`cfg`'s grid crop), with the evaluation's metric. Counts: pairs, points
    and points whose pseudo-flow is not zero."""
    import numpy as np
    from ff3d_tf import schema
    from ff3d_tf.data import pairs
    from ff3d_tf.metrics import SceneFlowMetrics
    pseudo, zero = SceneFlowMetrics(), SceneFlowMetrics()
    counts = {"pairs": 0, "points": 0, "points_with_pseudo_flow": 0}
    for ex in pairs.pair_dataset(files, cfg, extras=(schema.PSEUDO_FLOW_KEY,)):
        flow_true, flow_pseudo, class_id = ex["flow_mps_t0"], ex[schema.PSEUDO_FLOW_KEY], ex["class_id_t0"]
        pseudo.update_state(flow_true, flow_pseudo, class_id)
        zero.update_state(flow_true, np.zeros_like(flow_true), class_id)
        counts["pairs"] += 1
        counts["points"] += int(class_id.shape[0])
        counts["points_with_pseudo_flow"] += int(np.any(flow_pseudo.numpy() != 0, axis=1).sum())
    if not counts["pairs"]:
        raise ValueError(f"no pairs in {files}")
    return pseudo.result(), zero.result(), counts


@dataclasses.dataclass(frozen=True)
class StageOutputs:
    """What the stages wrote that the result reads."""
    eval_metrics: dict  # {human, pseudo, zero_flow_human, zero_flow_pseudo: the eval's metrics.json}
    nsfp_counts: dict  # the pseudo-labelling job's pseudo_label_counts.json
    histories: dict  # {human, pseudo: the model's train_history.json}


def read_stage_outputs(out_dir: str) -> StageOutputs:
    def read(path):
        with open(path) as f:
            return json.load(f)

    metrics = {}
    for labels in MODELS:
        metrics[labels] = read(f"{out_dir}/eval_{labels}/metrics.json")
        metrics[f"zero_flow_{labels}"] = read(f"{out_dir}/eval_{labels}/metrics_zero_flow.json")
    return StageOutputs(metrics, read(f"{out_dir}/records/train_pseudo/pseudo_label_counts.json"),
                        {labels: read(f"{out_dir}/model_{labels}/train_history.json") for labels in MODELS})


def json_without_nan(value):
    """`value` (dicts nested in dicts) with each non-finite float (an empty cell) as None: JSON null."""
    if isinstance(value, dict):
        return {k: json_without_nan(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _summary_keys(metrics: dict) -> dict:
    return {k: metrics[k] for k in SUMMARY_KEYS if k in metrics}


def _ratio(numerator: float, denominator: float) -> float | None:
    return numerator / denominator if denominator else None


def summary(options: Options, command: str, outputs: StageOutputs, pseudo_scores: tuple[dict, dict, dict],
            timings_s: dict, skipped: list[str]) -> dict:
    """The benchmark's result (NaN where a metric has no points; `json_without_nan` before writing it): the verdict,
    the summary and the full metrics of each of `RUNS`, the pseudo-labels' scores (`score_pseudo_labels`), the
    options, the NSFP job's counts per fitted pair, each model's logged losses, the timings and the machine."""
    metrics = {k: v for k, v in outputs.eval_metrics.items() if not k.startswith("zero_flow_")}
    # Zero flow does not depend on the model: both evaluations must give the same figures.
    zero_human, zero_pseudo = (json.dumps(json_without_nan(outputs.eval_metrics[f"zero_flow_{k}"]), sort_keys=True)
                               for k in MODELS)
    metrics["zero_flow"] = outputs.eval_metrics["zero_flow_human"]
    pseudo_vs_human, zero_train, label_counts = pseudo_scores
    moving = {k: metrics[k]["all/moving/mean_l2_mps"] for k in RUNS}
    stationary = {k: metrics[k]["all/stationary/mean_l2_mps"] for k in RUNS}
    nsfp = outputs.nsfp_counts
    fitted = max(nsfp.get("fitted_pairs", 0), 1)
    return {
        "what": "FastFlow3D trained on NSFP pseudo-labels (tools/pseudo_label.py, ZeroFlow's loss) vs the same model "
                "trained on the human labels (same config, seed, steps, input records) vs zero flow, on held-out "
                "synthetic WOD records scored against their human labels (tools/eval.py; m/s unless _m)",
        "command": command,
        "verdict": {
            "pseudo_beats_zero_flow_on_moving": bool(moving["pseudo"] < moving["zero_flow"]),
            "all_moving_mean_l2_mps": moving,
            "all_stationary_mean_l2_mps": stationary,
            "pseudo_over_human_moving": _ratio(moving["pseudo"], moving["human"]),
            "pseudo_over_zero_flow_moving": _ratio(moving["pseudo"], moving["zero_flow"]),
            "fg_dynamic_epe_m": {k: metrics[k].get("three_way/fg_dynamic_epe_m") for k in metrics},
        },
        "eval_summary": {k: _summary_keys(v) for k, v in metrics.items()},
        "pseudo_labels": {
            "what": "the pseudo-labels (flow_mps_pseudo_t0) against the human labels of the training records, on "
                    "the points training reads; zero flow on the same points for scale",
            "summary": _summary_keys(pseudo_vs_human),
            "zero_flow_summary": _summary_keys(zero_train),
            "points": label_counts,
            "metrics": pseudo_vs_human,
        },
        "eval_metrics": metrics,
        "zero_flow_same_in_both_evaluations": zero_human == zero_pseudo,
        "options": options.as_json(),
        "nsfp_job": {**nsfp, "seconds_per_fitted_pair": nsfp.get("nsfp_seconds", 0) / fitted,
                     "iterations_per_fitted_pair": nsfp.get("nsfp_iterations", 0) / fitted},
        "training": {k: {"last_logged_step": h["loss"][-1][0] if h.get("loss") else None,
                         "first_logged_loss": h["loss"][0] if h.get("loss") else None,
                         "last_logged_loss": h["loss"][-1] if h.get("loss") else None}
                     for k, h in outputs.histories.items()},
        "timings_s": timings_s,
        "stages_skipped_this_run": list(skipped),
        "machine": {"cpus": os.cpu_count(), "load_average_1_5_15": list(os.getloadavg())},
        "cpu": cpu.describe(),
    }


def table(result: dict) -> list[str]:
    """The headline of a `summary` result: EPE on moving and stationary points (m/s) and the foreground dynamic EPE
    (m) of each of `RUNS` and of the pseudo-labels themselves, then the verdict (a missing figure: nan)."""
    def figure(value) -> float:
        return float("nan") if value is None else value

    verdict, labels = result["verdict"], result["pseudo_labels"]["metrics"]
    lines = [f"{'on held-out records (human labels), m/s':<44}{'moving':>10}{'stationary':>12}{'fg dyn (m)':>12}"]
    lines += [f"{RUN_NAMES[k]:<44}{verdict['all_moving_mean_l2_mps'][k]:>10.3f}"
              f"{verdict['all_stationary_mean_l2_mps'][k]:>12.3f}{figure(verdict['fg_dynamic_epe_m'][k]):>12.3f}"
              for k in RUNS]
    lines.append(f"{'pseudo-labels vs human, training records':<44}{labels['all/moving/mean_l2_mps']:>10.3f}"
                 f"{labels['all/stationary/mean_l2_mps']:>12.3f}"
                 f"{figure(labels.get('three_way/fg_dynamic_epe_m')):>12.3f}")
    lines.append(f"pseudo-trained beats zero flow on moving points: {verdict['pseudo_beats_zero_flow_on_moving']}")
    return lines


def write_json(path: str, result: dict) -> None:
    """`result` as JSON at `path` (NaN as null, keys sorted), written whole or not at all."""
    bench.write_json(path, json_without_nan(result), sort_keys=True)


def run(options: Options, out_dir: str, json_path: str, command: str, tools_dir: str = TOOLS_DIR,
        log: Callable[[str], None] = print_line) -> dict:
    """Runs (or resumes) the stages under `out_dir`, scores the pseudo-labels, writes the result to `json_path`, logs
    its `table` and returns it. A stage that fails raises `ff3d_tf.stages.StageError`."""
    t0 = time.time()
    stages = run_stages(stage_plan(options, out_dir, tools_dir), out_dir, log)
    from ff3d_tf.config import load_config  # TensorFlow, in this process, once the stages have run
    from ff3d_tf.data.pairs import list_segment_files
    log("\n=== scoring the pseudo-labels against the human labels of the training records")
    cfg = load_config(options.config, options.config_sets())
    t = time.time()
    scores = score_pseudo_labels(cfg, list_segment_files(f"{out_dir}/records/train_pseudo"))
    score_s = time.time() - t
    timings_s = {**stages.seconds, "score_pseudo_labels": score_s, "total_this_run": time.time() - t0}
    result = summary(options, command, read_stage_outputs(out_dir), scores, timings_s, stages.skipped)
    write_json(json_path, result)
    log("\n" + "\n".join(table(result)))
    log(f"wrote {json_path} ({time.time() - t0:.0f} s)")
    return result
