"""Self-supervision's preparation (`tools/prepare_self_supervision.py`) on this machine: its time per pair beside the
NSFP pseudo-label job's (`tools/pseudo_label.py`) on the same CPU, and DUFOMap's dynamic flags scored against flow
labels (lab/tools/benchmark_self_supervision_prep.py).

Sections of the results, each a run of the tools users run (child processes), written to the output file as it
completes (`run`; a rerun keeps the sections already there):
- synthetic (`synthetic`): a realistic synthetic Argoverse 2 log (`tools/make_synthetic_data.py --format av2
  --realistic`), its records (`tools/write_pair_records.py --source av2`), prepared with the synthetic up lidar's
  mounting position as the sensor origin; the job's own counts, its seconds per pair, and the flags against the
  generator's flow labels (`flag_scores`).
- av2_sample (`av2_sample`): the same on the real Argoverse 2 pair in data/ (two sweeps), the sensor origin the log's
  own up lidar (calibration/egovehicle_SE3_sensor.feather), scored against Argoverse's labels.
- nsfp (`nsfp`): the NSFP job with its defaults on the same real pair, capped at `nsfp_steps` Adam steps: its
  seconds per step here, times the steps the uncapped fit takes (benchmarks/nsfp_cpu.json, `av2_sample.counts
  .nsfp_iterations`): NSFP's seconds per pair on this CPU (the grid build is in the timed seconds, so slightly
  over), beside the preparation's on the same pair (`ratios`, against `TARGET_RATIO`).

Flags (`flag_scores`): over the t0 points of every record that are labelled (class >= 0), not ground by the job's
ground flags, and in the Argoverse 2 challenge's box (`metrics_av2.MAX_DISTANCE_M`): a point is truly moving when its
label is at least `schema.MOVING_THRESHOLD_MPS`; flagged when the job calls it dynamic (in a cluster or not).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from typing import Callable

import numpy as np

from ff3d_tf import cpu, metrics_av2, schema
from ff3d_tf.data import pair_records
from ff3d_tf.labels import enrich_records, self_supervision
from lab import bench, paths

SYNTHETIC_SEED = 11
TARGET_RATIO = 20.0  # issue 53: the preparation at least this many times cheaper per pair than the NSFP job
NSFP_REFERENCE = "nsfp_cpu.json"  # whose av2_sample counts give the steps of the uncapped fit of the real pair


def flag_scores(records_dir: str) -> dict:
    """Precision and recall of the job's dynamic flags (module docstring) over every record of `records_dir`."""
    manifest = pair_records.read_manifest(records_dir)
    flagged = moving = both = scored = 0
    for name in sorted(os.listdir(records_dir)):
        if not name.endswith(pair_records.FILE_SUFFIX):
            continue
        for _, ex in enrich_records.read_examples(os.path.join(records_dir, name), manifest, False, {}):
            value = ex[schema.DYNAMIC_CLUSTER_KEY_FORMAT.format(cloud="t0")]
            region = metrics_av2.eval_mask(ex["points_xyz_t0"], value == schema.DYNAMIC_CLUSTER_GROUND)
            region &= ex["class_id_t0"] >= 0
            dynamic = value >= schema.DYNAMIC_CLUSTER_NOISE
            truth = np.linalg.norm(ex["flow_mps_t0"], axis=1) >= schema.MOVING_THRESHOLD_MPS
            scored += int(region.sum())
            flagged += int((dynamic & region).sum())
            moving += int((truth & region).sum())
            both += int((dynamic & truth & region).sum())
    return {"scored_points": scored, "flagged_dynamic": flagged, "truly_moving": moving, "flagged_and_moving": both,
            "precision": both / flagged if flagged else float("nan"),
            "recall": both / moving if moving else float("nan")}


def _tool(tools_dir: str, name: str, *args: str) -> list[str]:
    return [sys.executable, os.path.join(tools_dir, name), *args]


def _run(commands: list[list[str]], log: Callable[[str], None]) -> float:
    started = time.perf_counter()
    for command in commands:
        log("$ " + " ".join(command))
        subprocess.run(command, check=True)
    return time.perf_counter() - started


def _prepared(records: str, out: str, origin_m, tools_dir: str, threads: int, log) -> dict:
    sets = [f"selfsup.sensor_origin_m=[{', '.join(f'{v:g}' for v in origin_m)}]", f"selfsup.num_threads={threads}"]
    command = _tool(tools_dir, "prepare_self_supervision.py", "--input", records, "--out_dir", out,
                    *[a for s in sets for a in ("--set", s)])
    wall = _run([command], log)
    with open(os.path.join(out, f"{self_supervision.JOB_NAME}_counts.json")) as f:
        counts = json.load(f)
    return {"command": " ".join(command[1:]), "counts": counts, "wall_s_tool": wall,
            "seconds_per_pair": counts["seconds"] / max(counts["records"], 1),
            "dufomap_seconds_per_sweep": counts["dufomap_seconds"] / max(counts["sweeps"], 1),
            "flags": flag_scores(out)}


