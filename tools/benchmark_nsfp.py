"""NSFP pseudo-labels (ff3d_tf.labels.nsfp) on this machine: seconds per pair, distance transform vs exact nearest
neighbours, and the labels' end-point error on the Argoverse 2 sample pair. JSON out.

python tools/benchmark_nsfp.py --out benchmarks/nsfp_cpu.json [--points 65536] [--av2_log data/av2_sample_log]
    [--av2_subsample 4] [--av2_max_iterations N]

In one process:
- speed: the benchmark cloud (`ff3d_tf.bench.random_clouds`, --points points in the AV2 crop box) as a pair; the
  distance grids' build time, and seconds per Adam step with the distance transform and with exact nearest neighbours
  (each timed over a capped number of steps after a warm-up that compiles; the exact one is far slower). Seconds per
  pair = grid build + seconds per step x steps, at the steps the Argoverse pair took to stop early and at the cap.
- av2_sample: what a user runs on the Argoverse 2 sample log, in child processes: `tools/write_pair_records.py
  --source av2`, then `tools/pseudo_label.py` with its defaults (plus --av2_args), whose own scores against
  Argoverse's labels (pseudo_label_scores.json: the challenge's arithmetic, beside zero flow) and counts are kept,
  beside the bar (three-way EPE <= 0.08 m, bucketed normalized dynamic EPE <= 0.6) with `meets_bar`, the wall time
  and the command lines.
Each section is written to --out as it completes; a rerun keeps the sections already there (--fresh to redo; an
av2_sample section of other --av2_args is redone).
"""
import argparse
import dataclasses
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time

import _common  # noqa: F401

import numpy as np

from ff3d_tf import bench, cpu, metrics_av2
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.labels import nsfp, pseudo_records

BAR = {"three_way/mean_epe_m": 0.08, "bucketed/mean_dynamic_norm_epe": 0.6}  # at most, at full density
TOOLS = os.path.dirname(os.path.abspath(__file__))


def _save(path: str, result: dict) -> None:
    partial = path + ".partial"
    with open(partial, "w") as f:
        json.dump(result, f, indent=1)
    os.replace(partial, path)


def _speed(points: int, dt_steps: int, exact_steps: int, options: nsfp.NsfpOptions) -> dict:
    rng = np.random.default_rng(0)
    box = metrics_av2.MAX_DISTANCE_M
    clouds = bench.random_clouds(rng, points, points, ((-box, box), (-box, box), (-0.5, 3.0)))
    t0, tm1 = clouds["points_xyz_t0"][0], clouds["points_xyz_tm1_in_t0"][0]
    out = {"points": points, "point_bucket": bucket_size(points, options.point_bucket_base)}
    for name, exact, steps in (("distance_transform", False, dt_steps), ("exact_nearest_neighbours", True,
                                                                           exact_steps)):
        run = dataclasses.replace(options, exact_chamfer=exact, max_iterations=steps, patience=steps + 1,
                                  segment_iterations=steps)
        start = time.perf_counter()
        nsfp.nsfp_flow(t0, tm1, 0.1, dataclasses.replace(run, max_iterations=1))  # compiles both programs
        warmup_s = time.perf_counter() - start
        result = nsfp.nsfp_flow(t0, tm1, 0.1, run)
        out[name] = {"timed_steps": result.num_iterations, "seconds_per_step": result.fit_s / result.num_iterations,
                     "grid_build_s_both_clouds": result.grid_s, "first_call_s_with_compilation": warmup_s}
        print(f"{name}: {out[name]['seconds_per_step']:.3f} s/step, grids {result.grid_s:.2f} s "
              f"(first call {warmup_s:.1f} s)", flush=True)
    dt, ex = out["distance_transform"], out["exact_nearest_neighbours"]
    out["exact_over_distance_transform_per_step"] = ex["seconds_per_step"] / dt["seconds_per_step"]
    return out


