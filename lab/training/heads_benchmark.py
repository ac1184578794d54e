"""The per-point heads and losses compared on synthetic data, the job of `lab/tools/benchmark_heads.py`: FastFlow3D's
paper head and DeFlow's GRU head, trained with the L2, DeFlow and DeltaFlow losses and with augmentation, side by side on
the same records, seed and steps, scored on held-out records beside zero flow.

Stages (`stage_plan`), each one of the project's tools as a subprocess run by `ff3d_tf.stages` (resumable, its
output streaming through), for each data format of `Options.formats` in turn (WOD first):
1. synthetic data, training and held-out (`tools/make_synthetic_data.py`, different seeds; AV2: `--format av2`);
2. pair records of both (`tools/write_pair_records.py --source wod|av2`: human labels, per-point instance ids, and
   for AV2 the categories that DeltaFlow's class term reads);
3. each of `VARIANTS` trained on the training records, same config, seed, steps and input order, only its
   `--set` overrides differing (`tools/train.py`);
4. each evaluated on the held-out records (`tools/eval.py`; `--protocol av2` for AV2: the challenge's three-way and
   bucketed EPE over its eval mask and the paper's tables on the same points), beside zero flow.
Then `run` gathers every figure into one result (`summary`: per format and variant the paper's table (moving /
stationary per class, m/s), the three-way EPE (m) and the bucketed normalized dynamic EPE, each beside zero flow; the
eval's full metrics, the options, the commands, the CPU and the timings) with how often a moving point shares its
pillar with a stationary one in the training records (`pillar_sharing`: what a per-point head has to separate), writes
it as JSON (`write_json`) and returns it; `table` is its headline. The runner process imports TensorFlow only for
`pillar_sharing`, after every stage.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Callable

from ff3d_tf import cpu
from lab.paths import ROOT, TOOLS_DIR
from lab.training.distillation_benchmark import CLASSES, SUMMARY_KEYS, Stage, print_line, run_stages, write_json

FORMATS = ("wod", "av2")  # make_synthetic_data.py --format / write_pair_records.py --source
# {variant: its config overrides}; every variant also gets the benchmark's common overrides (Options.config_sets).
AUGMENT_SETS = ("data.augment_height_offset_prob=0.5", "data.augment_flip_prob=0.5")
VARIANTS = {
    "paper_l2": ("model.head=paper", "train.loss=l2"),
    "gru_l2": ("model.head=gru", "train.loss=l2"),
    "gru_deflow": ("model.head=gru", "train.loss=deflow"),
    "gru_deltaflow": ("model.head=gru", "train.loss=deltaflow"),
    "gru2_deltaflow": ("model.head=gru", "model.gru_iterations=2", "train.loss=deltaflow"),
    "gru_deflow_augment": ("model.head=gru", "train.loss=deflow") + AUGMENT_SETS,
}
VARIANT_NAMES = {"paper_l2": "paper head + L2", "gru_l2": "GRU head + L2", "gru_deflow": "GRU head + DeFlow loss",
                 "gru_deltaflow": "GRU head + DeltaFlow loss", "gru2_deltaflow": "GRU (2 iterations) + DeltaFlow loss",
                 "gru_deflow_augment": "GRU + DeFlow + augmentation", "zero_flow": "zero flow"}
SPLIT_SEEDS = {"train": 100, "eval": 900}  # make_synthetic_data.py --seed of each split
# The headline figures: {name: the key in the eval's metrics of each protocol (WOD: paper, AV2: av2)}.
HEADLINE_KEYS = {
    "moving_mps": {"wod": "all/moving/mean_l2_mps", "av2": "all/moving/mean_l2_mps"},
    "stationary_mps": {"wod": "all/stationary/mean_l2_mps", "av2": "all/stationary/mean_l2_mps"},
    "fg_dynamic_epe_m": {"wod": "three_way/fg_dynamic_epe_m", "av2": "three_way/fg_dynamic_epe_m"},
    "fg_static_epe_m": {"wod": "three_way/fg_static_epe_m", "av2": "three_way/fg_static_epe_m"},
    "bg_static_epe_m": {"wod": "three_way/bg_static_epe_m", "av2": "three_way/bg_static_epe_m"},
    "three_way_mean_epe_m": {"wod": "three_way/mean_epe_m", "av2": "three_way/mean_epe_m"},
    "bucketed_dynamic_norm_epe": {"wod": "bucketed/mean_dynamic", "av2": "bucketed/mean_dynamic_norm_epe"},
}
TABLE_COLUMNS = ("moving_mps", "stationary_mps", "fg_dynamic_epe_m", "three_way_mean_epe_m",
                 "bucketed_dynamic_norm_epe")
PER_CLASS_KEYS = tuple(f"{c}/{s}/mean_l2_mps" for c in CLASSES for s in ("moving", "stationary"))


def plan_names(formats: tuple[str, ...]) -> tuple[str, ...]:
    """The stage names of `stage_plan` in its order."""
    names = []
    for fmt in formats:
        names += [f"{stage}_{fmt}_{split}" for stage in ("generate", "records") for split in SPLIT_SEEDS]
        names += [f"{stage}_{fmt}_{variant}" for stage in ("train", "eval") for variant in VARIANTS]
    return tuple(names)


@dataclasses.dataclass(frozen=True)
class Options:
    """What the benchmark runs: the tool's flags."""
    config: str  # the config file of the trainings, evaluations and pair records
    sets: tuple[str, ...]  # the user's config overrides (KEY=VALUE), applied after the benchmark's own
    steps: int  # training steps of each variant
    seed: int  # train.seed of every variant
    formats: tuple[str, ...]  # of FORMATS, run in this order
    train_segments: int  # WOD segments / AV2 logs of the training split
    eval_segments: int  # of the held-out split
    frames_per_segment: int  # WOD frames a segment / AV2 sweeps a log
    lidar_scale: float  # WOD: < 1 shrinks the synthetic range images (fewer points)
    av2_points_per_sweep: int

    def config_sets(self) -> list[str]:
        """The config overrides of every training and evaluation: the benchmark's, then `sets`."""
        # point_bucket_base 8192 as the distillation benchmark: the clouds padded to a near bucket.
        return ["data.point_bucket_base=8192", "data.source=pair_records", f"train.num_steps={self.steps}",
                f"train.seed={self.seed}", "train.eval_every_steps=0"] + list(self.sets)

    def as_json(self) -> dict:
        """The options as the result's "options" records them."""
        return {**dataclasses.asdict(self), "sets": list(self.sets), "formats": list(self.formats),
                "set": self.config_sets(), "variants": {k: list(v) for k, v in VARIANTS.items()}}


