"""How fast the training input goes and what an accelerator needs from it. JSON into benchmarks/.

python tools/benchmark_training.py --config configs/fastflow3d_waymo.yaml --out benchmarks/training_cpu.json
    [--data_dir D | --segments 2 --frames_per_segment 4 --lidar_scale 1.0] [--cores 1,2] [--train_steps 2]

Four measurements, on synthetic WOD segments at full size (the five lidars' real range-image sizes; made in a temporary
directory unless --data_dir is given):
  input         the training input pipeline alone (`input.training_dataset`: decode, pair, shuffle, batch, pad),
                pairs/s after its first batch, in a child process pinned to 1, 2, ... cores (CPU affinity, TensorFlow
                and tf.data thread pools of that size);
  decode_count  decodes per epoch of `pairs.pair_dataset`, counted by a counter inside the decoder: one per frame,
                although every frame but the first and last of a segment is in two pairs;
  train_step    the trainer's step (`Trainer.step`, forward + backward + Adam) on one batch held in memory,
                repeated: steps/s with no input cost, batch `train.global_batch_size` (set 1 for the paper's point
                counts on a CPU);
  end_to_end    the same step fed by the real pipeline; input_bound_fraction = 1 - (in-memory step time / end-to-end
                step time), the share of an end-to-end step spent waiting for data (0 when the input keeps up);
                input_headroom = input pairs/s (most cores) x in-memory step time / batch: > 1 means the input
                outpaces the step.
On a shared machine the step times move with the load: compare ratios from one run.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import _common

from ff3d_tf import bench, children


def _args(argv=None):
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", default=None, help="WOD segments (default: synthetic ones in a temporary dir)")
    p.add_argument("--segments", type=int, default=2, help="synthetic segments to make")
    p.add_argument("--frames_per_segment", type=int, default=4)
    p.add_argument("--lidar_scale", type=float, default=1.0, help="< 1 shrinks the synthetic range images (tests)")
    p.add_argument("--cores", default="1,2", help="core counts for the input pipeline (comma-separated)")
    p.add_argument("--input_batches", type=int, default=12, help="batches timed per core count")
    p.add_argument("--train_steps", type=int, default=2, help="timed steps (after one warm-up step) per mode")
    p.add_argument("--out", default="benchmarks/training_cpu.json")
    p.add_argument("--input_child", type=int, default=0, help=argparse.SUPPRESS)  # internal: one pinned measurement
    return p.parse_args(argv)


def input_pairs_per_s(files, cfg, cores: int, batches: int) -> dict:
    """Pairs/s of the training input with tf.data's own thread pool of `cores` threads."""
    import tensorflow as tf
    from ff3d_tf.training.input import training_dataset
    options = tf.data.Options()
    options.threading.private_threadpool_size = cores
    options.threading.max_intra_op_parallelism = 1
    ds = training_dataset(files, cfg, cfg.train.global_batch_size).with_options(options)
    it = iter(ds)
    first, first_batch_s = bench.elapsed(lambda: next(it))
    points, elapsed = bench.elapsed(lambda: [float(tf.reduce_mean(tf.cast(next(it)["num_points_t0"], tf.float32)))
                                             for _ in range(batches)])
    del first
    pairs = batches * cfg.train.global_batch_size
    return {"cores": cores, "pairs_per_s": pairs / elapsed, "pairs_timed": pairs, "first_batch_s": first_batch_s,
            "mean_points_t0": sum(points) / len(points)}


