"""Timing NSFP's exported programs (`ff3d_tf.labels.nsfp_program`): on the default JAX device with JAX alone
(`run_export`, lab/tools/run_nsfp_xla.py, lab/tools/gpu_check.sh: seconds per Adam step, per grid build and per pair,
with the check against TensorFlow's reference) and, where TensorFlow is installed too, against TensorFlow's own fit
and grid build on this machine (`compare_on_this_machine`, lab/tools/benchmark_nsfp_xla_cpu.py).

Importing it imports no TensorFlow (`compare_on_this_machine` imports it when called): the runner uses it where only
JAX is installed.
"""
from __future__ import annotations

import dataclasses
import json
import time

import numpy as np

from ff3d_tf import cpu
from ff3d_tf.labels.nsfp_program import (CompiledNsfp, check_reference, entry_pair, initial_state, load_initial_params,
                                         load_reference, load_state_arrays, padded_clouds, read_manifest)
from lab import bench


def time_entry(nsfp: CompiledNsfp, start_state, runs: int, pair_steps: int, pair_runs: int) -> dict:
    """Seconds per Adam step (median of `runs` segment calls / their steps), per grid build (median, one cloud) and
    per pair (median of `pair_runs`: both clouds from the host, both grids, `pair_steps` steps rounded up to whole
    segments, the motion back to the host; at least one) on the entry's synthetic pair, and that pair's end-point
    error (m, moving and static points)."""
    pair = entry_pair(nsfp.entry)
    host_clouds = padded_clouds(pair, nsfp.entry)
    clouds = nsfp.put(host_clouds)
    grids, state = nsfp.fit(clouds, start_state, 1)  # warm-up: both programs run once
    grid_ms = bench.measure(lambda: nsfp.grids(clouds)[1].block_until_ready(), runs, 1)
    holder = {"state": state}

    def one_segment():
        holder["state"] = nsfp.segment(holder["state"], clouds, grids)
        holder["state"][nsfp.index["best_loss"]].block_until_ready()
    step_ms = bench.measure(one_segment, runs, 1)
    calls = -(-pair_steps // nsfp.segment_steps)

    def one_pair():
        _, s = nsfp.fit(nsfp.put(host_clouds), start_state, calls)
        holder["motion_m"] = np.asarray(s[nsfp.index["best_motion"]])
    pair_ms = bench.measure(one_pair, max(pair_runs, 1), 0)
    motion = holder["motion_m"][: nsfp.entry["points"]]
    moving = np.abs(pair["motion_m"]).sum(1) > 0
    s = nsfp.segment_steps
    return {"seconds_per_step": bench.middle([r["ms"] for r in step_ms]) / 1e3 / s,
            "grid_build_s_one_cloud": bench.middle([r["ms"] for r in grid_ms]) / 1e3,
            "pair_steps": calls * s, "seconds_per_pair": bench.middle([r["ms"] for r in pair_ms]) / 1e3,
            "segment_steps": s, "runs": runs, "pair_runs": pair_runs, "compile_s": nsfp.compile_s,
            "pair_epe_moving_m": float(np.linalg.norm(motion[moving] - pair["motion_m"][moving], axis=1).mean()),
            "pair_epe_static_m": float(np.linalg.norm(motion[~moving], axis=1).mean())}


def run_export(export_dir: str, runs: int = 5, pair_steps: int = 500, pair_runs: int = 3, precisions=(), points=(),
               budget_s: float | None = None, log=print, on_row=None) -> dict:
    """Times every (entry, precision) of an NSFP export directory on the default JAX device, with the reference
    check where the export has one: precision by precision (the float32 rows, and the check, first), entries in the
    manifest's order; (entry, precision) pairs not started within `budget_s` are listed as skipped."""
    import jax
    start = time.perf_counter()
    manifest = read_manifest(export_dir)
    params = load_initial_params(export_dir, manifest)
    stored = load_state_arrays(export_dir)
    reference = load_reference(export_dir)
    device = jax.devices()[0]
    result = {"export_dir": export_dir, "jax": jax.__version__, "platform": device.platform,
              "device": getattr(device, "device_kind", str(device)), "options": manifest["options"],
              "hyper": manifest["hyper"], "exported_with": manifest.get("exported_with", {}),
              "job_fit_every": manifest.get("job_fit_every", 1), "rows": [], "skipped": []}
    grid_cache: dict = {}  # one compiled grid program per entry, whatever the precision
    order = list(dict.fromkeys(p for entry in manifest["entries"] for p in entry["fit_files"]))
    for precision, entry in [(p, e) for p in order for e in manifest["entries"] if p in e["fit_files"]]:
        if (precisions and precision not in precisions) or (points and entry["points"] not in points):
            continue
        if budget_s is not None and time.perf_counter() - start > budget_s:
            result["skipped"].append({"points": entry["points"], "precision": precision,
                                      "reason": f"time budget of {budget_s:.0f} s spent"})
            continue
        nsfp = CompiledNsfp(export_dir, manifest, entry, precision, grid_cache)
        start_state = initial_state(entry, params, stored)
        row = {"points": entry["points"], "padded_points": entry["padded_points"], "precision": precision,
               "grid_dims": entry["dims"], **time_entry(nsfp, start_state, runs, pair_steps, pair_runs),
               "reference": check_reference(nsfp, start_state, reference)}
        del nsfp
        result["rows"].append(row)
        if on_row is not None:
            on_row(result)
        log(describe_row(row))
    result["total_s"] = time.perf_counter() - start
    return result


def describe_row(row: dict) -> str:
    check = row["reference"]
    text = (f"NSFP {row['points']:,} points ({row['precision']}): {row['seconds_per_step'] * 1e3:.2f} ms per step, "
            f"grid {row['grid_build_s_one_cloud'] * 1e3:.1f} ms per cloud, {row['seconds_per_pair']:.3f} s per pair "
            f"of {row['pair_steps']} steps, compile {row['compile_s']:.1f} s")
    if check:
        text += "; vs TensorFlow: " + ", ".join(f"{k} {v:.3g}" for k, v in check.items())
    return text


def nsfp_table(result: dict, target_s_per_pair: float = 1.0, target_points: int = 150000) -> str:
    """Markdown table of a `run_export` result: seconds per pair at the measured steps and, from the seconds per
    step, at NSFP's step counts; the issue's target (<= 1 s per pair at 150K points), judged on the entry that fits
    every point of such a pair and on the one the pseudo-label job fits (every `job_fit_every`-th point)."""
    lines = [f"NSFP per-pair fit, {result['device']} ({result['platform']}, jax {result['jax']})", "",
             "| points | precision | ms per step | grid ms (one cloud) | s per pair (measured) | s at 1000 steps | "
             "s at 5000 steps |", "|---:|---|---:|---:|---|---:|---:|"]
    for row in result["rows"]:
        grids_s = 2 * row["grid_build_s_one_cloud"]
        lines.append(f"| {row['points']:,} | {row['precision']} | {row['seconds_per_step'] * 1e3:.2f} | "
                     f"{row['grid_build_s_one_cloud'] * 1e3:.1f} | {row['seconds_per_pair']:.3f} at "
                     f"{row['pair_steps']} steps | {grids_s + 1000 * row['seconds_per_step']:.2f} | "
                     f"{grids_s + 5000 * row['seconds_per_step']:.2f} |")
    for row in result["skipped"]:
        lines.append(f"| {row['points']:,} | {row['precision']} | skipped: {row['reason']} | | | | |")
    fit_every = result.get("job_fit_every", 1)
    fitted = {target_points: "every point fitted"}
    if fit_every > 1:
        fitted[-(-target_points // fit_every)] = f"one point in {fit_every} fitted, as the pseudo-label job does"
    for row in [r for r in result["rows"] if r["points"] in fitted]:
        met = "met" if row["seconds_per_pair"] <= target_s_per_pair else "not met"
        lines.append(f"\nTarget <= {target_s_per_pair:g} s per pair of {target_points:,} points "
                     f"({fitted[row['points']]}: {row['points']:,}; {row['precision']}, {row['pair_steps']} steps): "
                     f"{met}")
    checks = [r for r in result["rows"] if r["reference"]]
    if checks:
        lines += ["", "Against TensorFlow's grids and fit on the reference pair (export machine, CPU, float32):", ""]
        lines += [f"- {r['points']:,} points {r['precision']}: " + ", ".join(
            f"{k} {v:.3g}" for k, v in r["reference"].items()) for r in checks]
    return "\n".join(lines)


def export_options(manifest: dict):
    """The `nsfp.NsfpOptions` an NSFP export was written with (its manifest's "options")."""
    from ff3d_tf.labels import nsfp
    return nsfp.NsfpOptions(**{k: tuple(v) if isinstance(v, list) else v for k, v in manifest["options"].items()})


def compare_on_this_machine(export_dir: str, options=None, points: int | None = None, rounds: int = 2,
                            log=print) -> dict:
    """Seconds per Adam step and per grid build on this machine's default JAX device (the CPU here) through the
    exported float32 programs against TensorFlow's own (`nsfp._fit_segment`, `build_distance_grid`), on the pair of
    `points` points (default: the first entry's): after one warm-up call each (compilation), `rounds` rounds that call
    each of the four once in turn (`bench.round_robin`: a change of load hits all alike), medians. `options` (an
    `nsfp.NsfpOptions`) must be those of the export; default: the export's own (`export_options`)."""
    import tensorflow as tf
    from ff3d_tf.labels import nsfp
    from ff3d_tf.labels.nsfp_export import tf_grids, tf_segment
    manifest = read_manifest(export_dir)
    options = export_options(manifest) if options is None else options
    entry = next(e for e in manifest["entries"] if points in (None, e["points"]))
    if json.loads(json.dumps(dataclasses.asdict(options))) != manifest["options"]:
        raise ValueError(f"{export_dir} was exported with other NSFP options: {manifest['options']}")
    host_clouds = padded_clouds(entry_pair(entry), entry)
    tf_clouds = tuple(tf.constant(c) for c in host_clouds)
    program = CompiledNsfp(export_dir, manifest, entry, "float32")
    start = initial_state(entry, load_initial_params(export_dir, manifest), load_state_arrays(export_dir))
    jax_clouds = program.put(host_clouds)
    jax_grids, jax_state = program.fit(jax_clouds, start, 0)
    tf_grid_pair = tf_grids(entry, host_clouds, options)
    segment = tf_segment(options, entry, manifest["hyper"])
    held = {"tf": nsfp.initial_fit_state(options, entry["padded_points"]), "jax": jax_state}
    loss_at = program.index["best_loss"]

    def tf_step():
        held["tf"] = segment(held["tf"], tf_clouds, tf_grid_pair)
        held["tf"].best_loss.numpy()

    def jax_step():
        held["jax"] = program.segment(held["jax"], jax_clouds, jax_grids)
        held["jax"][loss_at].block_until_ready()
    calls = {"tf_fit": tf_step, "jax_fit": jax_step,
             "tf_grid": lambda: tf_grids(entry, host_clouds, options)[0].distance_m.numpy(),
             "jax_grid": lambda: program.grids(jax_clouds)[0].block_until_ready()}
    readings = bench.round_robin(calls, rounds, warmup=1)
    ms = {name: bench.middle([r["ms"] for r in rows]) for name, rows in readings.items()}
    s = entry["segment_steps"]
    result = {"cpu": cpu.describe(), "points": entry["points"], "padded_points": entry["padded_points"],
              "grid_dims": entry["dims"], "segment_steps": s, "rounds": rounds, "jax_compile_s": program.compile_s,
              "tf_seconds_per_step": ms["tf_fit"] / 1e3 / s, "jax_seconds_per_step": ms["jax_fit"] / 1e3 / s,
              "tf_grid_s_one_cloud": ms["tf_grid"] / 1e3, "jax_grid_s_one_cloud": ms["jax_grid"] / 1e3,
              "load_average_at_end": bench.load_average()}
    result["jax_over_tf_per_step"] = result["jax_seconds_per_step"] / result["tf_seconds_per_step"]
    result["jax_over_tf_grid"] = result["jax_grid_s_one_cloud"] / result["tf_grid_s_one_cloud"]
    log(f"{entry['points']} points: {result['jax_seconds_per_step']:.3f} s per step through the exported program, "
        f"{result['tf_seconds_per_step']:.3f} s in TensorFlow (ratio {result['jax_over_tf_per_step']:.2f}); grid "
        f"{result['jax_grid_s_one_cloud']:.2f} s vs {result['tf_grid_s_one_cloud']:.2f} s per cloud")
    return result
