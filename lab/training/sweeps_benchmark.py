"""Multi-sweep models against the pair, over several seeds, the job of `lab/tools/benchmark_sweeps.py`: the paper's
model on 2 sweeps, DeFlow's GRU head with DeltaFlow's loss on 2 sweeps and `stack` of 3, DeltaFlow's point head and
loss with `delta` of 3 and 5 sweeps (and of 5 with every sweep's ground left out, `data.drop_ground`, as the
authors), a planted defect, `delta_5_reversed` (the difference taken from t0 whatever the records' direction,
`lab.training.planted_defects`), and without labels, each beside its supervised twin: the paper's model distilled
from NSFP's pseudo-labels, SeFlow's loss on the GRU head, TeFlow's on `delta` of 5 (`VARIANTS`). Each is trained with
every seed of `Options.seeds` on the same synthetic examples and scored on held-out ones (other logs, another
generator seed) beside zero flow; the spread over the seeds beside each mean.

Every variant trains and is scored on the same t0 sweeps: those whose every past slot holds its own sweep for the
variant of the most sweeps ("full", the log's t0 sweeps from rank `Options.history_rank()` on, rank counted among the
log's t0 sweeps), whatever the variant reads; the held-out t0 sweeps before that rank ("filled": the longer variants'
history stands in from the log's first sweep there) are scored apart. Logs of `Options.frames_per_segment` sweeps
(40 by default) make the filled share small, as in real logs.

Stages (`stage_plan`), each one of the project's tools as a subprocess run by `ff3d_tf.stages` (resumable), for each
data format of `Options.formats`:
1. synthetic data, training and held-out (`tools/make_synthetic_data.py`, the splits' seeds of `SPLIT_SEEDS`; with
   `Options.realistic`, its sensor model);
2. pair records of both splits for each number of sweeps the variants read (`tools/write_pair_records.py --set
   data.num_frames=N`: a record of N sweeps holds its past sweeps), then their full and filled parts
   (`lab/tools/benchmark_sweeps.py --subset`, `subset_records`);
3. the fields a variant's records need first (`PREPARATIONS`: pseudo-labels, self-supervision's, every sweep's
   ground), once per records part;
4. each variant trained with each seed on the full part (`tools/train.py`, `train.seed`), same config and steps; the
   planted variant through `lab/tools/run_planted.py`;
5. each evaluated on the held-out full and filled parts (`tools/eval.py`; `--protocol av2` for AV2), beside zero
   flow.
`run` gathers the figures (`format_summary`: per variant and part the mean, sample standard deviation, minimum and
maximum over the seeds of each headline figure of `heads_benchmark.HEADLINE_KEYS`; whether zero flow, the paper's
model and the best other variant are apart by more than the seeds' spread on each of `SEPARATION_FIGURES`; and
whether the planted defect comes out worse than the corrected variant beyond that spread, `instrument`), writes one
JSON and logs `table`.
"""
from __future__ import annotations

import dataclasses
import json
import os
import statistics
import time
import types
from typing import Callable

from ff3d_tf import cpu
from lab.paths import LAB_TOOLS_DIR, ROOT, TOOLS_DIR
from lab.training.distillation_benchmark import Stage, print_line, run_stages, write_json
from lab.training.heads_benchmark import FORMATS, HEADLINE_KEYS, SPLIT_SEEDS, eval_metrics, generate_stages, headline

# DeFlow's GRU head with its authors' gradient clip (configs/deltaflow_av2.yaml) and a rate below the config's: at the
# config's rate, on the benchmark's batch, it diverged with DeltaFlow's loss (the loss grew without bound and the
# trainer stopped on non-finite steps), with the clip and without. The paper's model keeps the config's rate.
GRU_HEAD = ("model.head=gru", "train.grad_clip_norm=5.0", "train.learning_rate=5e-4")
# DeltaFlow's point head (configs/deltaflow_av2.yaml's head) with the same clip, at the config's rate: the GRU's lower
# rate left it nearer zero flow at the planted defect's budget (docs/benchmarks.md).
MLP_HEAD = ("model.head=mlp", "train.grad_clip_norm=5.0")
GRU_DELTAFLOW, MLP_DELTAFLOW = (head + ("train.loss=deltaflow",) for head in (GRU_HEAD, MLP_HEAD))
PLANTED = "delta_5_reversed"  # the planted defect, and the variant it must come out worse than
CORRECTED = "delta_5"


