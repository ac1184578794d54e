"""Training input in pairs/s per core: decoding WOD frames on the fly vs decode-once pair records. JSON out.

python lab/tools/benchmark_input.py --out benchmarks/input_cpu.json [--densities wod,synthetic] [--cores 1,2]
python lab/tools/benchmark_input.py --av2 --out benchmarks/input_cpu.json [--cores 1,2]   (merged in as key "av2")
python lab/tools/benchmark_input.py --official --data_dir D --out O   (graph reader vs the official frame_utils)

Each reading runs in a child process pinned to 1, 2, ... cores (`lab.training.bench_input` says what each holds).
Densities of the synthetic WOD segments: `wod` ~177K points per frame over five lidars, first return, as WOD;
`synthetic` the embedded default's full size, about twice that. Disk: bytes per pair of each record kind, and the WOD
training split's size at that rate.

--av2: where Argoverse 2 labels are computed, on synthetic AV2 logs (`--av2_points` per sweep: 100K as the sample
log's two 32-beam lidars; `ff3d_tf.data.synthetic.av2`'s default, 6,000, is a test size): labels made in the input
pipeline (`ff3d_tf.labels.av2.challenge_pair` per pair) vs the records job and the training input reading its records.
The result goes into `--out` as its key "av2"; the file's other keys are kept.
"""
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402


def _args(argv=None):
    from lab.training import bench_input
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--densities", default="wod,synthetic", help=f"of: {', '.join(bench_input.DENSITY_LIDAR_SCALE)}")
    p.add_argument("--cores", default="1,2")
    p.add_argument("--frames_per_segment", type=int, default=6)
    p.add_argument("--segments", type=int, default=2)
    p.add_argument("--batches", type=int, default=8, help="batches of train.global_batch_size timed per reading")
    p.add_argument("--out", default=paths.benchmark_file("input_cpu.json"))
    p.add_argument("--official", action="store_true", help="graph reader vs official frame_utils (needs --data_dir)")
    p.add_argument("--data_dir", default=None)
    p.add_argument("--av2", action="store_true", help="Argoverse 2: labels in the input pipeline vs pair records")
    p.add_argument("--av2_logs", type=int, default=4)
    p.add_argument("--av2_sweeps", type=int, default=5, help="sweeps per synthetic AV2 log")
    p.add_argument("--av2_points", type=int, default=100_000, help="points per synthetic AV2 sweep")
    p.add_argument("--frames", type=int, default=10, help="--official: frames read")
    return p.parse_args(argv)


def main(argv=None):
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.labels import av2 as av2_labels
    from lab.training import bench_input
    args = _args(argv)
    _common.load(args)  # a config error ends the tool here, named
    cores = [int(c) for c in args.cores.split(",") if c]
    progress = lambda line: print(line, flush=True)  # noqa: E731
    if args.av2:
        command = " ".join(["python lab/tools/benchmark_input.py", *(sys.argv[1:] if argv is None else argv)])
        av2 = {"command": command, **bench_input.av2_input_benchmark(
            args.config, args.set, cores, av2_labels.__name__, args.av2_logs, args.av2_sweeps, args.av2_points,
            args.batches, progress)}
        result = {}
        if os.path.exists(args.out):
            with open(args.out) as f:
                result = json.load(f)
        result["av2"] = av2
    elif args.official:
        if not args.data_dir:
            sys.exit("--official needs --data_dir")
        result = bench_input.official_reader_comparison(args.data_dir, args.frames)
    else:
        densities = {d: bench_input.DENSITY_LIDAR_SCALE[d] for d in args.densities.split(",")}
        result = bench_input.input_benchmark(args.config, args.set, densities, cores, args.segments,
                                             args.frames_per_segment, args.batches, progress)
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
