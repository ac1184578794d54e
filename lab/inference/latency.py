"""Forward latency of FastFlow3D by compile mode and precision, beside the dense-convolution floor of each backend and
the training step, every measured call in one round robin (lab/tools/benchmark_latency.py; the paper's Table 3).

Variants (`variants`): every compile mode in every precision (float32, bfloat16 or auto: the `model.mixed_precision`
values false, true and auto, `PRECISION_SETTINGS`), named "mode" with one precision and "mode/precision" with several;
all with the first variant's weights. Input: batch 1, the benchmark cloud of `lab.bench` (uniform over the grid)
at each point count, padded to its bucket. Warm-up (tracing, compilation) is excluded; every measured call (each
variant at each point count, the conv floors, each variant's training step) takes its turn in one round robin
(`bench.round_robin`), so that load on a shared machine hits them alike: compare ratios within one run.

Each call is summarised (`call_summaries`) by the median and min of its wall times, its peak resident memory (Linux
VmHWM, reset before each call: start-up and compilation do not count), `rss_before_gb` (the resident set before a
call, after returning freed heap to the OS) and `rss_after_gb` (right after a call, untrimmed: what the process holds
between calls). Each variant's flow is compared with the first variant's over the real points (same weights, same
input).

The conv floor (`conv_floor_calls`) is the dense stages alone (the encoder on both frames stacked, then the decoder)
on a ready grid: XLA and graph kernels in float32, graph kernels (oneDNN) in bfloat16. The training step is forward +
backward + Adam, batch 1. The example inputs and the training steps come from the caller (`run`'s `example` and
`train_steps`: lab/tools/benchmark_latency.py passes `lab.training.bench_steps.example` and `train_steps`).
"""
from __future__ import annotations

import dataclasses
import os
from typing import Callable, Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf import cpu
from ff3d_tf.config import ExperimentConfig, replace_config
from ff3d_tf.model import build_model
from ff3d_tf.model import compile as compile_lib
from lab import bench

PRECISION_SETTINGS = {"float32": False, "bfloat16": True, "auto": "auto"}  # precision name -> model.mixed_precision
CONV_FLOOR_BACKENDS = ("xla", "graph")
WARMUP_ROUNDS = 2  # unmeasured rounds of the round robin before the measured ones

# (cfg, rng, points, labels=False) -> (the model's inputs as tensors, batch 1, padded to the bucket; the padded size)
Example = Callable[..., tuple[dict, int]]
# (cfg, {variant: resolved compile mode}, labelled example) -> {variant: a call running one training step}
TrainSteps = Callable[[ExperimentConfig, dict, dict], dict]


@dataclasses.dataclass(frozen=True)
class Variant:
    """One timed model: a compile mode in a precision."""
    compile: str  # model.compile as asked ("auto" included)
    resolved: str  # the compile mode it runs in
    precision: str  # a name of PRECISION_SETTINGS
    resolved_precision: str  # "float32" or "bfloat16"
    precision_reason: str  # why `precision` resolved so

    def record(self) -> dict:
        """The variant's entry under "modes" in the results."""
        return {"compile": self.compile, "resolved": self.resolved, "description": compile_lib.describe(self.resolved),
                "precision": self.precision, "resolved_precision": self.resolved_precision,
                "precision_reason": self.precision_reason,
                "precision_description": compile_lib.describe_precision(self.resolved_precision)}

    def describe(self) -> str:
        """One line: each choice as asked -> as resolved (why)."""
        return (f"{self.compile} -> {self.resolved} ({compile_lib.describe(self.resolved)}), {self.precision} -> "
                f"{self.resolved_precision} ({self.precision_reason})")


def precision_settings(names: str | None, config_setting) -> dict:
    """{precision name: model.mixed_precision value} of the comma-separated `names`; None: the name of
    `config_setting` (the config's own value). A name not in `PRECISION_SETTINGS` raises ValueError naming it."""
    if names is None:
        for name, setting in PRECISION_SETTINGS.items():
            if setting == config_setting and type(setting) is type(config_setting):
                return {name: setting}
        raise ValueError(f"model.mixed_precision={config_setting!r}: none of {list(PRECISION_SETTINGS.values())}")
    unknown = [n for n in names.split(",") if n not in PRECISION_SETTINGS]
    if unknown:
        raise ValueError(f"{unknown} unknown; one of {', '.join(PRECISION_SETTINGS)}")
    return {n: PRECISION_SETTINGS[n] for n in names.split(",")}


def variants(modes: Sequence[str], precisions: dict, device_type: str | None = None,
             cpu: tuple[str, tuple[str, ...]] | None = None) -> dict[str, Variant]:
    """{name: Variant} of every compile mode of `modes` in every precision of `precisions` ({name: model.mixed_precision
    value}), modes outermost. `device_type` and `cpu` (vendor, bfloat16 flags) resolve "auto" as
    `compile_lib.resolve_compile_mode` and `resolve_precision` do (default: this machine's)."""
    out = {}
    for mode in modes:
        resolved = compile_lib.resolve_compile_mode(mode, device_type)
        for name, setting in precisions.items():
            key = mode if len(precisions) == 1 else f"{mode}/{name}"
            resolved_precision = compile_lib.resolve_precision(setting, resolved, device_type, cpu)
            out[key] = Variant(mode, resolved, name, *resolved_precision)
    return out