@dataclasses.dataclass(frozen=True)
class Variant:
    """What a variant reads and how it trains: its sweeps, config overrides of its training and evaluation (`sets`)
    and of its training alone (`train_sets`: the labels it trains on and their loss; evaluation scores human
    labels), and the fields its records need first (`prepare`, a key of `PREPARATIONS`)."""
    sweeps: int
    sets: tuple[str, ...]
    train_sets: tuple[str, ...] = ()
    prepare: str = ""


# The jobs that add fields to a variant's records, {name: (tool, the splits it prepares)}, each run on a split's
# records before they are cut into parts (self-supervision's DUFOMap reads every sweep of a log): NSFP pseudo-labels
# (ZeroFlow's distillation) and self-supervision's DUFOMap flags and clusters (SeFlow, TeFlow) of the training split;
# every sweep's ground mask of both (`data.drop_ground`; Argoverse 2 records carry theirs, so it runs on WOD's).
PREPARATIONS = {"pseudo": ("pseudo_label.py", ("train",)), "self": ("prepare_self_supervision.py", ("train",)),
                "ground": ("add_ground_masks.py", ("train", "eval"))}
SELF_SUPERVISED = ("data.labels=self",)
VARIANTS = {
    "paper_pair": Variant(2, ("model.head=paper", "train.loss=l2")),
    "gru_deltaflow_pair": Variant(2, GRU_DELTAFLOW),
    "stack_3": Variant(3, GRU_DELTAFLOW + ("model.temporal=stack",)),
    "delta_3": Variant(3, MLP_DELTAFLOW + ("model.temporal=delta",)),
    CORRECTED: Variant(5, MLP_DELTAFLOW + ("model.temporal=delta",)),
    PLANTED: Variant(5, MLP_DELTAFLOW + ("model.temporal=delta_reversed",)),
    "delta_5_no_ground": Variant(5, MLP_DELTAFLOW + ("model.temporal=delta", "data.drop_ground=true"),
                                 prepare="ground"),
    # Without labels (issue 53), each beside its supervised twin above: the paper's model distilled from NSFP's
    # pseudo-labels (ZeroFlow); SeFlow's loss on DeFlow's head (its authors' backbone); TeFlow's on DeltaFlow's
    # backbone of 5 sweeps (its authors' command, KTH-RPL/OpenSceneFlow @848bf86 README "TeFlow").
    "nsfp_pair": Variant(2, ("model.head=paper",), ("data.labels=pseudo", "train.loss=l2"), "pseudo"),
    "seflow_pair": Variant(2, GRU_HEAD, SELF_SUPERVISED + ("train.loss=seflow",), "self"),
    "teflow_5": Variant(5, MLP_HEAD + ("model.temporal=delta",), SELF_SUPERVISED + ("train.loss=teflow",), "self"),
}
VARIANT_NAMES = {"paper_pair": "paper model, 2 sweeps", "gru_deltaflow_pair": "GRU + DeltaFlow loss, 2 sweeps",
                 "stack_3": "GRU + DeltaFlow loss, stack of 3", "delta_3": "DeltaFlow head and loss, delta of 3",
                 CORRECTED: "DeltaFlow head and loss, delta of 5",
                 PLANTED: "planted defect: delta of 5 reversed",
                 "delta_5_no_ground": "DeltaFlow head and loss, delta of 5, ground dropped",
                 "nsfp_pair": "paper model, NSFP pseudo-labels (ZeroFlow)", "seflow_pair": "GRU head, SeFlow's loss",
                 "teflow_5": "DeltaFlow head, TeFlow's loss, delta of 5", "zero_flow": "zero flow"}
REALISTIC_FLAGS = ("--realistic",)  # tools/make_synthetic_data.py: the sensor model
PARTS = ("full", "filled")  # the held-out t0 sweeps with every variant's own history, and those before
SUBSETS = (("train", "full"), ("eval", "full"), ("eval", "filled"))  # the (split, part) records each run reads
REAL_AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")  # the real pair the 2-sweep variants are also scored on
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
    realistic: bool = False  # the generator's sensor model (`tools/make_synthetic_data.py --realistic`)

    def config_sets(self) -> list[str]:
        return ["data.point_bucket_base=8192", "data.source=pair_records", f"train.num_steps={self.steps}",
                "train.eval_every_steps=0"] + list(self.sets)

    def sweeps(self) -> list[int]:
        """The numbers of sweeps the variants read, ascending (one set of records each)."""
        return sorted({VARIANTS[v].sweeps for v in self.variants})

    def history_rank(self) -> int:
        """The first rank (among a log's t0 sweeps) whose every past slot holds its own sweep for every variant: the
        most sweeps read, less t0 and its partner."""
        return max(self.sweeps()) - 2

    def as_json(self) -> dict:
        return {**dataclasses.asdict(self), "sets": list(self.sets), "seeds": list(self.seeds),
                "formats": list(self.formats),
                "variants": {v: {"sweeps": VARIANTS[v].sweeps, "set": list(VARIANTS[v].sets),
                                 "train_set": list(VARIANTS[v].train_sets), "prepare": VARIANTS[v].prepare}
                             for v in self.variants},
                "set": self.config_sets()}


