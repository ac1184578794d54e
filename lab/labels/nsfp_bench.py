"""NSFP pseudo-labels (`ff3d_tf.labels.nsfp`) on this machine: seconds per pair, distance transform against exact
nearest neighbours, and the labels' end-point error on the Argoverse 2 sample pair (lab/tools/benchmark_nsfp.py).

Sections of the results, each written to the output file as it completes (`run`):
- speed (`speed`): the benchmark cloud (`lab.bench.random_clouds`, uniform in the AV2 crop box, z in
  [-0.5, 3] m) as a pair, fitted with the pseudo-label job's fit (`nsfp.MEASURED_FIT_OPTIONS`): the distance grids'
  build time, and seconds per Adam step with the distance transform and with exact nearest neighbours, each timed
  over a capped number of steps after a one-step warm-up call that compiles (the exact one is far slower).
- av2_sample (`av2_sample`): what a user runs on the Argoverse 2 sample log, in child processes:
  tools/write_pair_records.py --source av2, then tools/pseudo_label.py with its defaults plus the given flags; its
  own scores against Argoverse's labels (`pseudo_records.SCORES_NAME`: the challenge's arithmetic, beside zero flow)
  and counts, beside the bar (`BAR`) with `meets_bar`, the wall time and the command lines.
- seconds_per_pair (`seconds_per_pair`): grid build + seconds per step x steps, at the steps the Argoverse pair's fit
  took to stop early and at the cap.
A rerun keeps the sections already in the file (`fresh` redoes them; an av2_sample section of other flags is redone).
"""
from __future__ import annotations

import dataclasses
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from typing import Callable, Sequence

import numpy as np

from ff3d_tf import cpu, metrics_av2
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.labels import nsfp, pseudo_records
from lab import bench

BAR = {"three_way/mean_epe_m": 0.08, "bucketed/mean_dynamic_norm_epe": 0.6}  # at most, at full density
COUNTS_NAME = "pseudo_label_counts.json"  # the pseudo-label job's counts in its output folder
CHAMFER_METHODS = {"distance_transform": False, "exact_nearest_neighbours": True}  # name -> NsfpOptions.exact_chamfer
SPEED_Z_RANGE_M = (-0.5, 3.0)
DT_S = 0.1  # the pair's time step (s): the flow's units only, not its fit


def speed(points: int, dt_steps: int, exact_steps: int, options: nsfp.NsfpOptions = nsfp.MEASURED_FIT_OPTIONS,
          log: Callable[[str], None] = print) -> dict:
    """The speed section: `options`' fit of one benchmark pair of `points` points a cloud, timed over `dt_steps` Adam
    steps with the distance transform and `exact_steps` with exact nearest neighbours (no early stop), each after a
    one-step call that compiles both programs."""
    rng = np.random.default_rng(0)
    box_m = metrics_av2.MAX_DISTANCE_M
    clouds = bench.random_clouds(rng, points, points, ((-box_m, box_m), (-box_m, box_m), SPEED_Z_RANGE_M))
    xyz_t0, xyz_tm1 = clouds["points_xyz_t0"][0], clouds["points_xyz_tm1_in_t0"][0]
    out = {"points": points, "point_bucket": bucket_size(points, options.point_bucket_base)}
    for name, steps in zip(CHAMFER_METHODS, (dt_steps, exact_steps)):
        timed = dataclasses.replace(options, exact_chamfer=CHAMFER_METHODS[name], max_iterations=steps,
                                    patience=steps + 1, segment_iterations=steps)
        _, warmup_s = bench.elapsed(lambda: nsfp.nsfp_flow(xyz_t0, xyz_tm1, DT_S,
                                                           dataclasses.replace(timed, max_iterations=1)))
        result = nsfp.nsfp_flow(xyz_t0, xyz_tm1, DT_S, timed)
        out[name] = {"timed_steps": result.num_iterations, "seconds_per_step": result.fit_s / result.num_iterations,
                     "grid_build_s_both_clouds": result.grid_s, "first_call_s_with_compilation": warmup_s}
        log(f"{name}: {out[name]['seconds_per_step']:.3f} s/step, grids {result.grid_s:.2f} s (first call "
            f"{warmup_s:.1f} s)")
    out["exact_over_distance_transform_per_step"] = (out["exact_nearest_neighbours"]["seconds_per_step"] /
                                                     out["distance_transform"]["seconds_per_step"])
    return out