def generate_stages(options, fmt: str, data: str, tools_dir: str = TOOLS_DIR,
                    generator_flags: tuple[str, ...] = ()) -> list[Stage]:
    """The synthetic data of both splits (`SPLIT_SEEDS`) in format `fmt` under `data`/<split>, sized by `options`
    (its train_segments, eval_segments, frames_per_segment, lidar_scale and av2_points_per_sweep), with the
    generator's further `generator_flags`."""
    counts = {"train": options.train_segments, "eval": options.eval_segments}
    stages = []
    for split, seed in SPLIT_SEEDS.items():
        if fmt == "wod":
            size = ["--num_segments", str(counts[split]), "--frames_per_segment", str(options.frames_per_segment),
                    "--lidar_scale", str(options.lidar_scale)]
        else:  # AV2 sensor logs under data/<split>/<split>/<log_id>/
            size = ["--format", "av2", "--split", split, "--num_logs", str(counts[split]), "--sweeps_per_log",
                    str(options.frames_per_segment), "--points_per_sweep", str(options.av2_points_per_sweep)]
        stages.append(Stage(f"generate_{fmt}_{split}", [os.path.join(tools_dir, "make_synthetic_data.py"),
                                                        "--out_dir", f"{data}/{split}", "--seed", str(seed), *size,
                                                        *generator_flags],
                            [f"{data}/{split}"]))
    return stages


