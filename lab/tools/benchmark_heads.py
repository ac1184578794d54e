"""The per-point heads and losses side by side on synthetic data: FastFlow3D's paper head + L2 against DeFlow's GRU
head with the L2, DeFlow and DeltaFlow losses and with augmentation, all trained on the same records, seed and steps,
scored on held-out records beside zero flow.

python lab/tools/benchmark_heads.py [--out_dir heads_out] [--json benchmarks/heads_synthetic.json] [--steps 300]
    [--formats wod,av2] [--train_segments 3 --eval_segments 2 --frames_per_segment 5 --lidar_scale 0.25
     --av2_points_per_sweep 6000] [--config configs/synthetic_cpu.yaml] [--set key=value ...]

Variants (lab/training/heads_benchmark.py VARIANTS): paper_l2, gru_l2, gru_deflow, gru_deltaflow, gru2_deltaflow
(model.gru_iterations=2), gru_deflow_augment (data.augment_height_offset_prob and data.augment_flip_prob 0.5).

Stages, per data format (WOD first, then Argoverse 2), each one of the project's tools as a subprocess:
1. synthetic data, training and held-out (`tools/make_synthetic_data.py`, different seeds);
2. pair records of both (`tools/write_pair_records.py --source wod|av2`: labels, instance ids, AV2 categories);
3. each variant trained on the training records (`tools/train.py`, same config, seed and steps);
4. each evaluated on the held-out records (`tools/eval.py`; `--protocol av2` for AV2), beside zero flow;
then --json gets, per format and variant: the paper's table (moving / stationary per class, m/s), the three-way EPE
(m) and the bucketed normalized dynamic EPE, each beside zero flow, with the commands, the CPU and the timings.

Resumable (`ff3d_tf.stages`, as `lab/tools/benchmark_distillation.py`): a rerun with the same command on the same code
skips finished stages; adding `av2` to --formats after a WOD-only run runs only the AV2 stages.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from ff3d_tf.stages import StageError  # noqa: E402
from lab import paths  # noqa: E402
from lab.training import heads_benchmark  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out_dir", default="heads_out", help="data, records, models, metrics")
    p.add_argument("--json", default=paths.benchmark_file("heads_synthetic.json"))
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for every training and evaluation (repeatable)")
    p.add_argument("--steps", type=int, default=300, help="training steps of each variant")
    p.add_argument("--seed", type=int, default=0, help="train.seed of every variant")
    p.add_argument("--formats", default="wod,av2", help="comma-separated, of: " + ", ".join(heads_benchmark.FORMATS))
    p.add_argument("--train_segments", type=int, default=3, help="WOD segments / AV2 logs for training")
    p.add_argument("--eval_segments", type=int, default=2, help="held-out WOD segments / AV2 logs")
    p.add_argument("--frames_per_segment", type=int, default=5, help="WOD frames a segment / AV2 sweeps a log")
    p.add_argument("--lidar_scale", type=float, default=0.25, help="WOD: < 1 shrinks the range images")
    p.add_argument("--av2_points_per_sweep", type=int, default=6000)
    args = p.parse_args()
    formats = tuple(f for f in args.formats.split(",") if f)
    if not formats or any(f not in heads_benchmark.FORMATS for f in formats) or len(set(formats)) != len(formats):
        p.error(f"--formats {args.formats!r}: distinct, of {', '.join(heads_benchmark.FORMATS)}")
    options = heads_benchmark.Options(
        config=args.config, sets=tuple(args.set), steps=args.steps, seed=args.seed, formats=formats,
        train_segments=args.train_segments, eval_segments=args.eval_segments,
        frames_per_segment=args.frames_per_segment, lidar_scale=args.lidar_scale,
        av2_points_per_sweep=args.av2_points_per_sweep)
    try:
        heads_benchmark.run(options, os.path.abspath(args.out_dir), os.path.abspath(args.json),
                            " ".join(["lab/tools/benchmark_heads.py"] + sys.argv[1:]))
    except StageError as e:
        sys.exit(f"benchmark_heads: {e}")


if __name__ == "__main__":
    _common.run(main)