def _av2(log_dir: str, extra_args: list[str]) -> dict:
    load_average = bench.load_average()
    with tempfile.TemporaryDirectory() as tmp:
        records, pseudo = os.path.join(tmp, "records"), os.path.join(tmp, "pseudo")
        commands = [[sys.executable, os.path.join(TOOLS, "write_pair_records.py"), "--source", "av2", "--input",
                     log_dir, "--out_dir", records],
                    [sys.executable, os.path.join(TOOLS, "pseudo_label.py"), "--input", records, "--out_dir", pseudo,
                     *extra_args]]
        start = time.perf_counter()
        for command in commands:
            print("$", shlex.join(command[1:]), flush=True)
            subprocess.run(command, check=True)
        wall_s = time.perf_counter() - start
        with open(os.path.join(pseudo, pseudo_records.SCORES_NAME)) as f:
            scores = json.load(f)
        with open(os.path.join(pseudo, "pseudo_label_counts.json")) as f:
            counts = json.load(f)
    return {"args": extra_args, "commands": [shlex.join(["python", os.path.relpath(c[1], os.path.dirname(TOOLS)),
                                                          *c[2:]]) for c in commands],
            **scores, "counts": counts, "wall_s_both_tools": wall_s, "load_average_at_start": load_average,
            "bar_at_most": BAR, "meets_bar": all(scores["nsfp"][k] <= bar for k, bar in BAR.items())}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="benchmarks/nsfp_cpu.json")
    p.add_argument("--points", type=int, default=65536)
    p.add_argument("--dt_steps", type=int, default=10, help="Adam steps timed with the distance transform")
    p.add_argument("--exact_steps", type=int, default=3, help="Adam steps timed with exact nearest neighbours")
    p.add_argument("--av2_log", default=os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                                     "data", "av2_sample_log"))
    p.add_argument("--av2_args", default="", help="extra flags of tools/pseudo_label.py, e.g. '--set nsfp.fit_every=8' "
                   "(its options are the config's nsfp section)")
    p.add_argument("--skip_av2", action="store_true")
    p.add_argument("--fresh", action="store_true", help="redo sections already in --out")
    args = p.parse_args()
    result = {}
    if os.path.exists(args.out) and not args.fresh:
        with open(args.out) as f:
            result = json.load(f)
    job_fit = pseudo_records.JobOptions().nsfp
    # The machine and options of the speed section: kept with it when a rerun redoes only the av2 section.
    result.setdefault("machine", {**cpu.describe(), "load_average_at_start": bench.load_average()})
    result.setdefault("options", dataclasses.asdict(job_fit))
    if "speed" not in result:
        result["speed"] = _speed(args.points, args.dt_steps, args.exact_steps, job_fit)
        _save(args.out, result)
    extra_args = shlex.split(args.av2_args)
    if not args.skip_av2 and result.get("av2_sample", {}).get("args") != extra_args:
        result["av2_sample"] = _av2(args.av2_log, extra_args)
        _save(args.out, result)
    speed = result["speed"]
    steps = {"max_iterations": job_fit.max_iterations}
    av2 = result.get("av2_sample", {})
    if av2:
        steps["av2_sample_steps"] = av2["counts"]["nsfp_iterations"]
    per_pair = {}
    for name in ("distance_transform", "exact_nearest_neighbours"):
        grid_s = speed["distance_transform"]["grid_build_s_both_clouds"] if name == "distance_transform" else 0.0
        per_pair[name] = {k: grid_s + speed[name]["seconds_per_step"] * n for k, n in steps.items()}
    result["seconds_per_pair"] = {
        "how": "grid build (both clouds) + seconds per Adam step x steps; seconds per step timed over "
               f"{speed['distance_transform']['timed_steps']} steps (distance transform) and "
               f"{speed['exact_nearest_neighbours']['timed_steps']} steps (exact nearest neighbours, capped: one "
               "full exact fit would take hours here), same process, the benchmark cloud of "
               f"{speed['points']} points; at the steps the Argoverse sample pair's fit took (av2_sample_steps) "
               "and at the cap (max_iterations)",
        **per_pair}
    _save(args.out, result)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
