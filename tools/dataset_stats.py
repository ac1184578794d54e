"""Per-class moving/stationary shares and speed histograms of a scene-flow dataset (paper Figure 2).

python tools/dataset_stats.py --data_dir D [--out_dir O] [--skip_bad_records]
"""
import argparse
import json
import os
import time

import _common  # noqa: F401

from ff3d_tf import viz
from ff3d_tf.data.stats import FlowStats


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.data.wod import waymo
    from ff3d_tf.data.pairs import list_segment_files
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--data_dir", required=True)
    p.add_argument("--out_dir", default=None)
    p.add_argument("--skip_bad_records", action="store_true")
    args = p.parse_args()
    files = list_segment_files(args.data_dir)
    stats, read = FlowStats(), waymo.ReadStats()
    t0 = time.time()
    for i, (path, index, frame) in enumerate(waymo.read_frames(files, skip_bad_records=args.skip_bad_records,
                                                               stats=read)):
        stats.update(frame["flow_mps"], frame["class_id"])
        if (i + 1) % 10 == 0:
            print(f"read {i + 1} frames ({(i + 1) / (time.time() - t0):.1f} frames/s), file {path}", flush=True)
    print(stats.table())
    if read.skipped:
        print(f"skipped {read.skipped} bad records:\n  " + "\n  ".join(read.errors))
    if args.out_dir:
        os.makedirs(args.out_dir, exist_ok=True)
        with open(os.path.join(args.out_dir, "dataset_stats.json"), "w") as f:
            json.dump({**stats.as_dict(), "skipped_records": read.skipped}, f, indent=1)
        png = viz.speed_histogram_png(os.path.join(args.out_dir, "speed_histogram.png"), stats.moving_speeds(),
                                      "speeds of moving points (|flow| >= 0.1 m/s)")
        print(f"wrote {png} and dataset_stats.json")


if __name__ == "__main__":
    main()
