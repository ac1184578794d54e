"""Multi-sweep models against the pair, over several seeds, the job of `lab/tools/benchmark_sweeps.py`: the paper's
model on 2 sweeps, DeFlow's GRU head with DeltaFlow's loss on 2 sweeps, and on 3 and 5 sweeps (`model.temporal`
stack and delta), each trained with every seed of `Options.seeds` on the same synthetic records and scored on
held-out records (other logs, another generator seed) beside zero flow; the spread over the seeds beside each mean.

Stages (`stage_plan`), each one of the project's tools as a subprocess run by `ff3d_tf.stages` (resumable), for each
data format of `Options.formats`:
1. synthetic data, training and held-out (`tools/make_synthetic_data.py`, the splits' seeds of `SPLIT_SEEDS`);
2. pair records of both splits for each number of sweeps the variants read (`tools/write_pair_records.py --set
   data.num_frames=N`: a record of N sweeps holds its past sweeps);
3. each variant trained with each seed (`tools/train.py`, `train.seed`), same config, steps and records;
4. each evaluated on the held-out records (`tools/eval.py`; `--protocol av2` for AV2), beside zero flow.
`run` gathers the figures (`format_summary`: per variant the mean, sample standard deviation, minimum and maximum
over the seeds of each headline figure of `heads_benchmark.HEADLINE_KEYS`; and whether zero flow, the paper's model
and the best other variant are apart by more than the seeds' spread on each of `SEPARATION_FIGURES`, `separations`),
writes one JSON and logs `table`.
"""
from __future__ import annotations

import dataclasses
import os
import statistics
import time
from typing import Callable

from ff3d_tf import cpu
from lab.paths import ROOT, TOOLS_DIR
from lab.training.distillation_benchmark import Stage, print_line, run_stages, write_json
from lab.training.heads_benchmark import FORMATS, HEADLINE_KEYS, SPLIT_SEEDS, eval_metrics, generate_stages, headline

# DeFlow's head with DeltaFlow's loss with its authors' gradient clip (configs/deltaflow_av2.yaml) and a rate below
# the config's: at the config's rate, on the benchmark's batch, this head and loss diverged (the loss grew without
# bound and the trainer stopped on non-finite steps), with the clip and without. The paper's model keeps the config's
# rate.
GRU_DELTAFLOW = ("model.head=gru", "train.loss=deltaflow", "train.grad_clip_norm=5.0", "train.learning_rate=5e-4")
# {variant: (sweeps, its config overrides)}: the five rows.
VARIANTS = {
    "paper_pair": (2, ("model.head=paper", "train.loss=l2")),
    "gru_deltaflow_pair": (2, GRU_DELTAFLOW),
    "stack_3": (3, GRU_DELTAFLOW + ("model.temporal=stack",)),
    "delta_3": (3, GRU_DELTAFLOW + ("model.temporal=delta",)),
    "delta_5": (5, GRU_DELTAFLOW + ("model.temporal=delta",)),
}
VARIANT_NAMES = {"paper_pair": "paper model, 2 sweeps", "gru_deltaflow_pair": "GRU + DeltaFlow loss, 2 sweeps",
                 "stack_3": "GRU + DeltaFlow loss, stack of 3", "delta_3": "GRU + DeltaFlow loss, delta of 3",
                 "delta_5": "GRU + DeltaFlow loss, delta of 5", "zero_flow": "zero flow"}
TABLE_COLUMNS = ("moving_mps", "stationary_mps", "three_way_mean_epe_m", "bucketed_dynamic_norm_epe")
# The figures whose means the separations compare: the paper's error on moving points (m/s), and the mean dynamic
# bucketed normalized EPE the Argoverse 2 board ranks by (no unit). Each has its own best variant.
SEPARATION_FIGURES = ("moving_mps", "bucketed_dynamic_norm_epe")


@dataclasses.dataclass(frozen=True)
class Options:
    """What the benchmark runs: the tool's flags."""
    config: str  # the config file of the trainings, evaluations and records
    sets: tuple[str, ...]  # the user's config overrides (KEY=VALUE), applied after the benchmark's own
    steps: int  # training steps of each run
    seeds: tuple[int, ...]  # train.seed of each run of each variant
    formats: tuple[str, ...]  # of heads_benchmark.FORMATS
    train_segments: int
    eval_segments: int
    frames_per_segment: int
    lidar_scale: float
    av2_points_per_sweep: int
    variants: tuple[str, ...] = tuple(VARIANTS)

    def config_sets(self) -> list[str]:
        return ["data.point_bucket_base=8192", "data.source=pair_records", f"train.num_steps={self.steps}",
                "train.eval_every_steps=0"] + list(self.sets)

    def sweeps(self) -> list[int]:
        """The numbers of sweeps the variants read, ascending (one set of records each)."""
        return sorted({VARIANTS[v][0] for v in self.variants})

    def as_json(self) -> dict:
        return {**dataclasses.asdict(self), "sets": list(self.sets), "seeds": list(self.seeds),
                "formats": list(self.formats), "variants": {v: {"sweeps": VARIANTS[v][0], "set": list(VARIANTS[v][1])}
                                                            for v in self.variants},
                "set": self.config_sets()}


