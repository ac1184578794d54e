"""What more sweeps cost on this CPU: the forward as served and the Trainer's training step of the pair and of
`model.temporal` stack and delta on 3 and 5 sweeps, at --points points per sweep, each variant in a process of its
own, one after another in one run, with the ratios to the pair's and the issue's bar (delta on 5 sweeps: forward at
most 1.5x the pair's).

python lab/tools/benchmark_sweeps_cost.py [--config configs/fastflow3d_waymo.yaml] [--points 32000]
    [--forward_runs 10] [--step_runs 3] [--export_sizes] [--json benchmarks/sweeps_cost_cpu.json] [--set key=value ...]

--export_sizes also writes each variant's portable XLA forward (CPU and CUDA, tools/export_xla.py's) and records its
size: what a GPU machine is sent.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402
from lab.training import sweeps_cost  # noqa: E402

DELTA_5_FORWARD_BAR = 1.5  # the target: delta on 5 sweeps over the pair's forward


def main():
    _common.start("inference")  # before TensorFlow is imported (the children inherit it)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="configs/fastflow3d_waymo.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--points", type=int, default=32000, help="points per sweep")
    p.add_argument("--forward_runs", type=int, default=10)
    p.add_argument("--step_runs", type=int, default=3)
    p.add_argument("--export_sizes", action="store_true")
    p.add_argument("--json", default=paths.benchmark_file("sweeps_cost_cpu.json"))
    args = p.parse_args()
    from ff3d_tf import cpu
    from lab import bench
    from lab.children import run_child
    results = {}
    for name, sets in sweeps_cost.VARIANTS.items():
        print(f"{name}: measuring ...", flush=True)
        results[name] = run_child("lab.training.sweeps_cost:measure", {
            "config": args.config, "sets": [*sets, *args.set], "points": args.points,
            "forward_runs": args.forward_runs, "step_runs": args.step_runs, "export_sizes": args.export_sizes},
            cores=os.cpu_count(), what=name, on_error="record")
        r = results[name]
        print(r["error"] if "error" in r else
              f"{name}: {r['params']:,} parameters, forward {r['forward']['median_ms']:.0f} ms, training step "
              f"{r['train_step']['median_ms']:.0f} ms, peak RSS {r['peak_rss_gb']:.2f} GB", flush=True)
    ratios = sweeps_cost.ratios(results)
    delta_5 = ratios.get("delta_5", {}).get("forward")
    result = {"what": "forward (inference plan) and training step (the Trainer's, training plan) per number of sweeps, "
                      "each variant in its own process, medians in ms; ratios over the pair's in this run",
              "command": " ".join(["lab/tools/benchmark_sweeps_cost.py"] + sys.argv[1:]),
              "variants": results, "ratios_to_pair": ratios,
              "delta_5_forward_bar": {"target_at_most": DELTA_5_FORWARD_BAR, "measured": delta_5,
                                      "met": delta_5 is not None and delta_5 <= DELTA_5_FORWARD_BAR},
              "cpu": cpu.describe(), "load_average_1_5_15": bench.load_average()}
    bench.write_json(args.json, result)
    for name, r in ratios.items():
        print(f"{name}: forward {r['forward']:.2f}x, training step {r['train_step']:.2f}x the pair's")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    _common.run(main)
