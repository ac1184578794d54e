"""Run and time exported NSFP programs with JAX alone (no TensorFlow):
python lab/tools/run_nsfp_xla.py DIR [--out J]


Loads DIR (written by tools/export_nsfp_xla.py), compiles each entry's grid and fit programs for the default JAX device
(GPU if JAX has one) and, on the entry's synthetic pair, times seconds per Adam step (--runs calls of the fit
program), per grid build and per pair (both grids and --pair_steps steps, clouds from and motion back to the host;
--pair_runs pairs); when DIR has TensorFlow's reference, how far the device's grids, loss and motion are from it.
Prints a table (with the issue's target, <= 1 s per pair at 150K points); --out writes the same as JSON. Imports numpy,
JAX and the TensorFlow-free lab.labels.nsfp_timing (over ff3d_tf.labels.nsfp_program) only.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too; imports no TensorFlow)
from lab import tool_args  # noqa: E402

from ff3d_tf import xla_program  # noqa: E402
from lab.labels import nsfp_timing  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("export_dir")
    p.add_argument("--runs", type=int, default=5, help="timed calls of the fit program (each --segment_steps steps)")
    p.add_argument("--pair_steps", type=int, default=500, help="Adam steps of a timed pair (whole segments)")
    p.add_argument("--pair_runs", type=int, default=3)
    p.add_argument("--precisions", default="", help="only these (comma-separated); default all in the manifest")
    p.add_argument("--points", default="", help="only these cloud sizes (comma-separated); default all")
    p.add_argument("--budget_s", type=float, default=None, help="start no entry after this many seconds")
    p.add_argument("--out", default=None, help="JSON file of the results")
    args = p.parse_args()
    points = tool_args.int_list(p, args.points, "--points")
    save = tool_args.json_saver(args.out)

    try:
        result = nsfp_timing.run_export(args.export_dir, args.runs, args.pair_steps, args.pair_runs,
                                         [v for v in args.precisions.split(",") if v], points, args.budget_s,
                                         on_row=save)
    except xla_program.ExportFormatError as e:
        sys.exit(f"export error: {e}")
    if not result["rows"] and not result["skipped"]:
        sys.exit(f"no entry in {args.export_dir} matches --precisions {args.precisions!r} --points {args.points!r}")
    result["table"] = nsfp_timing.nsfp_table(result)
    print(result["table"], flush=True)
    save(result)


if __name__ == "__main__":
    main()
