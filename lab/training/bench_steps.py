"""What the benchmarks and profilers run with TensorFlow: the benchmark cloud (`lab.bench`) as a batched example,
and the Trainer's own training step on it (lab/tools/benchmark_latency.py, profile_stages.py, profile_memory.py); the
training step fed by the training input against the same step on a batch held in memory, beside the input's own rate
(`training_benchmark`, lab/tools/benchmark_training.py)."""
from __future__ import annotations

import json
import os
import tempfile
from typing import Callable, Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig, load_config, replace_config
from ff3d_tf.data.pairs import bucket_size, list_segment_files
from ff3d_tf.model.plan import resolve
from ff3d_tf.training.input import training_dataset
from ff3d_tf.training.trainer import Trainer
from lab import bench


def example(cfg: ExperimentConfig, rng: np.random.Generator, points: int, labels: bool = False) -> tuple[dict, int]:
    """(One pair of benchmark clouds of `points` points over cfg's grid, padded to their bucket, batch 1, as tensors:
    the model's inputs, with `labels` also `bench.random_labels`; the padded size)."""
    padded = bucket_size(points, cfg.data.point_bucket_base)
    g = cfg.grid
    arrays = bench.random_clouds(rng, points, padded, (g.x_range_m, g.y_range_m, g.z_range_m))
    if labels:
        arrays.update(bench.random_labels(rng, points, padded))
    return {k: tf.constant(v) for k, v in arrays.items()}, padded


def train_steps(cfg: ExperimentConfig, modes: dict, labelled: dict, plan_changes: dict | None = None) -> dict:
    """{name: step} for each {name: compile mode}: `step()` runs the Trainer's own step (`Trainer.step`: forward,
    backward, Adam) on the labelled example `labelled` repeated forever and returns the loss; batch 1, learning rate
    1e-6, on the CPU. The same seed gives every mode's trainer the same initial weights. `plan_changes`: fields of the
    execution plan changed from the one the config resolves to for training (`ff3d_tf.model.plan`)."""
    steps = {}
    for name, mode in modes.items():
        tcfg = replace_config(cfg, {"model.compile": mode, "train.global_batch_size": 1, "train.learning_rate": 1e-6})
        plan = resolve(tcfg.model, "train")[0].replace(**(plan_changes or {}))
        trainer = Trainer(tcfg, tempfile.mkdtemp(prefix="bench_train_"), [],
                          strategy=tf.distribute.OneDeviceStrategy("/cpu:0"), log_fn=lambda s: None, plan=plan)
        dataset = tf.data.Dataset.from_tensors(labelled).repeat()
        iterator = iter(trainer.strategy.experimental_distribute_dataset(dataset))
        steps[name] = (lambda tr=trainer, it=iterator: tr.step(it))
    return steps


def timed_steps(trainer: Trainer, iterator, steps: int) -> dict:
    """One warm-up step (tracing, compilation), then `steps` timed steps of `trainer.step` (loss fetched); seconds."""
    _, warmup_s = bench.elapsed(bench.fetched(lambda: trainer.step(iterator)))
    ms = bench.summary([r["ms"] for r in bench.measure(bench.fetched(lambda: trainer.step(iterator)), steps)],
                       ("mean", "min"))
    mean_s = ms["mean_ms"] / 1e3
    return {"steps": steps, "mean_step_s": mean_s, "steps_per_s": 1.0 / mean_s, "min_step_s": ms["min_ms"] / 1e3,
            "warmup_step_s": warmup_s}


def train_step_and_end_to_end(files: list[str], cfg: ExperimentConfig, steps: int, model_dir: str) -> dict:
    """`timed_steps` of the Trainer of `cfg` fed one batch of `files` held in memory ("train_step": the step with no
    input cost), then fed the training input itself ("end_to_end", with "input_bound_fraction": 1 - in-memory step
    time / end-to-end step time, the share of a step spent waiting for data)."""
    trainer = Trainer(cfg, model_dir, files, log_fn=lambda _: None)
    batch_size = cfg.train.global_batch_size
    real = training_dataset(files, cfg, batch_size)
    # One real batch, cached and repeated: the same element spec as the real input, so both modes run one traced and
    # compiled step.
    in_memory = real.take(1).cache().repeat()
    distribute = trainer.strategy.experimental_distribute_dataset
    step = timed_steps(trainer, iter(distribute(in_memory)), steps)
    end_to_end = timed_steps(trainer, iter(distribute(real)), steps)
    end_to_end["input_bound_fraction"] = max(0.0, 1.0 - step["mean_step_s"] / end_to_end["mean_step_s"])
    return {"batch_size": batch_size, "replicas": trainer.strategy.num_replicas_in_sync, "train_step": step,
            "end_to_end": end_to_end}


def training_benchmark(config: str | None, overrides: Sequence[str], data_dir: str | None = None, segments: int = 2,
                       frames_per_segment: int = 4, lidar_scale: float = 1.0, cores: Sequence[int] = (1, 2),
                       input_batches: int = 12, train_steps: int = 2,
                       progress: Callable[[str], None] = print) -> dict:
    """On the segments of `data_dir` (default: `segments` synthetic ones at `lidar_scale`, in a temporary directory):
    "input", the training input's pairs/s on each core count of `cores` (`bench_input.training_input_child`, pinned);
    "decode_count" (`bench_input.count_decodes`); the step in memory and end to end (`train_step_and_end_to_end`);
    "input_headroom", the input's pairs/s on the most cores measured x the in-memory step time / batch size (> 1: the
    input outpaces the step). `progress` gets a line per reading."""
    from lab.training import bench_input  # here: the profilers that import this module do not load it
    bench_input.check_core_counts(cores)
    cfg = load_config(config, overrides)
    with tempfile.TemporaryDirectory() as tmp:
        if data_dir is None:
            data_dir = os.path.join(tmp, "segments")
            _, seconds = bench.elapsed(lambda: bench_input.write_synthetic_segments(
                data_dir, segments, frames_per_segment, lidar_scale, first_seed=100))
            progress(f"made {segments} synthetic segments in {seconds:.0f} s")
        files = [os.path.abspath(f) for f in list_segment_files(data_dir)]
        result = {**bench_input.header(config, overrides, cfg), "input": []}
        job = {"config": bench_input.child_config(config), "overrides": list(overrides), "files": files,
               "batches": input_batches}
        for n, reading in bench_input.per_core(f"{bench_input.MODULE}:training_input_child", job, cores,
                                               "training input").items():
            result["input"].append(reading)
            progress(f"input on {n} core(s): {reading['pairs_per_s']:.2f} pairs/s ({reading['mean_points_t0']:.0f} "
                     "points per t0 cloud)")
        result["decode_count"] = bench_input.count_decodes(files, cfg)
        progress(f"decode count: {json.dumps(result['decode_count'])}")
        result.update(train_step_and_end_to_end(files, cfg, train_steps, os.path.join(tmp, "model")))
    fastest_input = max(r["pairs_per_s"] for r in result["input"])
    result["input_headroom"] = fastest_input * result["train_step"]["mean_step_s"] / result["batch_size"]
    progress(f"train step (in-memory batch): {result['train_step']['mean_step_s']:.2f} s; end to end: "
             f"{result['end_to_end']['mean_step_s']:.2f} s; input-bound fraction "
             f"{result['end_to_end']['input_bound_fraction']:.3f}; input headroom {result['input_headroom']:.1f}x")
    return result