def synthetic(num_sweeps: int, tools_dir: str, threads: int, log=print) -> dict:
    from ff3d_tf.data.synthetic import av2 as synthetic_av2
    with tempfile.TemporaryDirectory() as tmp:
        data, records = os.path.join(tmp, "data"), os.path.join(tmp, "records")
        _run([_tool(tools_dir, "make_synthetic_data.py", "--format", "av2", "--realistic", "--out_dir", data,
                    "--num_logs", "1", "--sweeps_per_log", str(num_sweeps), "--seed", str(SYNTHETIC_SEED)),
              _tool(tools_dir, "write_pair_records.py", "--source", "av2", "--input", os.path.join(data, "train"),
                    "--out_dir", records)],
             log)
        up = next(lidar for lidar in synthetic_av2.LIDARS if lidar.name == "up_lidar")
        section = _prepared(records, os.path.join(tmp, "prepared"), up.translation, tools_dir, threads, log)
    return {"num_sweeps": num_sweeps, "generator": "synthetic Argoverse 2, realistic", "seed": SYNTHETIC_SEED,
            "sensor_origin_m": list(up.translation), **section}


def av2_up_lidar_m(log_dir: str) -> list[float]:
    """The up lidar's position in the ego frame (m) from the log's calibration/egovehicle_SE3_sensor.feather."""
    import pyarrow.feather as feather
    table = feather.read_table(os.path.join(log_dir, "calibration", "egovehicle_SE3_sensor.feather")).to_pydict()
    row = table["sensor_name"].index("up_lidar")
    return [float(table[k][row]) for k in ("tx_m", "ty_m", "tz_m")]


def av2_sample(log_dir: str, tools_dir: str, threads: int, log=print) -> dict:
    origin = av2_up_lidar_m(log_dir)
    with tempfile.TemporaryDirectory() as tmp:
        records = os.path.join(tmp, "records")
        _run([_tool(tools_dir, "write_pair_records.py", "--source", "av2", "--input", log_dir, "--out_dir", records)],
             log)
        section = _prepared(records, os.path.join(tmp, "prepared"), origin, tools_dir, threads, log)
    return {"log": os.path.relpath(log_dir, paths.ROOT), "sensor_origin_m": origin, **section}


def nsfp(log_dir: str, tools_dir: str, steps: int, log=print) -> dict:
    with open(paths.benchmark_file(NSFP_REFERENCE)) as f:
        uncapped = json.load(f)["av2_sample"]["counts"]["nsfp_iterations"]
    with tempfile.TemporaryDirectory() as tmp:
        records, out = os.path.join(tmp, "records"), os.path.join(tmp, "pseudo")
        command = _tool(tools_dir, "pseudo_label.py", "--input", records, "--out_dir", out, "--set",
                        f"nsfp.max_iterations={steps}", "--set", f"nsfp.patience={steps}")
        _run([_tool(tools_dir, "write_pair_records.py", "--source", "av2", "--input", log_dir, "--out_dir", records),
              command], log)
        with open(os.path.join(out, "pseudo_label_counts.json")) as f:
            counts = json.load(f)
    per_step = counts["nsfp_seconds"] / max(counts["nsfp_iterations"], 1)  # grid build included: an upper bound
    return {"command": " ".join(command[1:]), "counts": counts, "steps_timed": counts["nsfp_iterations"],
            "seconds_per_step": per_step, "uncapped_steps": uncapped, "uncapped_steps_from": NSFP_REFERENCE,
            "seconds_per_pair": per_step * uncapped}


def ratios(results: dict) -> dict:
    """NSFP's seconds per pair over the preparation's on the same pair (the real Argoverse 2 pair: the synthetic
    log's sweeps hold far fewer points, so its time per pair is not compared)."""
    if "nsfp" not in results or "av2_sample" not in results:
        return {}
    return {"nsfp_over_preparation_av2_sample": results["nsfp"]["seconds_per_pair"] /
            results["av2_sample"]["seconds_per_pair"]}


def run(out_path: str, sections: list[str], tools_dir: str, *, num_sweeps: int, nsfp_steps: int, threads: int,
        av2_log: str, fresh: bool = False, log=print) -> dict:
    results = {}
    if os.path.exists(out_path) and not fresh:
        with open(out_path) as f:
            results = json.load(f)
    results["machine"] = cpu.describe()
    makers = {"synthetic": lambda: synthetic(num_sweeps, tools_dir, threads, log),
              "av2_sample": lambda: av2_sample(av2_log, tools_dir, threads, log),
              "nsfp": lambda: nsfp(av2_log, tools_dir, nsfp_steps, log)}
    for name in [None] + list(sections):  # None: the sections already there, with this code's ratios
        if name is not None:
            load = bench.load_average()
            results[name] = {**makers[name](), "load_average_at_start": load}
        results["ratios"] = ratios(results)
        results["target"] = {"nsfp_over_preparation_at_least": TARGET_RATIO,
                             "met": {k: v >= TARGET_RATIO for k, v in results["ratios"].items()}}
        with open(out_path + ".partial", "w") as f:
            json.dump(results, f, indent=1, sort_keys=True)
        os.replace(out_path + ".partial", out_path)
        log(f"{name or 'ratios'}: written to {out_path}")
    return results