def variant_sets(variant: str) -> list[str]:
    """A variant's own overrides of its training and evaluation: its sweeps and `VARIANTS`' sets."""
    return [f"data.num_frames={VARIANTS[variant].sweeps}", *VARIANTS[variant].sets]


def preparation(variant: str, fmt: str, split: str) -> str:
    """The key of `PREPARATIONS` whose fields the variant's records of `split` ("train", "eval") need in format
    `fmt`, or "" (none)."""
    prepare = VARIANTS[variant].prepare
    if not prepare or (prepare == "ground" and fmt == "av2") or split not in PREPARATIONS[prepare][1]:
        return ""
    return prepare


def prepared_part(variant: str, fmt: str, part: str) -> str:
    """The records part (`train_full`, `eval_full`, `eval_filled`) a variant reads in format `fmt`: the part itself,
    or the same part of its split's prepared records (`<part>_<preparation>`)."""
    prepare = preparation(variant, fmt, part.split("_")[0])
    return f"{part}_{prepare}" if prepare else part


def stage_plan(options: Options, out_dir: str, tools_dir: str = TOOLS_DIR) -> list[Stage]:
    """The stages of the module docstring, writing under `out_dir`."""
    config = ["--config", options.config] + [a for s in options.config_sets() for a in ("--set", s)]

    def tool(name):
        return os.path.join(tools_dir, name)

    def flags(sets):
        return [a for s in sets for a in ("--set", s)]

    def run_tool(variant, name):  # the planted variant runs the tools with the lab's planted fusions registered
        return [os.path.join(LAB_TOOLS_DIR, "run_planted.py"), tool(name)] if variant == PLANTED else [tool(name)]

    def subsets(fmt, sweeps, split, prepare=""):  # the parts of one split's records (`subset_records`)
        records, suffix = f"{out_dir}/{fmt}/records_{sweeps}", f"_{prepare}" if prepare else ""
        return [Stage(f"subset_{fmt}_{split}_{part}{suffix}_{sweeps}",
                      [os.path.join(LAB_TOOLS_DIR, "benchmark_sweeps.py"), "--subset", f"{records}/{split}{suffix}",
                       f"{records}/{split}_{part}{suffix}", f"{part}:{rank}"], [f"{records}/{split}_{part}{suffix}"])
                for s, part in SUBSETS if s == split]

    rank = options.history_rank()
    plan = []
    for fmt in options.formats:
        data = f"{out_dir}/{fmt}/data"
        plan += generate_stages(options, fmt, data, tools_dir, REALISTIC_FLAGS if options.realistic else ())
        for sweeps in options.sweeps():
            temporal = [] if sweeps == 2 else ["model.temporal=delta"]  # records hold sweeps, whatever the model
            records = f"{out_dir}/{fmt}/records_{sweeps}"
            plan += [Stage(f"records_{fmt}_{split}_{sweeps}",
                           [tool("write_pair_records.py"), "--source", fmt, "--config", options.config,
                            *flags([f"data.num_frames={sweeps}", *temporal]), "--input",
                            f"{data}/{split}" + (f"/{split}" if fmt == "av2" else ""), "--out_dir",
                            f"{records}/{split}"],
                           [f"{records}/{split}"]) for split in SPLIT_SEEDS]
            plan += [stage for split in SPLIT_SEEDS for stage in subsets(fmt, sweeps, split)]
        protocol = ["--protocol", "av2"] if fmt == "av2" else []
        # Seed by seed, every variant of a seed before the next seed: a run cut short has whole seeds to compare.
        for seed, variant in ((seed, variant) for seed in options.seeds for variant in options.variants):
            records = f"{out_dir}/{fmt}/records_{VARIANTS[variant].sweeps}"
            run_dir = f"{out_dir}/{fmt}/{variant}/seed_{seed}"
            sets = flags([*variant_sets(variant), f"train.seed={seed}"])
            for split, prepare in ((s, preparation(variant, fmt, s)) for s in SPLIT_SEEDS):
                if not prepare or any(stage.outputs == [f"{records}/{split}_{prepare}"] for stage in plan):
                    continue  # nothing to add, or added once for every variant
                sweeps = VARIANTS[variant].sweeps
                plan.append(Stage(f"prepare_{fmt}_{split}_{prepare}_{sweeps}",
                                  [tool(PREPARATIONS[prepare][0]), "--config", options.config, "--input",
                                   f"{records}/{split}", "--out_dir", f"{records}/{split}_{prepare}"],
                                  [f"{records}/{split}_{prepare}"]))
                plan += subsets(fmt, sweeps, split, prepare)
            plan.append(Stage(f"train_{fmt}_{variant}_{seed}",
                              [*run_tool(variant, "train.py"), *config, *sets,
                               *flags(VARIANTS[variant].train_sets), "--data_dir",
                               f"{records}/{prepared_part(variant, fmt, 'train_full')}", "--model_dir",
                               f"{run_dir}/model"], [f"{run_dir}/model"]))
            plan += [Stage(f"eval_{fmt}_{variant}_{seed}_{part}",
                           [*run_tool(variant, "eval.py"), *config, *sets, *protocol, "--data_dir",
                            f"{records}/{prepared_part(variant, fmt, 'eval_' + part)}", "--checkpoint",
                            f"{run_dir}/model", "--out_dir", f"{run_dir}/eval_{part}"], [f"{run_dir}/eval_{part}"])
                     for part in PARTS]
            if fmt == "av2" and VARIANTS[variant].sweeps == 2:  # and on the real Argoverse 2 pair of data/
                plan.append(Stage(f"eval_real_{variant}_{seed}",
                                  [tool("eval.py"), *config, *sets, *protocol, "--data_dir",
                                   f"{out_dir}/real_av2/records", "--checkpoint", f"{run_dir}/model",
                                   "--out_dir", f"{run_dir}/eval_real"], [f"{run_dir}/eval_real"]))
    if "av2" in options.formats and any(VARIANTS[v].sweeps == 2 for v in options.variants):
        real = Stage("records_real_av2", [tool("write_pair_records.py"), "--source", "av2", "--config",
                                          options.config, "--input", REAL_AV2_LOG, "--out_dir",
                                          f"{out_dir}/real_av2/records"], [f"{out_dir}/real_av2/records"])
        first_eval = next(i for i, stage in enumerate(plan) if stage.name.startswith("eval_real_"))
        plan.insert(first_eval, real)
    return plan


