"""ZeroFlow's distillation measured on synthetic WOD data: FastFlow3D trained on NSFP pseudo-labels against the same
model trained on the human labels and against zero flow, scored on held-out human-labelled records.

python lab/tools/benchmark_distillation.py [--out_dir distillation_out] [--json benchmarks/distillation_synthetic.json]
    [--steps 1000] [--train_segments 3 --eval_segments 2 --frames_per_segment 5 --lidar_scale 0.25]
    [--nsfp_max_iterations 400 --nsfp_patience 100 --nsfp_grid_cell_m 0.1 --nsfp_ground_below_z_m 0.3
     --nsfp_crop_m 32] [--config configs/synthetic_cpu.yaml] [--set key=value ...]

Stages (each one of the project's tools as a subprocess, as `tools/demo.py` runs them; its output streams through):
1. synthetic WOD segments, training and held-out (`tools/make_synthetic_data.py`, different seeds);
2. pair records of both (`tools/write_pair_records.py`, with the human labels);
3. NSFP pseudo-labels of the training records (`tools/pseudo_label.py`; the --nsfp_* flags set its config's nsfp
   section: max_iterations, patience, grid_cell_m, crop_xy_half_extent_m, remove_ground_below_z_m, seed);
4. FastFlow3D trained twice on the pseudo-labelled records, same config, seed, steps and input order, once with
   `data.labels=human` and once with `data.labels=pseudo` (ZeroFlow's speed-scaled loss) (`tools/train.py`);
5. both evaluated on the held-out records against their human labels, beside zero flow (`tools/eval.py`);
6. the pseudo-labels scored against the human labels of the training records (same metric, same points as
   training reads: the grid crop), and everything written to --json: EPE on moving / stationary points per class,
   the three-way EPE (foreground dynamic), the eval's full tables, the options, steps and timings.
The job: lab/training/distillation_benchmark.py.

Resumable (`ff3d_tf.stages`, as `tools/demo.py`): a finished stage leaves `OUT/stages/<stage>.json` (its command, a
hash of the project's code and configs, its outputs' files and sizes, and its seconds); a rerun with the same command
on the same code, its outputs untouched, skips it (its recorded seconds stay in the JSON) and reruns every later stage;
an interrupted stage resumes (the tools skip finished outputs, training restarts from its checkpoint). A stage whose
command or code changed (other NSFP options, another step count, a tool's new defaults) starts again from nothing:
its outputs are removed first.
"""
import argparse
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from ff3d_tf.stages import StageError  # noqa: E402
from lab import paths  # noqa: E402
from lab.training import distillation_benchmark  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out_dir", default="distillation_out", help="segments, records, models, metrics")
    p.add_argument("--json", default=paths.benchmark_file("distillation_synthetic.json"))
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for both trainings and the evaluations (repeatable)")
    p.add_argument("--steps", type=int, default=1000, help="training steps of each model")
    p.add_argument("--seed", type=int, default=0, help="train.seed of both models")
    p.add_argument("--train_segments", type=int, default=3)
    p.add_argument("--eval_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=5)
    p.add_argument("--lidar_scale", type=float, default=0.25, help="< 1 shrinks the range images (fewer points)")
    p.add_argument("--nsfp_max_iterations", type=int, default=400, help="NSFP step cap per pair")
    p.add_argument("--nsfp_patience", type=int, default=100, help="NSFP early stopping")
    p.add_argument("--nsfp_grid_cell_m", type=float, default=0.1, help="NSFP distance transform cell")
    p.add_argument("--nsfp_ground_below_z_m", type=float, default=0.3,
                   help="NSFP drops points below this z (vehicle frame); they get pseudo-flow 0 (< 0: keep all)")
    p.add_argument("--nsfp_crop_m", type=float, default=32.0, help="NSFP fits |x|, |y| <= this; the rest gets 0")
    p.add_argument("--nsfp_seed", type=int, default=0)
    p.add_argument("--nsfp_arg", action="append", default=[], metavar="ARG",
                   help="one more argument for tools/pseudo_label.py (repeatable; write "
                        "--nsfp_arg=--set=nsfp.KEY=VALUE)")
    args = p.parse_args()
    options = distillation_benchmark.Options(
        config=args.config, sets=tuple(args.set), steps=args.steps, seed=args.seed,
        train_segments=args.train_segments, eval_segments=args.eval_segments,
        frames_per_segment=args.frames_per_segment, lidar_scale=args.lidar_scale,
        nsfp_max_iterations=args.nsfp_max_iterations, nsfp_patience=args.nsfp_patience,
        nsfp_grid_cell_m=args.nsfp_grid_cell_m, nsfp_ground_below_z_m=args.nsfp_ground_below_z_m,
        nsfp_crop_m=args.nsfp_crop_m, nsfp_seed=args.nsfp_seed, nsfp_args=tuple(args.nsfp_arg))
    try:
        distillation_benchmark.run(options, os.path.abspath(args.out_dir), os.path.abspath(args.json),
                                   " ".join(["lab/tools/benchmark_distillation.py"] + sys.argv[1:]))
    except StageError as e:
        sys.exit(f"benchmark_distillation: {e}")


if __name__ == "__main__":
    _common.run(main)
