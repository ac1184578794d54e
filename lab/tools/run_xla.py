"""Run and time exported artifacts with JAX alone (no TensorFlow): python lab/tools/run_xla.py DIR [--out J]

Loads DIR (written by tools/export_xla.py), compiles each artifact for the default JAX device (GPU if JAX has one),
runs it on random clouds of its size and prints the median latency of --runs passes after --warmup, in a table beside
the paper's P100 figures; then the training steps (--train_runs steps each), and, when DIR has TensorFlow's reference
results, how far the device's are from them; --out writes the same as JSON. Imports numpy, JAX and the TensorFlow-free
lab.xla_export_timing (the run over ff3d_tf.xla_export_dir), lab.inference.xla_timing (the forward) and
lab.training.xla_step_timing (the training step) only.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too; imports no TensorFlow)
from lab import tool_args  # noqa: E402

from ff3d_tf import xla_export_dir  # noqa: E402
from lab import xla_export_timing  # noqa: E402
from lab.inference import xla_timing  # noqa: E402
from lab.training import xla_step_timing  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("export_dir")
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--precisions", default="", help="only these (comma-separated); default all in the manifest")
    p.add_argument("--points", default="", help="only these cloud sizes (comma-separated); default all")
    p.add_argument("--train_runs", type=int, default=None, help="timed training steps per artifact (default --runs)")
    p.add_argument("--budget_s", type=float, default=None, help="start no artifact after this many seconds")
    p.add_argument("--out", default=None, help="JSON file of the results")
    args = p.parse_args()
    points = tool_args.int_list(p, args.points, "--points")
    save = tool_args.json_saver(args.out)

    timings = (xla_timing.ForwardTiming(args.runs, args.warmup),
               xla_step_timing.TrainStepTiming(args.train_runs or args.runs, args.warmup))
    try:
        result = xla_export_timing.run_export(args.export_dir, timings,
                                              [v for v in args.precisions.split(",") if v], points, args.budget_s,
                                              on_row=save)
    except xla_export_dir.ExportFormatError as e:
        sys.exit(f"export error: {e}")
    if not result["latency"] and not result["train_step"] and not result["skipped"]:
        sys.exit(f"no artifact in {args.export_dir} matches --precisions {args.precisions!r} --points {args.points!r}")
    result["table"] = xla_export_timing.results_table(result, timings)
    print(result["table"], flush=True)
    save(result)


if __name__ == "__main__":
    main()
