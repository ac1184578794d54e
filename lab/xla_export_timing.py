"""The run that times every artifact kind of a portable XLA export directory (`ff3d_tf.xla_export_dir`) on the default
JAX device, each kind an `ArtifactTiming` (the forward: `lab.inference.xla_timing.ForwardTiming`; the training step:
`lab.training.xla_step_timing.TrainStepTiming`), and its tables (lab/tools/run_xla.py, lab/tools/gpu_check.sh).

Like `ff3d_tf.xla_export_dir`, importing it imports neither TensorFlow nor JAX: it runs where only JAX is installed.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Protocol, Sequence

import numpy as np

from ff3d_tf import cpu
from ff3d_tf.xla_export_dir import load_reference, load_weights, read_manifest


@dataclasses.dataclass
class ExportRun:
    """What every artifact timing of one run reads: the directory, its manifest, weights and reference (None when it
    has none), and the run's random generator (the benchmark inputs, drawn in manifest order)."""
    export_dir: str
    manifest: dict
    weights: list
    reference: dict | None
    rng: np.random.Generator


class ArtifactTiming(Protocol):
    """One kind of artifact as `run_export` times it."""
    kind: str  # a skipped row's "kind"
    manifest_key: str  # the manifest's list of this kind's entries
    result_key: str  # the result's list of this kind's rows

    def time(self, run: ExportRun, entry: dict) -> dict:
        """The row of one entry: its timing and "reference" (the check against TensorFlow's results, or None)."""

    def describe(self, row: dict) -> str:
        """The log line of a row."""

    def table(self, result: dict) -> list[str]:
        """The Markdown lines of this kind's rows (none when the run has none)."""

    def check_name(self, row: dict) -> str:
        """What a row's reference check is called in the table."""


def run_export(export_dir: str, timings: Sequence[ArtifactTiming], precisions=None, points=None,
               budget_s: float | None = None, seed: int = 0, log=print, on_row=None) -> dict:
    """Times the artifacts of an export directory, kind by kind in the order of `timings` (optionally only some
    precisions / point counts), each with its reference check.

    Artifacts still untimed when `budget_s` seconds have passed are listed as skipped (a GPU check must end in time).
    `on_row(result)` is called after each timed artifact with the result so far (e.g. to save partial results).
    """
    import jax
    start = time.perf_counter()
    manifest = read_manifest(export_dir)
    weights = load_weights(export_dir, manifest)
    device = jax.devices()[0]
    result = {"export_dir": export_dir, "host_cpu": cpu.describe(), "jax": jax.__version__, "platform": device.platform,
              "device": getattr(device, "device_kind", str(device)), "num_weights": len(weights),
              "exported_with": manifest.get("exported_with", {}), **{t.result_key: [] for t in timings},
              "skipped": []}
    run = ExportRun(export_dir, manifest, weights, load_reference(export_dir), np.random.default_rng(seed))

    def wanted(entry, kind):
        if (precisions and entry["precision"] not in precisions) or (points and entry["points"] not in points):
            return False
        if budget_s is not None and time.perf_counter() - start > budget_s:
            result["skipped"].append({"kind": kind, "points": entry["points"], "precision": entry["precision"],
                                      "batch_size": entry["batch_size"],
                                      "reason": f"time budget of {budget_s:.0f} s spent"})
            return False
        return True

    for timing in timings:
        for entry in manifest.get(timing.manifest_key, []):
            if not wanted(entry, timing.kind):
                continue
            row = timing.time(run, entry)
            result[timing.result_key].append(row)
            if on_row is not None:
                on_row(result)
            log(timing.describe(row))
    result["total_s"] = time.perf_counter() - start
    return result


def describe_check(check: dict | None) -> str:
    """"; vs TensorFlow: " and a reference check's differences, or "" without one."""
    return "" if check is None else "; vs TensorFlow: " + ", ".join(f"{k} {v:.3g}" for k, v in check.items())


def results_table(result: dict, timings: Sequence[ArtifactTiming]) -> str:
    """Markdown tables of a `run_export` result, one per kind of `timings`, then the reference checks of every row."""
    lines, checks = [], []
    for timing in timings:
        lines += timing.table(result)
        checks += [(timing.check_name(row), row.get("reference")) for row in result.get(timing.result_key, [])]
    checks = [(name, check) for name, check in checks if check]
    if checks:
        lines += ["", "Against TensorFlow's results on the reference inputs (export machine, CPU, float32):", ""]
        lines += [f"- {name}:{describe_check(check).split(':', 1)[1]}" for name, check in checks]
    return "\n".join(lines)
