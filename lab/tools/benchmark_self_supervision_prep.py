"""Self-supervision's preparation (tools/prepare_self_supervision.py) on this machine: its time per pair beside the
NSFP pseudo-label job's on the same CPU, and DUFOMap's dynamic flags against flow labels (precision, recall). JSON out.

python lab/tools/benchmark_self_supervision_prep.py [--out benchmarks/self_supervision_prep.json]
    [--sections synthetic,av2_sample,nsfp] [--num_sweeps 20] [--nsfp_steps 40] [--threads 1] [--fresh]

- synthetic: a realistic synthetic Argoverse 2 log of --num_sweeps sweeps through the tools a user runs
  (make_synthetic_data.py, write_pair_records.py, prepare_self_supervision.py); seconds per pair, flags against the
  generator's labels.
- av2_sample: the same on the real Argoverse 2 pair in data/ (two sweeps), flags against Argoverse's labels.
- nsfp: tools/pseudo_label.py with its defaults on the real pair, capped at --nsfp_steps Adam steps; its seconds per
  step times the steps of the uncapped fit (benchmarks/nsfp_cpu.json) is NSFP's seconds per pair here.
Each section is written to --out as it completes; a rerun keeps the sections already there (--fresh starts anew).
Run one section a call to keep each run short. What each figure is: `lab.labels.self_supervision_prep`.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402, F401  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402

SECTIONS = ("synthetic", "av2_sample", "nsfp")


def main():
    _common.start("inference")  # before TensorFlow is imported
    from lab.labels import self_supervision_prep
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=paths.benchmark_file("self_supervision_prep.json"))
    p.add_argument("--sections", default=",".join(SECTIONS), help=f"comma-separated, of {', '.join(SECTIONS)}")
    p.add_argument("--num_sweeps", type=int, default=20, help="sweeps of the synthetic log")
    p.add_argument("--nsfp_steps", type=int, default=40, help="Adam steps of the capped NSFP fit")
    p.add_argument("--threads", type=int, default=1, help="DUFOMap's threads (selfsup.num_threads)")
    p.add_argument("--av2_log", default=os.path.join(paths.ROOT, "data", "av2_sample_log"))
    p.add_argument("--fresh", action="store_true")
    args = p.parse_args()
    sections = [s for s in args.sections.split(",") if s]  # none: the ratios of the sections already there
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        p.error(f"--sections: unknown {unknown}; known: {', '.join(SECTIONS)}")
    self_supervision_prep.run(args.out, sections, paths.TOOLS_DIR, num_sweeps=args.num_sweeps,
                              nsfp_steps=args.nsfp_steps, threads=args.threads, av2_log=args.av2_log,
                              fresh=args.fresh)


if __name__ == "__main__":
    _common.run(main)