def stage_plan(options: Options, out_dir: str, tools_dir: str = TOOLS_DIR) -> list[Stage]:
    """The stages of the module docstring, in `plan_names(options.formats)`'s order, writing under `out_dir`."""
    config = ["--config", options.config] + [a for s in options.config_sets() for a in ("--set", s)]

    def tool(name):
        return os.path.join(tools_dir, name)

    plan = []
    for fmt in options.formats:
        data, records = f"{out_dir}/{fmt}/data", f"{out_dir}/{fmt}/records"
        plan += generate_stages(options, fmt, data, tools_dir)
        plan += [Stage(f"records_{fmt}_{split}",
                       [tool("write_pair_records.py"), "--source", fmt, "--config", options.config, "--input",
                        f"{data}/{split}" + (f"/{split}" if fmt == "av2" else ""), "--out_dir", f"{records}/{split}"],
                       [f"{records}/{split}"]) for split in SPLIT_SEEDS]
        plan += [Stage(f"train_{fmt}_{variant}",
                       [tool("train.py"), *config, *[a for s in sets for a in ("--set", s)], "--data_dir",
                        f"{records}/train", "--model_dir", f"{out_dir}/{fmt}/model_{variant}"],
                       [f"{out_dir}/{fmt}/model_{variant}"]) for variant, sets in VARIANTS.items()]
        protocol = ["--protocol", "av2"] if fmt == "av2" else []
        # The model's own config (saved in its model_dir) holds its head; the benchmark's sets are the same for all.
        plan += [Stage(f"eval_{fmt}_{variant}",
                       [tool("eval.py"), *config, *[a for s in VARIANTS[variant] for a in ("--set", s)], *protocol,
                        "--data_dir", f"{records}/eval", "--checkpoint", f"{out_dir}/{fmt}/model_{variant}",
                        "--out_dir", f"{out_dir}/{fmt}/eval_{variant}"],
                       [f"{out_dir}/{fmt}/eval_{variant}"]) for variant in VARIANTS]
    return plan


def eval_metrics(eval_dir: str, fmt: str) -> tuple[dict, dict]:
    """(the model's metrics, zero flow's) that `tools/eval.py` wrote to `eval_dir` for data format `fmt`: WOD the
    paper protocol's metrics.json / metrics_zero_flow.json; AV2 the challenge's figures over its eval mask merged over
    the paper's tables on the same points (metrics_av2.json)."""
    def read(name):
        with open(os.path.join(eval_dir, name)) as f:
            return json.load(f)

    if fmt == "wod":
        return read("metrics.json"), read("metrics_zero_flow.json")
    found = read("metrics_av2.json")
    return {**found["paper_model"], **found["model"]}, {**found["paper_zero_flow"], **found["zero_flow"]}


def headline(metrics: dict, fmt: str) -> dict:
    """{HEADLINE_KEYS name: value (None when absent)} of one eval's metrics in format `fmt`."""
    return {name: metrics.get(keys[fmt]) for name, keys in HEADLINE_KEYS.items()}


def _ratio(numerator, denominator):
    return numerator / denominator if numerator is not None and denominator else None