def _input_in_child(args, cores: int) -> dict:
    """`input_pairs_per_s` in a fresh process pinned to `cores` CPUs (thread pools cannot shrink once started)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "input.json")
        cmd = [sys.executable, os.path.abspath(__file__), "--input_child", str(cores), "--data_dir", args.data_dir,
               "--input_batches", str(args.input_batches), "--out", out]
        cmd += ["--config", args.config or ""] + [a for s in args.set for a in ("--set", s)]
        env = {**os.environ, "TF_NUM_INTEROP_THREADS": str(cores), "TF_NUM_INTRAOP_THREADS": str(cores)}
        run = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if run.returncode != 0:
            sys.exit(f"input measurement on {cores} cores failed:\n{run.stderr[-3000:]}")
        with open(out) as f:
            return json.load(f)


def count_decodes(files, cfg) -> dict:
    """Frames decoded during one pass over `pair_dataset` (a counter in the decoder) vs frames and pairs."""
    from unittest import mock

    import tensorflow as tf
    from ff3d_tf.data import pairs
    from ff3d_tf.data.wod import waymo, wod_decode
    decodes = tf.Variable(0, dtype=tf.int64, trainable=False)
    make_decoder = wod_decode.traced_decoder  # the one decoder every frame goes through (traced once per process)

    def counting_decoder(options):
        decode = make_decoder(options)

        def counted(record, source):
            with tf.control_dependencies([decodes.assign_add(1)]):
                return decode(record, source)
        return counted

    frames = sum(1 for path in files for _ in waymo.iterate_records(path))
    with mock.patch.object(wod_decode, "traced_decoder", counting_decoder):
        num_pairs = sum(1 for _ in pairs.pair_dataset(files, cfg))
    return {"frames": frames, "pairs": num_pairs, "decodes": int(decodes.numpy()),
            "decodes_if_each_pair_decoded_both_frames": 2 * num_pairs,
            "decode_once_per_frame": int(decodes.numpy()) == frames}


def _time_steps(trainer, iterator, steps: int) -> dict:
    """One warm-up step (tracing, compilation), then `steps` timed steps of `trainer.step` (loss fetched)."""
    _, warmup_s = bench.elapsed(bench.fetched(lambda: trainer.step(iterator)))
    ms = bench.summary([r["ms"] for r in bench.measure(bench.fetched(lambda: trainer.step(iterator)), steps)],
                       ("mean", "min"))
    mean = ms["mean_ms"] / 1e3
    return {"steps": steps, "mean_step_s": mean, "steps_per_s": 1.0 / mean, "min_step_s": ms["min_ms"] / 1e3,
            "warmup_step_s": warmup_s}


def train_step_and_end_to_end(files, cfg, steps: int, model_dir: str) -> dict:
    from ff3d_tf.training.input import training_dataset
    from ff3d_tf.training.trainer import Trainer
    trainer = Trainer(cfg, model_dir, files, log_fn=lambda _: None)
    batch_size = cfg.train.global_batch_size
    real = training_dataset(files, cfg, batch_size)
    # One real batch, cached in memory and repeated: the step with no input work at all (after the warm-up step,
    # which reads it). Same element spec as the real input, so both modes run one traced and compiled step.
    in_memory = real.take(1).cache().repeat()
    distribute = trainer.strategy.experimental_distribute_dataset
    step = _time_steps(trainer, iter(distribute(in_memory)), steps)
    end_to_end = _time_steps(trainer, iter(distribute(real)), steps)
    fraction = max(0.0, 1.0 - step["mean_step_s"] / end_to_end["mean_step_s"])
    end_to_end["input_bound_fraction"] = fraction
    return {"batch_size": batch_size, "replicas": trainer.strategy.num_replicas_in_sync, "train_step": step,
            "end_to_end": end_to_end}


def _synthetic_segments(args, out_dir: str) -> list[str]:
    from ff3d_tf.data.synthetic import wod as synthetic
    paths = []
    for k in range(args.segments):
        path = os.path.join(out_dir, f"segment-bench-{k:03d}.tfrecord")
        synthetic.write_segment(path, synthetic.SegmentSpec(seed=100 + k, num_frames=args.frames_per_segment,
                                                            lidar_scale=args.lidar_scale))
        paths.append(path)
    return paths


def main(argv=None):
    args = _args(argv)
    if args.input_child:
        try:
            pinned = children.pin_cores(args.input_child)
        except ValueError as e:
            sys.exit(f"--cores: {e}")
        cfg = _common.load(args)
        from ff3d_tf.data.pairs import list_segment_files
        result = {**input_pairs_per_s(list_segment_files(args.data_dir), cfg, args.input_child, args.input_batches),
                  "cpus": pinned}
        with open(args.out, "w") as f:
            json.dump(result, f)
        return
    cfg = _common.load(args)
    cores = [int(c) for c in args.cores.split(",") if c]
    with tempfile.TemporaryDirectory() as tmp:
        if args.data_dir is None:
            args.data_dir = os.path.join(tmp, "segments")
            os.makedirs(args.data_dir)
            _, seconds = bench.elapsed(lambda: _synthetic_segments(args, args.data_dir))
            print(f"made {args.segments} synthetic segments in {seconds:.0f} s", flush=True)
        from ff3d_tf.data.pairs import list_segment_files
        files = list_segment_files(args.data_dir)
        result = {"config": args.config, "overrides": args.set, "batch_size": cfg.train.global_batch_size,
                  "cpus_available": len(os.sched_getaffinity(0)), "input": []}
        for c in cores:
            result["input"].append(_input_in_child(args, c))
            r = result["input"][-1]
            print(f"input on {c} core(s): {r['pairs_per_s']:.2f} pairs/s ({r['mean_points_t0']:.0f} points per "
                  f"t0 cloud)", flush=True)
        result["decode_count"] = count_decodes(files, cfg)
        print(f"decode count: {json.dumps(result['decode_count'])}", flush=True)
        result.update(train_step_and_end_to_end(files, cfg, args.train_steps, os.path.join(tmp, "model")))
        # How many times faster the input (on all the cores measured) makes pairs than the step consumes them.
        fastest_input = max(r["pairs_per_s"] for r in result["input"])
        result["input_headroom"] = fastest_input * result["train_step"]["mean_step_s"] / result["batch_size"]
        print(f"train step (in-memory batch): {result['train_step']['mean_step_s']:.2f} s; end to end: "
              f"{result['end_to_end']['mean_step_s']:.2f} s; input-bound fraction "
              f"{result['end_to_end']['input_bound_fraction']:.3f}; input headroom {result['input_headroom']:.1f}x",
              flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