def _t0_keys(path: str, compression: str) -> list[tuple[str, int]]:
    """(sequence id, t0 timestamp ns) of every record of one pair-records file, in file order (scalars only)."""
    import tensorflow as tf  # here: the benchmark's tool imports this module before its start-up

    from ff3d_tf.data import pair_records
    spec = {pair_records.SEQUENCE_KEY: tf.io.FixedLenFeature([], tf.string),
            pair_records.TIMESTAMP_KEY: tf.io.FixedLenFeature([], tf.int64)}
    ds = tf.data.TFRecordDataset(path, compression_type="ZLIB" if compression == "zlib" else "")
    return [(f[pair_records.SEQUENCE_KEY].decode(), int(f[pair_records.TIMESTAMP_KEY]))
            for f in ds.map(lambda r: tf.io.parse_single_example(r, spec)).as_numpy_iterator()]


def subset_records(source: str, target: str, part: str, rank: int) -> dict:
    """Copies into `target` (with `source`'s manifest) the records of `source` whose t0 sweep has, among its log's t0
    sweeps ordered by time, a rank >= `rank` (`part` "full") or < `rank` ("filled"); the records' bytes unchanged.
    Returns {"kept": n, "of": n}."""
    import tensorflow as tf

    from ff3d_tf.data import pair_records
    if part not in PARTS:
        raise ValueError(f"part {part!r}: one of {PARTS}")
    manifest = pair_records.read_manifest(source)
    files = sorted(f for f in os.listdir(source) if f.endswith(pair_records.FILE_SUFFIX))
    keys = {f: _t0_keys(os.path.join(source, f), manifest.compression) for f in files}
    by_log: dict = {}
    for log_id, t0_ns in (k for ks in keys.values() for k in ks):
        by_log.setdefault(log_id, []).append(t0_ns)
    ranks = {(log_id, t): i for log_id, stamps in by_log.items() for i, t in enumerate(sorted(stamps))}
    os.makedirs(target, exist_ok=True)
    kept = 0
    for f in files:
        wanted = [(ranks[k] >= rank) == (part == "full") for k in keys[f]]
        raw = tf.data.TFRecordDataset(os.path.join(source, f),
                                      compression_type="ZLIB" if manifest.compression == "zlib" else "")
        kept += pair_records.write_records_atomically(
            os.path.join(target, f), (r for r, keep in zip(raw.as_numpy_iterator(), wanted) if keep),
            manifest.compression)
    pair_records.write_manifest(target, manifest)
    return {"kept": kept, "of": sum(len(k) for k in keys.values())}


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


