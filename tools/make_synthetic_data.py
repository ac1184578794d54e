"""Synthetic WOD-format segments (the embedded default): python tools/make_synthetic_data.py --out_dir D

Writes one TFRecord of complete WOD v1 `Frame`s per segment (all five lidars, scene-flow labels). Deterministic by seed;
skips segment files that already exist (resumable).
"""
import argparse
import os
import time

import _common  # noqa: F401

from ff3d_tf.data import synthetic


def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out_dir", required=True)
    p.add_argument("--num_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=20)
    p.add_argument("--seed", type=int, default=0, help="segment k uses seed + k")
    p.add_argument("--lidar_scale", type=float, default=1.0, help="< 1 shrinks the range images (tests)")
    args = p.parse_args()
    os.makedirs(args.out_dir, exist_ok=True)
    t0, frames = time.time(), 0
    for k in range(args.num_segments):
        seed = args.seed + k
        path = os.path.join(args.out_dir, f"segment-synthetic-{seed:05d}.tfrecord")
        if os.path.exists(path):
            print(f"[{k + 1}/{args.num_segments}] exists, skipped: {path}", flush=True)
            continue
        ts = time.time()
        tmp = path + ".partial"
        n = synthetic.write_segment(tmp, synthetic.SegmentSpec(seed=seed, num_frames=args.frames_per_segment,
                                                               name=f"synthetic-{seed:05d}",
                                                               lidar_scale=args.lidar_scale))
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