def format_summary(fmt: str, metrics: dict, histories: dict) -> dict:
    """One format's part of the result. `metrics` {variant: (model metrics, zero-flow metrics)} of `eval_metrics`;
    `histories` {variant: train_history.json}. Zero flow is the first variant's (it does not depend on the model; the
    result says whether every variant's evaluation gave the same)."""
    zero = metrics[next(iter(metrics))][1]
    rows = {variant: headline(model, fmt) for variant, (model, _) in metrics.items()}
    rows["zero_flow"] = headline(zero, fmt)
    moving = {k: r["moving_mps"] for k, r in rows.items()}
    best = min((k for k in VARIANTS if moving.get(k) is not None), key=lambda k: moving[k], default=None)
    return {
        "headline": rows,
        "versus_paper_l2": {k: {name: _ratio(r[name], rows["paper_l2"][name]) for name in TABLE_COLUMNS}
                            for k, r in rows.items() if "paper_l2" in rows},
        "best_on_moving": best,
        "beats_zero_flow_on_moving": {k: bool(moving[k] is not None and moving["zero_flow"] is not None
                                              and moving[k] < moving["zero_flow"]) for k in metrics},
        "per_class_mps": {k: {c: m.get(c) for c in PER_CLASS_KEYS} for k, m in
                          [(v, model) for v, (model, _) in metrics.items()] + [("zero_flow", zero)]},
        "eval_summary": {k: {s: m[s] for s in SUMMARY_KEYS if s in m} for k, m in
                         [(v, model) for v, (model, _) in metrics.items()] + [("zero_flow", zero)]},
        "zero_flow_same_in_every_evaluation": len({json.dumps(z, sort_keys=True, default=str)
                                                   for _, z in metrics.values()}) == 1,
        "eval_metrics": {**{v: model for v, (model, _) in metrics.items()}, "zero_flow": zero},
        "training": {k: {"last_logged_step": h["loss"][-1][0] if h.get("loss") else None,
                         "first_logged_loss": h["loss"][0] if h.get("loss") else None,
                         "last_logged_loss": h["loss"][-1] if h.get("loss") else None}
                     for k, h in histories.items()},
    }


def read_format(out_dir: str, fmt: str) -> dict:
    """`format_summary` of what the stages of format `fmt` wrote under `out_dir`."""
    histories = {}
    for variant in VARIANTS:
        with open(f"{out_dir}/{fmt}/model_{variant}/train_history.json") as f:
            histories[variant] = json.load(f)
    return format_summary(fmt, {v: eval_metrics(f"{out_dir}/{fmt}/eval_{v}", fmt) for v in VARIANTS}, histories)


def pillar_sharing(cfg, files: list[str]) -> dict:
    """How often a moving point (label speed >= `schema.MOVING_THRESHOLD_MPS`) shares its pillar (`cfg.grid`'s cells)
    with a stationary point, over the t0 clouds of the pair records `files`: what a per-point head can separate that a
    per-pillar output cannot. Counts of pairs, points in the grid, moving points, moving points in a shared pillar,
    pillars holding a moving point, shared pillars; and the two shares."""
    import numpy as np
    from ff3d_tf import schema
    from ff3d_tf.data import pairs
    grid = cfg.grid
    counts = dict.fromkeys(("pairs", "points_in_grid", "moving_points", "moving_points_in_shared_pillars",
                            "pillars_with_moving_points", "shared_pillars"), 0)
    for ex in pairs.pair_dataset(files, cfg):
        xyz, flow = ex["points_xyz_t0"].numpy(), ex["flow_mps_t0"].numpy()
        cell_x = np.floor((xyz[:, 0] - grid.x_range_m[0]) / (grid.x_range_m[1] - grid.x_range_m[0])
                          * grid.num_pillars_x).astype(np.int64)
        cell_y = np.floor((xyz[:, 1] - grid.y_range_m[0]) / (grid.y_range_m[1] - grid.y_range_m[0])
                          * grid.num_pillars_y).astype(np.int64)
        inside = (cell_x >= 0) & (cell_x < grid.num_pillars_x) & (cell_y >= 0) & (cell_y < grid.num_pillars_y)
        pillar = (cell_x * grid.num_pillars_y + cell_y)[inside]
        moving = (np.linalg.norm(flow, axis=1) >= schema.MOVING_THRESHOLD_MPS)[inside]
        shared = np.intersect1d(pillar[moving], pillar[~moving])
        counts["pairs"] += 1
        counts["points_in_grid"] += int(pillar.size)
        counts["moving_points"] += int(moving.sum())
        counts["moving_points_in_shared_pillars"] += int(np.isin(pillar[moving], shared).sum())
        counts["pillars_with_moving_points"] += int(np.unique(pillar[moving]).size)
        counts["shared_pillars"] += int(shared.size)
    return {**counts, "share_of_moving_points_in_shared_pillars":
            _ratio(counts["moving_points_in_shared_pillars"], counts["moving_points"]),
            "share_of_moving_pillars_shared": _ratio(counts["shared_pillars"], counts["pillars_with_moving_points"])}


