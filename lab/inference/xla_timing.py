"""Timing the forward's portable programs with JAX alone on the default JAX device, and the latency table beside the
paper's P100 figures (lab/tools/run_xla.py, lab/tools/gpu_check.sh; `ForwardTiming` is the forward's part of
`lab.xla_export_timing.run_export`).

Like `ff3d_tf.inference.xla_artifact` (the loading it times), nothing here imports TensorFlow or a module that does.
Inputs are `xla_export_dir.random_inputs` (the benchmark cloud, `xla_export_dir.random_clouds`), resident on the
device as after a prefetch; each timed call waits until its results are complete on the device.
"""
from __future__ import annotations

import numpy as np

from ff3d_tf.inference.xla_artifact import CompiledForward, check_forward, load_forward
from ff3d_tf.xla_export_dir import random_inputs
from lab import bench
from lab.xla_export_timing import ExportRun, describe_check

# Paper, table "Inference latency varying point cloud sizes": FastFlow3D on an NVIDIA Tesla P100, batch 1, mean of 90
# forward passes after 10 warm-up passes (appendix "Measurements of Latency"). Keyed by point count.
PAPER_P100_LATENCY_MS = {32000: 49.3, 100000: 51.9, 255000: 63.1, 1000000: 98.1}
TARGET_SPEEDUP_VS_P100 = 10.0  # the GPU check's goal on an H200: <= 4.9 ms at 32K points, <= 9.8 ms at 1M


def time_forward(forward: CompiledForward, inputs: list[np.ndarray], runs: int, warmup: int) -> dict:
    """Median, mean and min latency (ms) of `runs` passes after `warmup`, inputs resident on the device; then the
    median host to host.

    `median_ms` (and `mean_ms`, the paper's statistic) is the model alone (the paper's setting: clouds already on the
    accelerator, outputs complete there); `median_host_ms` adds copying the two clouds in and flow/validity back out.
    """
    device_inputs = forward.on_device(inputs)
    device = bench.measure(lambda: _block(forward(device_inputs)), runs, warmup)
    host = bench.measure(lambda: forward.numpy(inputs), runs, warmup)
    return {**bench.summary([r["ms"] for r in device]),
            "median_host_ms": bench.summary([r["ms"] for r in host], ("median",))["median_ms"], "runs": runs,
            "warmup": warmup, "compile_s": forward.compile_s}


def _block(outputs):
    for x in outputs:
        x.block_until_ready()


class ForwardTiming:
    """The forward artifacts of a `run_export`: `runs` passes after `warmup` each (`time_forward`), rows under
    "latency". Two cloud sizes of one bucket share an artifact, compiled once."""
    kind, manifest_key, result_key = "forward", "artifacts", "latency"

    def __init__(self, runs: int, warmup: int):
        self.runs, self.warmup = runs, warmup
        self._compiled: dict[str, CompiledForward] = {}

    def time(self, run: ExportRun, entry: dict) -> dict:
        if entry["file"] not in self._compiled:
            exported = load_forward(run.export_dir, entry, len(run.weights))
            self._compiled[entry["file"]] = CompiledForward(exported, run.weights)
        forward = self._compiled[entry["file"]]
        timing = time_forward(forward, random_inputs(run.manifest, entry, run.rng), self.runs, self.warmup)
        return {"points": entry["points"], "padded_points": entry["padded_points"], "precision": entry["precision"],
                **timing, "reference": check_forward(forward, entry, run.manifest, run.reference)}

    def describe(self, row: dict) -> str:
        return (f"{row['points']} points ({row['precision']}): median {row['median_ms']:.2f} ms, min "
                f"{row['min_ms']:.2f} ms, host to host {row['median_host_ms']:.2f} ms, compile "
                f"{row['compile_s']:.1f} s" + describe_check(row["reference"]))

    def table(self, result: dict) -> list[str]:
        return latency_table(result).splitlines()

    def check_name(self, row: dict) -> str:
        return f"forward {row['points']:,} points {row['precision']}"


def latency_table(result: dict) -> str:
    """Markdown table of the forward rows of a `run_export` result beside the paper's P100 figures (speed-up = P100
    mean / our median; the target is at least `TARGET_SPEEDUP_VS_P100` times the P100)."""
    lines = [f"FastFlow3D forward, batch 1, {result['device']} ({result['platform']}, jax {result['jax']})", "",
             "| points | precision | median ms | mean ms | min ms | host-to-host ms | paper P100 ms (mean) | "
             f"speed-up vs P100 | >= {TARGET_SPEEDUP_VS_P100:g}x |", "|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in result["latency"]:
        paper = PAPER_P100_LATENCY_MS.get(row["points"])
        paper_s, speedup, met = "-", "-", "-"
        if paper:
            paper_s, speedup = f"{paper:.1f}", f"{paper / row['median_ms']:.1f}x"
            met = "yes" if paper / row["median_ms"] >= TARGET_SPEEDUP_VS_P100 else "no"
        lines.append(f"| {row['points']:,} | {row['precision']} | {row['median_ms']:.2f} | {row['mean_ms']:.2f} | "
                     f"{row['min_ms']:.2f} | "
                     f"{row['median_host_ms']:.2f} | {paper_s} | {speedup} | {met} |")
    for row in result["skipped"]:
        if row.get("kind", "forward") == "forward":
            lines.append(f"| {row['points']:,} | {row['precision']} | skipped: {row['reason']} | | | | | | |")
    return "\n".join(lines)
