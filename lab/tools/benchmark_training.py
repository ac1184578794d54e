"""How fast the training input goes and what an accelerator needs from it. JSON into benchmarks/.

python lab/tools/benchmark_training.py --config configs/fastflow3d_waymo.yaml --out benchmarks/training_cpu.json
    [--data_dir D | --segments 2 --frames_per_segment 4 --lidar_scale 1.0] [--cores 1,2] [--train_steps 2]

On WOD segments (synthetic ones at full size, the five lidars' real range-image sizes, unless --data_dir is given):
the training input alone in pairs/s, in a child process pinned to 1, 2, ... cores; decodes per epoch (one per frame,
although a frame is in two pairs); the trainer's step on a batch held in memory and fed by the real input, their
input-bound fraction and the input's headroom (`lab.training.bench_steps.training_benchmark`). On a shared machine
the step times move with the load: compare ratios from one run.
"""
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402


def _args(argv=None):
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", default=None, help="WOD segments (default: synthetic ones in a temporary dir)")
    p.add_argument("--segments", type=int, default=2, help="synthetic segments to make")
    p.add_argument("--frames_per_segment", type=int, default=4)
    p.add_argument("--lidar_scale", type=float, default=1.0, help="< 1 shrinks the synthetic range images (tests)")
    p.add_argument("--cores", default="1,2", help="core counts for the input pipeline (comma-separated)")
    p.add_argument("--input_batches", type=int, default=12, help="batches timed per core count")
    p.add_argument("--train_steps", type=int, default=2, help="timed steps (after one warm-up step) per mode")
    p.add_argument("--out", default=paths.benchmark_file("training_cpu.json"))
    return p.parse_args(argv)


def main(argv=None):
    _common.start("train")  # before TensorFlow is imported
    from lab.training import bench_steps
    args = _args(argv)
    _common.load(args)  # a config error ends the tool here, named
    result = bench_steps.training_benchmark(
        args.config, args.set, args.data_dir, args.segments, args.frames_per_segment, args.lidar_scale,
        [int(c) for c in args.cores.split(",") if c], args.input_batches, args.train_steps,
        progress=lambda line: print(line, flush=True))
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
