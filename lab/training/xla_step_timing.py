"""Timing the training step's portable programs (`ff3d_tf.training.xla_step_runner`) with JAX alone on the default
JAX device: `TrainStepTiming` is the training step's part of `lab.xla_export_timing.run_export` (lab/tools/run_xla.py,
lab/tools/gpu_check.sh). Nothing here imports TensorFlow or a module that does.
"""
from __future__ import annotations

import numpy as np

from ff3d_tf.training.xla_step_runner import (CompiledTrainStep, check_train_step, initial_train_state, load_train_step,
                                              random_labels)
from ff3d_tf.xla_export_dir import random_inputs
from lab import bench
from lab.xla_export_timing import ExportRun, describe_check


def time_train_step(step: CompiledTrainStep, batch: list[np.ndarray], runs: int, warmup: int) -> dict:
    """Median, mean and min time (ms) of `runs` steps after `warmup`, batch resident on the device (as after a
    prefetch), and what that means for input: ms and pairs/s per pair of clouds."""
    device_batch = step.on_device(batch)
    losses = []

    def one_step():
        loss, _ = step(device_batch)
        losses.append(loss.block_until_ready())

    times = bench.summary([r["ms"] for r in bench.measure(one_step, runs, warmup)])
    losses = [float(loss) for loss in losses[warmup:]]
    b = int(batch[0].shape[0])
    return {**times, "ms_per_pair": times["median_ms"] / b, "pairs_per_s": 1e3 * b / times["median_ms"],
            "runs": runs, "warmup": warmup, "loss_first": losses[0], "loss_last": losses[-1],
            "compile_s": step.compile_s}


class TrainStepTiming:
    """The training-step artifacts of a `lab.xla_export_timing.run_export`: each from the initial state, checked
    against the reference, then `runs` steps after `warmup` (`time_train_step`); rows under "train_step"."""
    kind, manifest_key, result_key = "train_step", "train_artifacts", "train_step"

    def __init__(self, runs: int, warmup: int):
        self.runs, self.warmup = runs, warmup

    def time(self, run: ExportRun, entry: dict) -> dict:
        step = CompiledTrainStep(load_train_step(run.export_dir, entry, run.manifest),
                                 initial_train_state(run.weights, run.manifest))
        check = check_train_step(step, entry, run.manifest, run.reference)
        batch = random_inputs(run.manifest, entry, run.rng) + random_labels(entry, run.manifest, run.rng)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "batch_size": entry["batch_size"],
               "precision": entry["precision"], **time_train_step(step, batch, self.runs, self.warmup),
               "reference": check}
        del step  # its state (weights and Adam slots) leaves the device before the next artifact
        return row

    def describe(self, row: dict) -> str:
        return (f"train step {row['batch_size']} x {row['points']} points ({row['precision']}): median "
                f"{row['median_ms']:.2f} ms ({row['ms_per_pair']:.2f} ms per pair), loss {row['loss_first']:.4f} -> "
                f"{row['loss_last']:.4f}, compile {row['compile_s']:.1f} s" + describe_check(row["reference"]))

    def table(self, result: dict) -> list[str]:
        """The training-step rows and skipped entries (no lines when the run has neither)."""
        skipped = [row for row in result["skipped"] if row.get("kind") == self.kind]
        if not result.get(self.result_key) and not skipped:
            return []
        lines = ["", "Training step (forward, loss, backward, Adam; batch on the device; state updated in place)", "",
                 "| batch x points | precision | median ms | min ms | ms per pair | pairs/s | loss first -> last |",
                 "|---|---|---:|---:|---:|---:|---|"]
        for row in result.get(self.result_key, []):
            lines.append(f"| {row['batch_size']} x {row['points']:,} | {row['precision']} | {row['median_ms']:.2f} | "
                         f"{row['min_ms']:.2f} | {row['ms_per_pair']:.2f} | {row['pairs_per_s']:.1f} | "
                         f"{row['loss_first']:.4f} -> {row['loss_last']:.4f} |")
        for row in skipped:
            lines.append(f"| {row['batch_size']} x {row['points']:,} | {row['precision']} | skipped: "
                         f"{row['reason']} | | | | |")
        return lines

    def check_name(self, row: dict) -> str:
        return f"train step {row['batch_size']} x {row['points']:,} {row['precision']}"
