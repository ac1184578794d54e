"""Where an exported forward's time goes, with JAX alone (no TensorFlow): python lab/tools/profile_xla.py DIR [--out J]

For each of --points (default 32000) in --precision (default bfloat16): the plain artifact of DIR (written by
tools/export_xla.py), with --bake_weights also compiled with its weights as constants, and every variant DIR holds
(tools/export_xla.py --variants): median latency, device time per HLO instruction from a profiler trace, summed by
kind and by the paper table's row, and each program's flow against the plain artifact's
(lab.inference.xla_profile). Prints the tables; --out writes the rows as JSON, rewritten after each size.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too; imports no TensorFlow)
from lab import tool_args  # noqa: E402

from ff3d_tf.xla_export_dir import ExportFormatError  # noqa: E402
from lab.inference import xla_profile  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("export_dir")
    p.add_argument("--points", default="32000", help="cloud sizes (comma-separated)")
    p.add_argument("--precision", default="bfloat16")
    p.add_argument("--variants", default=None, help="only these variants (comma-separated; default all, '' none)")
    p.add_argument("--bake_weights", action="store_true", help="also time the weights compiled in as constants")
    p.add_argument("--runs", type=int, default=90)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--trace_runs", type=int, default=20, help="passes under the profiler")
    p.add_argument("--out", default=None, help="JSON file of the results")
    args = p.parse_args()
    variants = None if args.variants is None else [v for v in args.variants.split(",") if v]
    save = tool_args.json_saver(args.out)
    import jax
    device = jax.devices()[0]
    result = {"jax": jax.__version__, "platform": device.platform,
              "device": getattr(device, "device_kind", str(device)), "export_dir": args.export_dir, "rows": []}
    try:
        for points in tool_args.int_list(p, args.points, "--points"):
            result["rows"] += xla_profile.profile_export(args.export_dir, points, args.precision, args.runs,
                                                         args.warmup, args.trace_runs, variants, args.bake_weights)
            save(result)
    except ExportFormatError as e:
        sys.exit(f"export error: {e}")
    result["table"] = xla_profile.profile_table(result["rows"])
    print(result["table"], flush=True)
    save(result)


if __name__ == "__main__":
    main()
