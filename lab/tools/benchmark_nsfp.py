"""NSFP pseudo-labels (ff3d_tf.labels.nsfp) on this machine: seconds per pair, distance transform vs exact nearest
neighbours, and the labels' end-point error on the Argoverse 2 sample pair. JSON out.

python lab/tools/benchmark_nsfp.py --out benchmarks/nsfp_cpu.json [--points 65536] [--dt_steps 10] [--exact_steps 3]
    [--av2_log data/av2_sample_log] [--av2_args '--set nsfp.fit_every=8'] [--skip_av2] [--fresh]

- speed: the benchmark cloud (--points points in the AV2 crop box) as a pair; the distance grids' build time, and
  seconds per Adam step with the distance transform and with exact nearest neighbours (each timed over a capped
  number of steps after a warm-up that compiles). Seconds per pair = grid build + seconds per step x steps, at the
  steps the Argoverse pair took to stop early and at the cap.
- av2_sample: what a user runs on the Argoverse 2 sample log, in child processes: `tools/write_pair_records.py
  --source av2`, then `tools/pseudo_label.py` with its defaults (plus --av2_args), whose own scores against
  Argoverse's labels and counts are kept, beside the bar (three-way EPE <= 0.08 m, bucketed normalized dynamic EPE
  <= 0.6) with `meets_bar`, the wall time and the command lines.
Each section is written to --out as it completes; a rerun keeps the sections already there (--fresh to redo; an
av2_sample section of other --av2_args is redone). What each figure is: `lab.labels.nsfp_bench`.
"""
import argparse
import json
import os
import shlex
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402, F401  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    from lab.labels import nsfp_bench
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=paths.benchmark_file("nsfp_cpu.json"))
    p.add_argument("--points", type=int, default=65536)
    p.add_argument("--dt_steps", type=int, default=10, help="Adam steps timed with the distance transform")
    p.add_argument("--exact_steps", type=int, default=3, help="Adam steps timed with exact nearest neighbours")
    p.add_argument("--av2_log", default=os.path.join(paths.ROOT, "data", "av2_sample_log"))
    p.add_argument("--av2_args", default="", help="extra flags of tools/pseudo_label.py, e.g. '--set nsfp.fit_every=8' "
                   "(its options are the config's nsfp section)")
    p.add_argument("--skip_av2", action="store_true")
    p.add_argument("--fresh", action="store_true", help="redo sections already in --out")
    args = p.parse_args()
    result = nsfp_bench.run(args.out, args.points, args.dt_steps, args.exact_steps, args.av2_log,
                            shlex.split(args.av2_args), args.skip_av2, args.fresh, paths.TOOLS_DIR,
                            log=lambda line: print(line, flush=True))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
