"""NSFP's exported programs against TensorFlow's own fit and grid build, in one process on this machine's CPU. JSON out.

python lab/tools/benchmark_nsfp_xla_cpu.py DIR --out benchmarks/nsfp_xla_cpu.json [--rounds 2] [--points 64000]
DIR is an export of tools/export_nsfp_xla.py (with the xla extra): the float32 fit (its --segment_steps Adam steps a
call) and grid programs run by JAX on the CPU against `nsfp._fit_segment` and `build_distance_grid` with the export's
options on the same synthetic pair (the first entry's, or --points'), called in turn (`bench.round_robin`), medians of
--rounds after one warm-up call each (`lab.labels.nsfp_timing.compare_on_this_machine`). The JSON also holds the
export's options and versions.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402, F401  (puts the repository root on sys.path too)

from ff3d_tf.json_io import write_json  # noqa: E402
from ff3d_tf.labels import nsfp_program  # noqa: E402
from lab.labels import nsfp_timing  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("export_dir")
    p.add_argument("--out", required=True, help="JSON of JAX-vs-TensorFlow seconds per step on this CPU")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--points", type=int, default=None, help="the entry timed (default: the first)")
    args = p.parse_args()
    manifest = nsfp_program.read_manifest(args.export_dir)
    result = nsfp_timing.compare_on_this_machine(args.export_dir, points=args.points, rounds=args.rounds)
    write_json(args.out, {"options": manifest["options"], "exported_with": manifest["exported_with"], **result})


if __name__ == "__main__":
    main()
