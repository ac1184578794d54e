"""Models of several sweeps against the pair, over several seeds, and a planted defect the benchmark must catch: the
paper's model and DeFlow's GRU head with DeltaFlow's loss on 2 sweeps, the GRU head on `stack` of 3, DeltaFlow's head
and loss on `delta` of 3 and 5 sweeps, and `delta` of 5 reversed (lab/training/planted_defects.py), each trained with
every seed on the same synthetic t0 sweeps and scored on held-out ones beside zero flow, mean ± spread over the seeds.

python lab/tools/benchmark_sweeps.py [--out_dir sweeps_out] [--json benchmarks/sweeps_synthetic.json] [--steps 1000]
    [--seeds 0,1,2] [--formats av2,wod] [--variants paper_pair,delta_5,...] [--train_segments 12 --eval_segments 2
     --frames_per_segment 40 --lidar_scale 0.12 --av2_points_per_sweep 6000] [--realistic]
    [--config configs/synthetic_cpu.yaml] [--set key=value ...]
python lab/tools/benchmark_sweeps.py --summarize_again J: J's summaries made again from the per-seed figures it
    holds, by this code (after a change to what the summary says; no training)
python lab/tools/benchmark_sweeps.py ... --collect: run nothing; gather what an earlier run of the same options (its
    seeds and variants may be fewer) finished under --out_dir into --json
python lab/tools/benchmark_sweeps.py --subset SRC DST full:K|filled:K: the pair records of SRC whose t0 sweep ranks
    at or after (full) or before (filled) K among its log's t0 sweeps, into DST (a stage of the benchmark)

Variants (lab/training/sweeps_benchmark.py VARIANTS): paper_pair, gru_deltaflow_pair, stack_3, delta_3, delta_5,
delta_5_reversed, delta_5_no_ground; without labels nsfp_pair, seflow_pair, teflow_5. Stages per data format:
synthetic data (training, held-out; --realistic: the generator's sensor model); pair records of both for each number
of sweeps, and their full and filled parts; the fields a variant's records need (pseudo-labels, self-supervision's,
ground masks); each variant trained with each seed on the full part (`tools/train.py`); each evaluated on both
held-out parts (`tools/eval.py`). --json gets per variant and part the mean, sample standard deviation, min and max
over the seeds of the paper's moving / stationary error, the three-way EPE and the bucketed dynamic EPE, zero flow's,
whether zero flow, the paper's model and the best variant are apart by more than the seeds' spread, and whether the
planted defect comes out worse than delta of 5 beyond it. Resumable (`ff3d_tf.stages`): a rerun with the same
command skips what is done.
"""
import argparse
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from ff3d_tf.stages import StageError  # noqa: E402
from lab import paths  # noqa: E402
from lab.training import sweeps_benchmark  # noqa: E402


def _words(text: str) -> tuple[str, ...]:
    return tuple(w for w in text.split(",") if w)


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out_dir", default="sweeps_out", help="data, records, models, metrics")
    p.add_argument("--json", default=paths.benchmark_file("sweeps_synthetic.json"))
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every training and evaluation (repeatable)")
    p.add_argument("--steps", type=int, default=1000, help="training steps of each run")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated train.seed values: one run each per variant")
    p.add_argument("--formats", default="av2", help="comma-separated, of: " + ", ".join(sweeps_benchmark.FORMATS))
    p.add_argument("--variants", default=",".join(sweeps_benchmark.VARIANTS),
                   help="comma-separated, of: " + ", ".join(sweeps_benchmark.VARIANTS))
    p.add_argument("--train_segments", type=int, default=12, help="WOD segments / AV2 logs for training")
    p.add_argument("--eval_segments", type=int, default=2, help="held-out WOD segments / AV2 logs")
    p.add_argument("--frames_per_segment", type=int, default=40, help="WOD frames a segment / AV2 sweeps a log")
    p.add_argument("--realistic", action="store_true", help="the synthetic generator's sensor model")
    p.add_argument("--lidar_scale", type=float, default=0.12, help="WOD: < 1 shrinks the range images")
    p.add_argument("--av2_points_per_sweep", type=int, default=6000)
    p.add_argument("--summarize_again", metavar="JSON", help="rewrite this result's summaries; run nothing")
    p.add_argument("--collect", action="store_true", help="run nothing: gather the finished stages' results")
    p.add_argument("--subset", nargs=3, metavar=("SRC", "DST", "PART:RANK"), help="write one part of pair records")
    args = p.parse_args()
    if args.subset:
        source, target, part_rank = args.subset
        part, _, rank = part_rank.partition(":")
        if part not in sweeps_benchmark.PARTS or not rank.isdigit():
            p.error(f"--subset {part_rank!r}: PART:RANK, PART one of {', '.join(sweeps_benchmark.PARTS)}")
        print(f"{target}: {sweeps_benchmark.subset_records(source, target, part, int(rank))}")
        return
    command = " ".join(["lab/tools/benchmark_sweeps.py"] + sys.argv[1:])
    if args.summarize_again:
        with open(args.summarize_again) as f:
            result = sweeps_benchmark.summarize_again(json.load(f), command)
        sweeps_benchmark.write_json(args.summarize_again, result)
        print("\n".join(sweeps_benchmark.table(result)) + f"\nwrote {args.summarize_again}")
        return
    formats, variants = _words(args.formats), _words(args.variants)
    if not formats or any(f not in sweeps_benchmark.FORMATS for f in formats) or len(set(formats)) != len(formats):
        p.error(f"--formats {args.formats!r}: distinct, of {', '.join(sweeps_benchmark.FORMATS)}")
    if not variants or any(v not in sweeps_benchmark.VARIANTS for v in variants):
        p.error(f"--variants {args.variants!r}: of {', '.join(sweeps_benchmark.VARIANTS)}")
    try:
        seeds = tuple(int(s) for s in _words(args.seeds))
    except ValueError:
        p.error(f"--seeds {args.seeds!r}: comma-separated integers")
    if not seeds or len(set(seeds)) != len(seeds):
        p.error(f"--seeds {args.seeds!r}: one or more distinct integers")
    options = sweeps_benchmark.Options(
        config=args.config, sets=tuple(args.set), steps=args.steps, seeds=seeds, formats=formats,
        train_segments=args.train_segments, eval_segments=args.eval_segments,
        frames_per_segment=args.frames_per_segment, lidar_scale=args.lidar_scale,
        av2_points_per_sweep=args.av2_points_per_sweep, variants=variants, realistic=args.realistic)
    try:
        sweeps_benchmark.run(options, os.path.abspath(args.out_dir), os.path.abspath(args.json), command,
                             collect_only=args.collect)
    except (StageError, ValueError) as e:
        sys.exit(f"benchmark_sweeps: {e}")


if __name__ == "__main__":
    _common.run(main)