def variant_sets(variant: str) -> list[str]:
    """A variant's own overrides: its sweeps (and the pair's temporal default) and `VARIANTS`' sets."""
    sweeps, sets = VARIANTS[variant]
    return [f"data.num_frames={sweeps}", *sets]


def stage_plan(options: Options, out_dir: str, tools_dir: str = TOOLS_DIR) -> list[Stage]:
    """The stages of the module docstring, writing under `out_dir`."""
    config = ["--config", options.config] + [a for s in options.config_sets() for a in ("--set", s)]

    def tool(name):
        return os.path.join(tools_dir, name)

    def flags(sets):
        return [a for s in sets for a in ("--set", s)]

    plan = []
    for fmt in options.formats:
        data = f"{out_dir}/{fmt}/data"
        plan += generate_stages(options, fmt, data, tools_dir)
        for sweeps in options.sweeps():
            temporal = [] if sweeps == 2 else ["model.temporal=delta"]  # records hold sweeps, whatever the model
            plan += [Stage(f"records_{fmt}_{split}_{sweeps}",
                           [tool("write_pair_records.py"), "--source", fmt, "--config", options.config,
                            *flags([f"data.num_frames={sweeps}", *temporal]), "--input",
                            f"{data}/{split}" + (f"/{split}" if fmt == "av2" else ""), "--out_dir",
                            f"{out_dir}/{fmt}/records_{sweeps}/{split}"],
                           [f"{out_dir}/{fmt}/records_{sweeps}/{split}"]) for split in SPLIT_SEEDS]
        protocol = ["--protocol", "av2"] if fmt == "av2" else []
        for variant in options.variants:
            records = f"{out_dir}/{fmt}/records_{VARIANTS[variant][0]}"
            for seed in options.seeds:
                run_dir = f"{out_dir}/{fmt}/{variant}/seed_{seed}"
                sets = flags([*variant_sets(variant), f"train.seed={seed}"])
                plan.append(Stage(f"train_{fmt}_{variant}_{seed}", [tool("train.py"), *config, *sets, "--data_dir",
                                                                    f"{records}/train", "--model_dir",
                                                                    f"{run_dir}/model"], [f"{run_dir}/model"]))
                plan.append(Stage(f"eval_{fmt}_{variant}_{seed}",
                                  [tool("eval.py"), *config, *sets, *protocol, "--data_dir", f"{records}/eval",
                                   "--checkpoint", f"{run_dir}/model", "--out_dir", f"{run_dir}/eval"],
                                  [f"{run_dir}/eval"]))
    return plan


def spread(values: list) -> dict:
    """{mean, std (sample, n - 1; 0 for one value), min, max, n} of the figures that are not None."""
    got = [v for v in values if v is not None]
    if not got:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": statistics.fmean(got), "std": statistics.stdev(got) if len(got) > 1 else 0.0,
            "min": min(got), "max": max(got), "n": len(got)}


def apart(a: dict, b: dict) -> dict:
    """Whether two variants' `spread`s of one figure are apart by more than the seeds' spread: |mean a - mean b| >
    the larger of their ranges (max - min); with the difference and that range."""
    if a["mean"] is None or b["mean"] is None:
        return {"difference": None, "largest_range": None, "apart": False}
    difference = abs(a["mean"] - b["mean"])
    largest = max(a["max"] - a["min"], b["max"] - b["min"])
    return {"difference": difference, "largest_range": largest, "apart": difference > largest}


def format_summary(per_seed: dict, zero_flow: dict) -> dict:
    """One format's part of the result: `per_seed` {variant: [headline of each seed's eval]}, `zero_flow` the
    headline of zero flow (the same for every run: it does not depend on the model)."""
    rows = {v: {name: spread([h[name] for h in heads]) for name in HEADLINE_KEYS} for v, heads in per_seed.items()}
    zero = {name: spread([zero_flow[name]]) for name in HEADLINE_KEYS}
    moving = {v: r["moving_mps"]["mean"] for v, r in rows.items() if r["moving_mps"]["mean"] is not None}
    separations = {}
    for figure in SEPARATION_FIGURES:
        means = {v: r[figure]["mean"] for v, r in rows.items() if r[figure]["mean"] is not None and v != "paper_pair"}
        best_variant = min(means, key=means.get) if means else None  # the best of the other variants
        if "paper_pair" in rows:
            paper = rows["paper_pair"][figure]
            separations[figure] = {
                "best_variant": best_variant, "zero_flow_vs_paper_pair": apart(zero[figure], paper),
                "paper_pair_vs_best_variant": (apart(paper, rows[best_variant][figure])
                                               if best_variant is not None else None)}
    return {"per_variant": rows, "zero_flow": zero, "best_on_moving": min(moving, key=moving.get) if moving else None,
            "separations": separations, "per_seed": per_seed, "zero_flow_headline": zero_flow}