def instrument(rows: dict) -> dict:
    """Whether the planted defect (`PLANTED`) comes out worse than the corrected variant (`CORRECTED`) beyond the seeds'
    spread, on each of `SEPARATION_FIGURES` (lower is better on each): `apart`'s figures, `planted_worse`, and
    `caught` (worse and apart, over 2 seeds or more)."""
    if PLANTED not in rows or CORRECTED not in rows:
        return {}
    out = {}
    for figure in SEPARATION_FIGURES:
        planted, corrected = rows[PLANTED][figure], rows[CORRECTED][figure]
        versus = apart(planted, corrected)
        worse = planted["mean"] is not None and corrected["mean"] is not None and planted["mean"] > corrected["mean"]
        seeds = min(planted["n"], corrected["n"])  # one seed has no spread to be apart by
        out[figure] = {**versus, "planted_worse": bool(worse), "seeds": seeds,
                       "caught": bool(worse and versus["apart"] and seeds >= 2)}
    return out


def format_result(per_seed: dict, zero_flow: dict, per_seed_filled: dict | None = None,
                  zero_flow_filled: dict | None = None) -> dict:
    """One format's result: the full part's `format_summary` with its `instrument`, and the filled part's summary
    (`filled`) where the run scored one."""
    out = format_summary(per_seed, zero_flow)
    out["instrument"] = instrument(out["per_variant"])
    if per_seed_filled is not None:
        out["filled"] = format_summary(per_seed_filled, zero_flow_filled)
    return out


def summarize_again(result: dict, command: str) -> dict:
    """`result` (a JSON `run` wrote) with each format's summary made again by this code's `format_result` from the
    per-seed figures it holds; `command` is recorded beside the run's own."""
    formats = {fmt: format_result(part["per_seed"], part["zero_flow_headline"],
                                  part["filled"]["per_seed"] if "filled" in part else None,
                                  part["filled"]["zero_flow_headline"] if "filled" in part else None)
               for fmt, part in result["formats"].items()}
    return {**result, "formats": formats, "summarized_again_by": command}


def read_real(options: Options, out_dir: str) -> dict | None:
    """{variant: spread of each headline figure over the seeds} of the 2-sweep variants on the real Argoverse 2 pair
    (None without an av2 run)."""
    variants = [v for v in options.variants if VARIANTS[v].sweeps == 2]
    if "av2" not in options.formats or not variants:
        return None
    out = {}
    for variant in variants:
        heads = [headline(eval_metrics(f"{out_dir}/av2/{variant}/seed_{seed}/eval_real", "av2")[0], "av2")
                 for seed in options.seeds]
        out[variant] = {name: spread([h[name] for h in heads]) for name in HEADLINE_KEYS}
    zero = headline(eval_metrics(f"{out_dir}/av2/{variants[0]}/seed_{options.seeds[0]}/eval_real", "av2")[1], "av2")
    out["zero_flow"] = {name: spread([zero[name]]) for name in HEADLINE_KEYS}
    return out


def read_format(options: Options, out_dir: str, fmt: str) -> dict:
    """`format_result` of what the stages of format `fmt` wrote under `out_dir`."""
    per_seed, zero = {part: {} for part in PARTS}, {}
    for part in PARTS:
        for variant in options.variants:
            per_seed[part][variant] = []
            for seed in options.seeds:
                model, zero_metrics = eval_metrics(f"{out_dir}/{fmt}/{variant}/seed_{seed}/eval_{part}", fmt)
                per_seed[part][variant].append(headline(model, fmt))
                zero[part] = zero.get(part) or headline(zero_metrics, fmt)
    return format_result(per_seed["full"], zero["full"], per_seed["filled"], zero["filled"])