def av2_commands(log_dir: str, extra_args: Sequence[str], tools_dir: str, records_dir: str,
                 pseudo_dir: str) -> list[list[str]]:
    """The two tool runs of the av2_sample section: records of the log at `log_dir` into `records_dir`, then
    pseudo-labels of them into `pseudo_dir` with `extra_args` added."""
    return [[sys.executable, os.path.join(tools_dir, "write_pair_records.py"), "--source", "av2", "--input", log_dir,
             "--out_dir", records_dir],
            [sys.executable, os.path.join(tools_dir, "pseudo_label.py"), "--input", records_dir, "--out_dir",
             pseudo_dir, *extra_args]]


def meets_bar(scores: dict) -> bool:
    """Whether every figure of `BAR` in the NSFP scores is at most the bar."""
    return all(scores[k] <= bar for k, bar in BAR.items())


def av2_sample(log_dir: str, extra_args: Sequence[str], tools_dir: str, log: Callable[[str], None] = print) -> dict:
    """The av2_sample section (module docstring): the tools in `tools_dir` run on the log at `log_dir`."""
    load_average = bench.load_average()
    with tempfile.TemporaryDirectory() as tmp:
        pseudo = os.path.join(tmp, "pseudo")
        commands = av2_commands(log_dir, extra_args, tools_dir, os.path.join(tmp, "records"), pseudo)
        start = time.perf_counter()
        for command in commands:
            log("$ " + shlex.join(command[1:]))
            subprocess.run(command, check=True)
        wall_s = time.perf_counter() - start
        with open(os.path.join(pseudo, pseudo_records.SCORES_NAME)) as f:
            scores = json.load(f)
        with open(os.path.join(pseudo, COUNTS_NAME)) as f:
            counts = json.load(f)
    repository = os.path.dirname(os.path.normpath(tools_dir))
    shown = [shlex.join(["python", os.path.relpath(c[1], repository), *c[2:]]) for c in commands]
    return {"args": list(extra_args), "commands": shown, **scores, "counts": counts, "wall_s_both_tools": wall_s,
            "load_average_at_start": load_average, "bar_at_most": BAR, "meets_bar": meets_bar(scores["nsfp"])}


def seconds_per_pair(speed_section: dict, max_iterations: int, av2_sample_steps: int | None) -> dict:
    """{"how", and per Chamfer method {steps name: seconds}}: the grid build (both clouds; none for exact nearest
    neighbours) + seconds per Adam step x steps, at `max_iterations` (the cap) and, where known, `av2_sample_steps`
    (the steps the Argoverse sample pair's fit took)."""
    steps = {"max_iterations": max_iterations}
    if av2_sample_steps is not None:
        steps["av2_sample_steps"] = av2_sample_steps
    per_method = {}
    for name in CHAMFER_METHODS:
        grid_s = speed_section[name]["grid_build_s_both_clouds"] if name == "distance_transform" else 0.0
        per_method[name] = {k: grid_s + speed_section[name]["seconds_per_step"] * n for k, n in steps.items()}
    return {"how": "grid build (both clouds) + seconds per Adam step x steps; seconds per step timed over "
                   f"{speed_section['distance_transform']['timed_steps']} steps (distance transform) and "
                   f"{speed_section['exact_nearest_neighbours']['timed_steps']} steps (exact nearest neighbours, "
                   "capped: one full exact fit would take hours here), same process, the benchmark cloud of "
                   f"{speed_section['points']} points; at the steps the Argoverse sample pair's fit took "
                   "(av2_sample_steps) and at the cap (max_iterations)",
            **per_method}


def run(out: str, points: int, dt_steps: int, exact_steps: int, av2_log: str, av2_args: Sequence[str],
        skip_av2: bool, fresh: bool, tools_dir: str, log: Callable[[str], None] = print) -> dict:
    """The benchmark (module docstring), written to `out` after each section; the results. `av2_args`: flags added
    to tools/pseudo_label.py; `tools_dir`: the folder of the tools the av2_sample section runs."""
    result = {}
    if os.path.exists(out) and not fresh:
        with open(out) as f:
            result = json.load(f)
    fit = nsfp.MEASURED_FIT_OPTIONS
    # The machine and options of the speed section: kept with it when a rerun redoes only the av2 section.
    result.setdefault("machine", {**cpu.describe(), "load_average_at_start": bench.load_average()})
    result.setdefault("options", dataclasses.asdict(fit))
    if "speed" not in result:
        result["speed"] = speed(points, dt_steps, exact_steps, fit, log)
        bench.write_json(out, result)
    if not skip_av2 and result.get("av2_sample", {}).get("args") != list(av2_args):
        result["av2_sample"] = av2_sample(av2_log, av2_args, tools_dir, log)
        bench.write_json(out, result)
    av2 = result.get("av2_sample")
    result["seconds_per_pair"] = seconds_per_pair(result["speed"], fit.max_iterations,
                                                  av2["counts"]["nsfp_iterations"] if av2 else None)
    bench.write_json(out, result)
    return result