def conv_floor_key(backend: str, precision: str) -> str:
    """A conv floor's name: the backend in float32, "backend/precision" in another precision."""
    return backend if precision == "float32" else f"{backend}/{precision}"


def conv_floor_calls(models_by_precision: dict, bev_features: tf.Tensor) -> dict:
    """{conv floor name: call} of each {resolved precision: model}: `model.grid_stages(bev_features)` as graph kernels
    and, in float32, as one XLA program. `bev_features`: [2, H, W, C], both frames of one pair stacked."""
    calls = {}
    for precision, model in models_by_precision.items():
        dense = {"graph": tf.function(lambda x, model=model: model.grid_stages(x))}
        if precision == "float32":
            dense["xla"] = tf.function(lambda x, model=model: model.grid_stages(x), jit_compile=True)
        calls.update({conv_floor_key(backend, precision): (lambda f=f: f(bev_features))
                      for backend, f in sorted(dense.items())})
    return calls


def call_summaries(readings: dict[str, list[dict]]) -> dict:
    """{call: summary} of each call's `bench.timed_with_memory` readings: median_ms, min_ms, runs, peak_rss_gb (the
    largest peak), rss_before_gb and rss_after_gb (medians), and peak_reset (whether the peak could be reset before
    every reading of every call)."""
    peak_reset = all(r["peak_reset"] for rs in readings.values() for r in rs)
    return {name: {**bench.summary([r["ms"] for r in rs], ("median", "min")), "runs": len(rs),
                   "peak_rss_gb": float(np.max([r["peak_rss_gb"] for r in rs])),
                   "rss_before_gb": float(np.median([r["rss_before_gb"] for r in rs])),
                   "rss_after_gb": float(np.median([r["rss_after_gb"] for r in rs])), "peak_reset": peak_reset}
            for name, rs in readings.items()}


def flow_differences(flow_mps: np.ndarray, reference_flow_mps: np.ndarray, reference: str) -> dict:
    """How a variant's flow [N,3] (m/s, the real points) differs from the reference variant's: the largest absolute
    component difference, the largest and mean length of the difference, and the mean length of the variant's flow."""
    diff_norm = np.linalg.norm(flow_mps - reference_flow_mps, axis=-1)
    return {f"max_abs_flow_diff_vs_{reference}": float(np.abs(flow_mps - reference_flow_mps).max()),
            f"max_flow_diff_norm_vs_{reference}_mps": float(diff_norm.max()),
            f"mean_flow_diff_norm_vs_{reference}_mps": float(diff_norm.mean()),
            "mean_flow_norm_mps": float(np.linalg.norm(flow_mps, axis=-1).mean())}


def report(timed: dict, timed_variants: dict[str, Variant], points: Sequence[int], padded_points: dict,
           flows_mps: dict, train_points: int) -> dict:
    """The results' "conv_floor" (where timed), "latency", "ratios" and "train_step" (with `train_points`) sections.

    `timed`: `call_summaries` keyed "conv_floor/<floor>", "<points>/<variant>" and "train/<variant>". `padded_points`:
    {points: padded size, "train": that of the training example}. `flows_mps`: {points: {variant: flow [points,3]}}.
    Ratios per variant: the median at the largest point count over that at the smallest, and the median at the smallest
    over the fastest conv floor in the variant's precision (nan without one). A training step's
    `over_inference_same_points` is its median over the forward's at `train_points` (None where not timed)."""
    points = sorted(points)
    reference = next(iter(timed_variants))
    out = {}
    floors = {k[len("conv_floor/"):]: v for k, v in timed.items() if k.startswith("conv_floor/")}
    if floors:
        out["conv_floor"] = floors
    latency = out["latency"] = {
        str(n): {name: {**timed[f"{n}/{name}"], "padded_points": padded_points[n],
                        **flow_differences(flows_mps[n][name], flows_mps[n][reference], reference)}
                 for name in timed_variants} for n in points}

    def fastest_floor_ms(variant: Variant) -> float:
        same = [floors[k]["median_ms"] for k in (conv_floor_key(b, variant.resolved_precision)
                                                 for b in CONV_FLOOR_BACKENDS) if k in floors]
        return min(same) if same else float("nan")

    smallest, largest = latency[str(points[0])], latency[str(points[-1])]
    out["ratios"] = {name: {"max_over_min_points": largest[name]["median_ms"] / smallest[name]["median_ms"],
                            "min_points_over_fastest_conv_floor": smallest[name]["median_ms"] / fastest_floor_ms(v)}
                     for name, v in timed_variants.items()}
    if train_points:
        same_points = latency.get(str(train_points))
        out["train_step"] = {
            name: {**timed[f"train/{name}"], "padded_points": padded_points["train"],
                   "over_inference_same_points": (timed[f"train/{name}"]["median_ms"] / same_points[name]["median_ms"]
                                                  if same_points else None)} for name in timed_variants}
    return out