def records_bytes(out_dir: str, options: Options) -> dict:
    """{format: {sweeps: bytes of the training records of that many sweeps}}: every number of sweeps has the same
    examples (the full part of each), so the ratios are those of one record."""
    def size(directory):
        return sum(os.path.getsize(os.path.join(directory, f)) for f in os.listdir(directory)
                   if f.endswith(".tfrecord"))
    return {fmt: {str(n): size(f"{out_dir}/{fmt}/records_{n}/train_full") for n in options.sweeps()}
            for fmt in options.formats}


def table(result: dict) -> list[str]:
    """The result as Markdown rows, as docs/benchmarks.md shows it (tests/test_docs.py checks it): per format, each
    variant and zero flow, each of `TABLE_COLUMNS` as mean ± sample standard deviation over the seeds."""
    def cell(s: dict) -> str:
        return "n/a" if s["mean"] is None else f"{s['mean']:.3f} ± {s['std']:.3f}"

    lines = ["| data | model | moving (m/s) | stationary (m/s) | three-way mean EPE (m) | bucketed dynamic "
             "(normalized) |", "|---|---|" + "---:|" * len(TABLE_COLUMNS)]
    for fmt, part in result["formats"].items():
        for label, summary in ((fmt, part), (f"{fmt}, filled history", part.get("filled"))):
            if summary is None:
                continue
            rows = {**summary["per_variant"], "zero_flow": summary["zero_flow"]}
            lines += [f"| {label} | {VARIANT_NAMES[v]} | " + " | ".join(cell(r[c]) for c in TABLE_COLUMNS) + " |"
                      for v, r in rows.items()]
    lines += [f"| real AV2 pair | {VARIANT_NAMES[v]} | " + " | ".join(cell(r[c]) for c in TABLE_COLUMNS) + " |"
              for v, r in (result.get("real_av2_pair") or {}).items()]
    return lines


def recorded_seconds(plan: list[Stage], out_dir: str) -> dict:
    """{stage: seconds} of the stages of `plan` whose record `ff3d_tf.stages` wrote under `out_dir` (they finished)."""
    out = {}
    for stage in plan:
        path = f"{out_dir}/stages/{stage.name}.json"
        if os.path.exists(path):
            with open(path) as f:
                out[stage.name] = float(json.load(f).get("seconds", 0.0))
    return out


def run(options: Options, out_dir: str, json_path: str, command: str, tools_dir: str = TOOLS_DIR,
        log: Callable[[str], None] = print_line, collect_only: bool = False) -> dict:
    """Runs (or resumes) the stages under `out_dir`, writes the result to `json_path`, logs its `table` and returns
    it. A stage that fails raises `ff3d_tf.stages.StageError`. `collect_only`: runs nothing, and gathers what the
    stages of `options` (its seeds, variants) wrote under `out_dir` in an earlier run (each must have finished)."""
    t0 = time.time()
    plan = stage_plan(options, out_dir, tools_dir)
    if collect_only:
        seconds = recorded_seconds(plan, out_dir)
        missing = [s.name for s in plan if s.name not in seconds]
        if missing:
            raise ValueError(f"{out_dir}: stages not finished: {', '.join(missing)}")
        stages = types.SimpleNamespace(seconds=seconds, skipped=list(seconds))
    else:
        stages = run_stages(plan, out_dir, log)
    result = {
        "what": "models of 2, 3 and 5 sweeps (model.temporal pair, stack, delta) and a planted defect (delta of 5 "
                "reversed) trained with several seeds on the same synthetic t0 sweeps, scored on held-out ones beside "
                "zero flow (tools/eval.py; mean, sample standard deviation, min and max over the seeds; m/s for "
                "*_mps, m for *_epe_m); the held-out t0 sweeps whose history the longest variants fill from the log's "
                "first sweep under 'filled'; whether the planted defect comes out worse beyond the spread under "
                "'instrument'",
        "command": command,
        "formats": {fmt: read_format(options, out_dir, fmt) for fmt in options.formats},
        "real_av2_pair": read_real(options, out_dir),
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


__all__ = ["FORMATS", "Options", "PARTS", "VARIANTS", "run", "stage_plan", "subset_records", "table"]