def summary(options: Options, command: str, formats: dict, commands: list[list[str]], timings_s: dict,
            skipped: list[str], cpu_description: dict, pillars: dict | None = None) -> dict:
    """The benchmark's result: `formats` {format: `format_summary`}, the options, the stages' commands, the timings,
    the CPU, and `pillars` {format: `pillar_sharing` of its training records}."""
    return {
        "what": "FastFlow3D's paper head and DeFlow's GRU head with the L2, DeFlow and DeltaFlow losses and "
                "augmentation, trained on the same synthetic records, seed and steps, scored on held-out synthetic "
                "records beside zero flow (tools/eval.py; m/s for *_mps, m for *_epe_m; the bucketed dynamic EPE "
                "is normalized by speed, no unit)",
        "command": command,
        "formats": formats,
        "options": options.as_json(),
        "stage_commands": [" ".join(c) for c in commands],
        "timings_s": timings_s,
        "stages_skipped_this_run": list(skipped),
        "cpu": cpu_description,
        "pillar_sharing_training_records": pillars or {},
        "machine": {"cpus": os.cpu_count(), "load_average_1_5_15": list(os.getloadavg())},
    }


def table(result: dict) -> list[str]:
    """The headline of a `summary` result as Markdown rows, as docs/training.md shows it (tests/test_docs.py checks
    it): per format, each variant and zero flow with `TABLE_COLUMNS` (3 decimals; a missing figure: n/a)."""
    def cell(value) -> str:
        return "n/a" if value is None else f"{value:.3f}"

    lines = ["| data | variant | moving (m/s) | stationary (m/s) | fg dynamic EPE (m) | three-way mean EPE (m) "
             "| bucketed dynamic (normalized) |", "|---|---|" + "---:|" * len(TABLE_COLUMNS)]
    for fmt, part in result["formats"].items():
        lines += [f"| {fmt} | {VARIANT_NAMES[k]} | " + " | ".join(cell(row[c]) for c in TABLE_COLUMNS) + " |"
                  for k, row in part["headline"].items()]
    return lines


def run(options: Options, out_dir: str, json_path: str, command: str, tools_dir: str = TOOLS_DIR,
        log: Callable[[str], None] = print_line) -> dict:
    """Runs (or resumes) the stages under `out_dir`, writes the result to `json_path`, logs its `table` and returns
    it. A stage that fails raises `ff3d_tf.stages.StageError`."""
    t0 = time.time()
    plan = stage_plan(options, out_dir, tools_dir)
    stages = run_stages(plan, out_dir, log)
    from ff3d_tf.config import load_config  # TensorFlow, in this process, once the stages have run
    from ff3d_tf.data.pairs import list_segment_files
    log("\n=== counting the pillars shared by moving and stationary points in the training records")
    cfg = load_config(options.config, options.config_sets())
    pillars = {fmt: pillar_sharing(cfg, list_segment_files(f"{out_dir}/{fmt}/records/train"))
               for fmt in options.formats}
    timings_s = {**stages.seconds, "total_this_run": time.time() - t0}
    commands = [[os.path.relpath(s.command[0], ROOT), *s.command[1:]] for s in plan]
    result = summary(options, command, {fmt: read_format(out_dir, fmt) for fmt in options.formats}, commands,
                     timings_s, stages.skipped, cpu.describe(), pillars)
    write_json(json_path, result)
    log("\n" + "\n".join(table(result)))
    log(f"wrote {json_path} ({time.time() - t0:.0f} s)")
    return result