def report_lines(results: dict, train_points: int) -> list[str]:
    """The printed summary of `report`'s sections: conv floors, then the variants at each point count, then the
    training step."""
    lines = []
    if "conv_floor" in results:
        floors = results["conv_floor"]
        lines.append("conv floor: " + "; ".join(f"{k} {v['median_ms']:.0f} ms" for k, v in floors.items()))
    lines += [f"{n} points: " + "; ".join(f"{m} {v['median_ms']:.0f} ms (peak RSS {v['peak_rss_gb']:.2f} GB)"
                                          for m, v in row.items()) for n, row in results["latency"].items()]
    if "train_step" in results:
        lines.append(f"train step at {train_points} points: " + "; ".join(
            f"{m} {v['median_ms']:.0f} ms (RSS between steps {v['rss_after_gb']:.2f} GB)"
            for m, v in results["train_step"].items()))
    return lines


def run(cfg: ExperimentConfig, modes: Sequence[str], precisions: dict, points: Sequence[int], runs: int,
        train_points: int, conv_floor: bool, example: Example, train_steps: TrainSteps | None,
        log: Callable[[str], None] = print) -> dict:
    """The benchmark (module docstring): the results as written to JSON. `modes`: compile modes as asked; `precisions`:
    {name: model.mixed_precision value} (`precision_settings`); `points`: the point counts; `runs`: measured rounds;
    `train_points`: the training example's point count (0: no training step); `conv_floor`: time the conv floors."""
    if train_points and train_steps is None:
        raise ValueError("train_points given without train_steps")
    if not points:
        raise ValueError("no point counts")
    points = sorted(points)
    timed_variants = variants(modes, precisions)
    log("variants: " + "; ".join(f"{name}: {v.describe()}" for name, v in timed_variants.items()))
    models = {name: build_model(replace_config(cfg, {"model.mixed_precision": precisions[v.precision]}), v.resolved)
              for name, v in timed_variants.items()}
    first = next(iter(models.values()))
    for model in models.values():
        model.set_weights(first.get_weights())
    framework_baseline_gb = bench.proc_status("VmRSS")  # TensorFlow imported, model variables created
    forwards = {name: tf.function(lambda x, model=model: model(x, training=False), reduce_retracing=True)
                for name, model in models.items()}
    results = {"device": compile_lib.accelerator_type(), "cpu_count": os.cpu_count(), "cpu": cpu.describe(),
               "load_average_at_start": bench.load_average(), "grid": [cfg.grid.num_pillars_x, cfg.grid.num_pillars_y],
               "modes": {name: v.record() for name, v in timed_variants.items()}, "precisions": dict(precisions),
               "cpu_bf16_support": list(compile_lib.cpu_bf16_support()), "params": first.count_params(),
               "framework_baseline_rss_gb": framework_baseline_gb}
    rng = np.random.default_rng(0)
    g = cfg.grid
    # Drawn first with or without the conv floors, so that the clouds after it are the same either way.
    bev_features = tf.constant(rng.uniform(0, 1, (2, g.num_pillars_y, g.num_pillars_x, cfg.model.point_feature_dim))
                               .astype(np.float32))
    calls = {}
    if conv_floor:
        floor_models = {}  # each precision's first variant
        for name, model in models.items():
            floor_models.setdefault(timed_variants[name].resolved_precision, model)
        calls.update({f"conv_floor/{k}": f for k, f in conv_floor_calls(floor_models, bev_features).items()})
    padded_points, flows_mps = {}, {}
    for n in points:
        inputs, padded_points[n] = example(cfg, rng, n)
        flows_mps[n] = {name: f(inputs)["flow_mps"].numpy()[0, :n] for name, f in forwards.items()}  # the real points
        calls.update({f"{n}/{name}": (lambda f=f, x=inputs: f(x)) for name, f in forwards.items()})
    if train_points:
        labelled, padded_points["train"] = example(cfg, rng, train_points, labels=True)
        for precision, setting in precisions.items():  # a trainer builds its model from its config: one per precision
            modes_in_precision = {name: v.resolved for name, v in timed_variants.items() if v.precision == precision}
            steps = train_steps(replace_config(cfg, {"model.mixed_precision": setting}), modes_in_precision, labelled)
            calls.update({f"train/{name}": step for name, step in steps.items()})
    readings = bench.round_robin({k: bench.fetched(fn) for k, fn in calls.items()}, runs, warmup=WARMUP_ROUNDS,
                                 reading=bench.timed_with_memory)
    results.update(report(call_summaries(readings), timed_variants, points, padded_points, flows_mps, train_points))
    for line in report_lines(results, train_points):
        log(line)
    results["load_average_at_end"] = bench.load_average()
    return results
