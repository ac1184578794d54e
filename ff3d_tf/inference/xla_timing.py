"""Timing the portable programs with JAX alone: every artifact of an export directory on the default JAX device, and
the latency table beside the paper's P100 figures (tools/run_xla.py, tools/gpu_check.sh).

Like `ff3d_tf.inference.xla_artifact` (the format and loading it times), nothing here imports TensorFlow or a module
that does. Inputs are `xla_artifact.random_inputs` (the benchmark cloud of `ff3d_tf.bench`), resident on the device
as after a prefetch; each timed call waits until its results are complete on the device.
"""
from __future__ import annotations

import time

import numpy as np

from ff3d_tf import bench
from ff3d_tf.inference.xla_artifact import (CompiledForward, CompiledTrainStep, check_forward, check_train_step,
                                            initial_train_state, load_forward, load_reference, load_train_step,
                                            load_weights, random_inputs, random_labels, read_manifest)

# Paper, table "Inference latency varying point cloud sizes": FastFlow3D on an NVIDIA Tesla P100, batch 1, mean of 90
# forward passes after 10 warm-up passes (appendix "Measurements of Latency"). Keyed by point count.
PAPER_P100_LATENCY_MS = {32000: 49.3, 100000: 51.9, 255000: 63.1, 1000000: 98.1}
TARGET_SPEEDUP_VS_P100 = 10.0  # the GPU check's goal on an H200: <= 4.9 ms at 32K points, <= 9.8 ms at 1M


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


def run_export(export_dir: str, runs: int, warmup: int, precisions=None, points=None, budget_s: float | None = None,
               seed: int = 0, log=print, on_row=None, train_runs: int | None = None) -> dict:
    """Times every artifact of an export directory (optionally only some precisions / point counts): the forward
    artifacts first, then the training steps (`train_runs` steps each, default `runs`), then the reference checks.

    Artifacts still untimed when `budget_s` seconds have passed are listed as skipped (a GPU check must end in time).
    `on_row(result)` is called after each timed artifact with the result so far (e.g. to save partial results).
    """
    import jax
    start = time.perf_counter()
    manifest = read_manifest(export_dir)
    weights = load_weights(export_dir, manifest)
    device = jax.devices()[0]
    result = {"export_dir": export_dir, "jax": jax.__version__, "platform": device.platform,
              "device": getattr(device, "device_kind", str(device)), "num_weights": len(weights),
              "exported_with": manifest.get("exported_with", {}), "latency": [], "train_step": [], "skipped": []}
    rng = np.random.default_rng(seed)
    reference = load_reference(export_dir)
    compiled: dict[str, CompiledForward] = {}  # two cloud sizes of one bucket share an artifact

    def wanted(entry, kind):
        if (precisions and entry["precision"] not in precisions) or (points and entry["points"] not in points):
            return False
        if budget_s is not None and time.perf_counter() - start > budget_s:
            result["skipped"].append({"kind": kind, "points": entry["points"], "precision": entry["precision"],
                                      "batch_size": entry["batch_size"],
                                      "reason": f"time budget of {budget_s:.0f} s spent"})
            return False
        return True

    for entry in manifest["artifacts"]:
        if not wanted(entry, "forward"):
            continue
        if entry["file"] not in compiled:
            compiled[entry["file"]] = CompiledForward(load_forward(export_dir, entry, len(weights)), weights)
        timing = time_forward(compiled[entry["file"]], random_inputs(manifest, entry, rng), runs, warmup)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "precision": entry["precision"],
               **timing, "reference": check_forward(compiled[entry["file"]], entry, manifest, reference)}
        result["latency"].append(row)
        if on_row is not None:
            on_row(result)
        log(f"{entry['points']} points ({entry['precision']}): median {row['median_ms']:.2f} ms, min "
            f"{row['min_ms']:.2f} ms, host to host {row['median_host_ms']:.2f} ms, compile {row['compile_s']:.1f} s"
            + _describe_check(row["reference"]))
    for entry in manifest.get("train_artifacts", []):
        if not wanted(entry, "train_step"):
            continue
        step = CompiledTrainStep(load_train_step(export_dir, entry, manifest), initial_train_state(weights, manifest))
        check = check_train_step(step, entry, manifest, reference)
        batch = random_inputs(manifest, entry, rng) + random_labels(entry, rng)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "batch_size": entry["batch_size"],
               "precision": entry["precision"], **time_train_step(step, batch, train_runs or runs, warmup),
               "reference": check}
        del step  # its state (weights and Adam slots) leaves the device before the next artifact
        result["train_step"].append(row)
        if on_row is not None:
            on_row(result)
        log(f"train step {entry['batch_size']} x {entry['points']} points ({entry['precision']}): median "
            f"{row['median_ms']:.2f} ms ({row['ms_per_pair']:.2f} ms per pair), loss {row['loss_first']:.4f} -> "
            f"{row['loss_last']:.4f}, compile {row['compile_s']:.1f} s" + _describe_check(row["reference"]))
    result["total_s"] = time.perf_counter() - start
    return result


def _describe_check(check: dict | None) -> str:
    return "" if check is None else "; vs TensorFlow: " + ", ".join(f"{k} {v:.3g}" for k, v in check.items())


def latency_table(result: dict) -> str:
    """Markdown table of a `run_export` result beside the paper's P100 figures (speed-up = P100 mean / our median; the
    target is at least `TARGET_SPEEDUP_VS_P100` times the P100)."""
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
    checks = [(f"forward {r['points']:,} points {r['precision']}", r.get("reference")) for r in result["latency"]]
    if result.get("train_step") or any(r.get("kind") == "train_step" for r in result["skipped"]):
        lines += ["", "Training step (forward, loss, backward, Adam; batch on the device; state updated in place)", "",
                  "| batch x points | precision | median ms | min ms | ms per pair | pairs/s | loss first -> last |",
                  "|---|---|---:|---:|---:|---:|---|"]
        for row in result.get("train_step", []):
            lines.append(f"| {row['batch_size']} x {row['points']:,} | {row['precision']} | {row['median_ms']:.2f} | "
                         f"{row['min_ms']:.2f} | {row['ms_per_pair']:.2f} | {row['pairs_per_s']:.1f} | "
                         f"{row['loss_first']:.4f} -> {row['loss_last']:.4f} |")
            checks.append((f"train step {row['batch_size']} x {row['points']:,} {row['precision']}",
                           row.get("reference")))
        for row in result["skipped"]:
            if row.get("kind") == "train_step":
                lines.append(f"| {row['batch_size']} x {row['points']:,} | {row['precision']} | skipped: "
                             f"{row['reason']} | | | | |")
    checks = [(name, check) for name, check in checks if check]
    if checks:
        lines += ["", "Against TensorFlow's results on the reference inputs (export machine, CPU, float32):", ""]
        lines += [f"- {name}:{_describe_check(check).split(':', 1)[1]}" for name, check in checks]
    return "\n".join(lines)