def summarize_again(result: dict, command: str) -> dict:
    """`result` (a JSON `run` wrote) with each format's summary made again by this code's `format_summary` from the
    per-seed figures it holds; `command` is recorded beside the run's own."""
    formats = {fmt: format_summary(part["per_seed"], part["zero_flow_headline"])
               for fmt, part in result["formats"].items()}
    return {**result, "formats": formats, "summarized_again_by": command}


def read_format(options: Options, out_dir: str, fmt: str) -> dict:
    """`format_summary` of what the stages of format `fmt` wrote under `out_dir`."""
    per_seed, zero = {}, None
    for variant in options.variants:
        per_seed[variant] = []
        for seed in options.seeds:
            model, zero_metrics = eval_metrics(f"{out_dir}/{fmt}/{variant}/seed_{seed}/eval", fmt)
            per_seed[variant].append(headline(model, fmt))
            zero = zero or headline(zero_metrics, fmt)
    return format_summary(per_seed, zero)


def records_bytes(out_dir: str, options: Options) -> dict:
    """{format: {sweeps: bytes of the training records of that many sweeps}}: every number of sweeps has the same
    examples (a log's first sweeps included, their history clamped), so the ratios are those of one record."""
    def size(directory):
        return sum(os.path.getsize(os.path.join(directory, f)) for f in os.listdir(directory)
                   if f.endswith(".tfrecord"))
    return {fmt: {str(n): size(f"{out_dir}/{fmt}/records_{n}/train") for n in options.sweeps()}
            for fmt in options.formats}


def table(result: dict) -> list[str]:
    """The result as Markdown rows, as docs/benchmarks.md shows it (tests/test_docs.py checks it): per format, each
    variant and zero flow, each of `TABLE_COLUMNS` as mean ± sample standard deviation over the seeds."""
    def cell(s: dict) -> str:
        return "n/a" if s["mean"] is None else f"{s['mean']:.3f} ± {s['std']:.3f}"

    lines = ["| data | model | moving (m/s) | stationary (m/s) | three-way mean EPE (m) | bucketed dynamic "
             "(normalized) |", "|---|---|" + "---:|" * len(TABLE_COLUMNS)]
    for fmt, part in result["formats"].items():
        rows = {**part["per_variant"], "zero_flow": part["zero_flow"]}
        lines += [f"| {fmt} | {VARIANT_NAMES[v]} | " + " | ".join(cell(r[c]) for c in TABLE_COLUMNS) + " |"
                  for v, r in rows.items()]
    return lines


def run(options: Options, out_dir: str, json_path: str, command: str, tools_dir: str = TOOLS_DIR,
        log: Callable[[str], None] = print_line) -> dict:
    """Runs (or resumes) the stages under `out_dir`, writes the result to `json_path`, logs its `table` and returns
    it. A stage that fails raises `ff3d_tf.stages.StageError`."""
    t0 = time.time()
    plan = stage_plan(options, out_dir, tools_dir)
    stages = run_stages(plan, out_dir, log)
    result = {
        "what": "models of 2, 3 and 5 sweeps (model.temporal pair, stack, delta) trained with several seeds on the "
                "same synthetic records, scored on held-out synthetic records beside zero flow (tools/eval.py; mean, "
                "sample standard deviation, min and max over the seeds; m/s for *_mps, m for *_epe_m)",
        "command": command,
        "formats": {fmt: read_format(options, out_dir, fmt) for fmt in options.formats},
        "training_records_bytes": records_bytes(out_dir, options),
        "options": options.as_json(),
        "stage_commands": [" ".join([os.path.relpath(s.command[0], ROOT), *s.command[1:]]) for s in plan],
        "timings_s": {**stages.seconds, "total_this_run": time.time() - t0},
        "stages_skipped_this_run": list(stages.skipped),
        "cpu": cpu.describe(),
        "machine": {"cpus": os.cpu_count(), "load_average_1_5_15": list(os.getloadavg())},
    }
    write_json(json_path, result)
    log("\n" + "\n".join(table(result)))
    log(f"wrote {json_path} ({time.time() - t0:.0f} s)")
    return result


__all__ = ["FORMATS", "Options", "VARIANTS", "run", "stage_plan", "table"]
