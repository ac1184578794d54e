"""What the benchmarks and profilers run with TensorFlow: the benchmark cloud (`ff3d_tf.bench`) as a batched example,
and the Trainer's own training step on it (tools/benchmark_latency.py, profile_stages.py, profile_memory.py)."""
from __future__ import annotations

import tempfile

import numpy as np
import tensorflow as tf

from ff3d_tf import bench
from ff3d_tf.config import ExperimentConfig, replace_config
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.training.trainer import Trainer


def example(cfg: ExperimentConfig, rng: np.random.Generator, points: int, labels: bool = False) -> tuple[dict, int]:
    """(One pair of benchmark clouds of `points` points over cfg's grid, padded to their bucket, batch 1, as tensors:
    the model's inputs, with `labels` also `bench.random_labels`; the padded size)."""
    padded = bucket_size(points, cfg.data.point_bucket_base)
    g = cfg.grid
    arrays = bench.random_clouds(rng, points, padded, (g.x_range_m, g.y_range_m, g.z_range_m))
    if labels:
        arrays.update(bench.random_labels(rng, points, padded))
    return {k: tf.constant(v) for k, v in arrays.items()}, padded


def train_steps(cfg: ExperimentConfig, modes: dict, labelled: dict) -> dict:
    """{name: step} for each {name: compile mode}: `step()` runs the Trainer's own step (`Trainer.step`: forward,
    backward, Adam) on the labelled example `labelled` repeated forever and returns the loss; batch 1, learning rate
    1e-6, on the CPU. The same seed gives every mode's trainer the same initial weights."""
    steps = {}
    for name, mode in modes.items():
        tcfg = replace_config(cfg, {"model.compile": mode, "train.global_batch_size": 1, "train.learning_rate": 1e-6})
        trainer = Trainer(tcfg, tempfile.mkdtemp(prefix="bench_train_"), [],
                          strategy=tf.distribute.OneDeviceStrategy("/cpu:0"), log_fn=lambda s: None)
        dataset = tf.data.Dataset.from_tensors(labelled).repeat()
        iterator = iter(trainer.strategy.experimental_distribute_dataset(dataset))
        steps[name] = (lambda tr=trainer, it=iterator: tr.step(it))
    return steps
