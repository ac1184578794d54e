"""Synthetic data in a dataset's exact format (the embedded defaults).

python tools/make_synthetic_data.py --out_dir D                 WOD: one TFRecord of complete WOD v1 `Frame`s per
                                                                segment (all five lidars, scene-flow labels)
python tools/make_synthetic_data.py --format av2 --out_dir D    Argoverse 2: sensor logs D/<split>/<log_id>/ (lidar
                                                                sweeps, cuboids, poses, ground raster, map)
python tools/make_synthetic_data.py --format files --out_dir D  your own sweeps' layout: D/<sequence>/ with .bin
                                   [--no_boxes]                 sweeps, poses.txt, timestamps.txt and boxes.csv
                                                                (tools/write_pair_records.py --source files)
--realistic (any format): the realistic profile (ff3d_tf/data/synthetic/realism.py) instead of the ideal default: a
city world (sloped ground, traffic lights, traffic that accelerates, brakes and turns, vegetation, more poles) seen by
lidars that fire each column at its own time (motion distortion; AV2 offset_ns, WOD pixel poses), with range noise and
dropped returns. Long logs for multi-sweep histories: --sweeps_per_log 40 (AV2), --frames_per_segment 40 (WOD, files).
Deterministic by seed; skips segments and logs that already exist (resumable).
"""
import argparse
import os
import time

import _common



def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.data.synthetic import wod as synthetic
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out_dir", required=True)
    p.add_argument("--num_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=20)
    p.add_argument("--seed", type=int, default=0, help="segment k uses seed + k")
    p.add_argument("--lidar_scale", type=float, default=1.0, help="< 1 shrinks the range images (tests)")
    p.add_argument("--format", choices=("wod", "av2", "files"), default="wod")
    p.add_argument("--no_boxes", action="store_true", help="files: no box table (sweeps and poses only)")
    p.add_argument("--num_logs", type=int, default=2, help="av2: logs to write")
    p.add_argument("--sweeps_per_log", type=int, default=6, help="av2")
    p.add_argument("--points_per_sweep", type=int, default=6000, help="av2")
    p.add_argument("--split", default="train", help="av2: the split folder under --out_dir")
    p.add_argument("--realistic", action="store_true",
                   help="the realistic profile (city world, motion distortion, range noise, dropped returns)")
    args = p.parse_args()
    realism = "realistic" if args.realistic else "ideal"
    if args.format == "av2":
        from ff3d_tf.data.synthetic import av2 as synthetic_av2
        t0 = time.time()

        def progress(k, n, log_dir, skipped):
            print(f"[{k + 1}/{n}] {'exists, kept' if skipped else 'wrote'}: {log_dir} "
                  f"ETA {(time.time() - t0) / (k + 1) * (n - k - 1):.0f}s", flush=True)
        synthetic_av2.write_synthetic_split(args.out_dir, args.num_logs, args.split, args.sweeps_per_log, args.seed,
                                            args.points_per_sweep, progress=progress, realism=realism)
        return
    if args.format == "files":
        from ff3d_tf.data.synthetic import files as synthetic_files
        t0 = time.time()

        def progress_files(k, n, directory, skipped):
            print(f"[{k + 1}/{n}] {'exists, kept' if skipped else 'wrote'}: {directory} "
                  f"ETA {(time.time() - t0) / (k + 1) * (n - k - 1):.0f}s", flush=True)
        synthetic_files.write_synthetic_sequences(args.out_dir, args.num_segments, args.frames_per_segment, args.seed,
                                                  args.lidar_scale, not args.no_boxes, progress_files, realism)
        return
    os.makedirs(args.out_dir, exist_ok=True)
    t0, frames = time.time(), 0
    for k in range(args.num_segments):
        seed = args.seed + k
        name = f"synthetic-{seed:05d}" if realism == "ideal" else f"synthetic-{realism}-{seed:05d}"
        path = os.path.join(args.out_dir, f"segment-{name}.tfrecord")
        if os.path.exists(path):
            print(f"[{k + 1}/{args.num_segments}] exists, skipped: {path}", flush=True)
            continue
        ts = time.time()
        tmp = path + ".partial"
        n = synthetic.write_segment(tmp, synthetic.SegmentSpec(seed=seed, num_frames=args.frames_per_segment,
                                                               name=name, lidar_scale=args.lidar_scale,
                                                               realism=realism))
        os.replace(tmp, path)
        frames += n
        el = time.time() - t0
        eta = el / (k + 1) * (args.num_segments - k - 1)
        print(f"[{k + 1}/{args.num_segments}] {path}: {n} frames, {(time.time() - ts) / n:.2f} s/frame, "
              f"ETA {eta:.0f}s", flush=True)
    if frames:
        print(f"generated {frames} frames at {(time.time() - t0) / frames:.2f} s/frame")


if __name__ == "__main__":
    main()
