"""Frames per second of bootstrapping scene-flow labels for one segment (all five lidars, both returns). JSON out.

python lab/tools/benchmark_annotation.py --segment S.tfrecord --out benchmarks/annotation_cpu.json
Without --segment a synthetic segment of --frames frames is generated into --work_dir first (about 1 s a frame).

Reports, in one process: the first segment (cold: includes tracing the decoder), the same segment again (warm: what
every later segment of a job costs) and its steady rate after the first frame; then the two stages alone for the
breakdown: decoding (parallel reader) and labelling + re-encoding (one thread, decoded frames in memory).
"""
import argparse
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402, F401  (puts the repository root on sys.path too)

from lab import bench  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf import cpu
    from ff3d_tf.data.synthetic import wod as synthetic
    from ff3d_tf.data.wod import waymo
    from ff3d_tf.labels import pipeline as annotate_segments
    from ff3d_tf.labels.box_flow import boxes_from_wod_labels
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--segment", help="a WOD segment TFRecord with laser_labels")
    p.add_argument("--frames", type=int, default=48, help="frames of the generated segment (without --segment)")
    p.add_argument("--work_dir", default="/tmp/ff3d_annotation_benchmark")
    p.add_argument("--out", default="annotation_benchmark.json")
    args = p.parse_args()
    os.makedirs(args.work_dir, exist_ok=True)
    segment = args.segment
    if segment is None:
        segment = os.path.join(args.work_dir, f"segment-synthetic-bench-{args.frames}.tfrecord")
        if not os.path.exists(segment):
            print(f"generating {args.frames} synthetic frames -> {segment}", flush=True)
            synthetic.write_segment(segment + ".partial", synthetic.SegmentSpec(seed=500, num_frames=args.frames,
                                                                                name="bench"))
            os.replace(segment + ".partial", segment)
    result = {"segment": segment, "cpu_count": os.cpu_count(), "cpu": cpu.describe(),
              "malloc_tuned": annotate_segments.keep_freed_memory()}
    for run in ("cold", "warm"):
        out_path = os.path.join(args.work_dir, f"annotated-{run}.tfrecord")
        if os.path.exists(out_path):
            os.remove(out_path)
        totals = annotate_segments.annotate_segment(segment, out_path)
        frames = totals["frames"]
        result[f"{run}_seconds"] = totals["seconds"]
        result[f"{run}_fps"] = frames / totals["seconds"]
        result[f"{run}_first_frame_seconds"] = totals["first_frame_seconds"]
        result[f"{run}_steady_fps"] = (frames - 1) / (totals["seconds"] - totals["first_frame_seconds"])
        print(f"{run}: {frames} frames in {totals['seconds']:.1f} s = {result[f'{run}_fps']:.2f} frames/s; "
              f"after the first frame {result[f'{run}_steady_fps']:.2f} frames/s", flush=True)
    result["frames"] = frames
    result["points_per_frame"] = totals["points"] / frames
    result["class_counts"] = {k: totals[k] for k in annotate_segments.COUNT_KEYS}

    # Breakdown: each stage alone.
    from waymo_open_dataset import dataset_pb2
    decoded, decode_s = bench.elapsed(lambda: [(record, frame) for _, record, frame in
                                               waymo.decoded_records(segment, annotate_segments.decode_options())])
    result["decode_only_fps"] = len(decoded) / decode_s

    def label_all():
        prev = None
        for record, frame in decoded:
            parsed = dataset_pb2.Frame.FromString(record)
            boxes = boxes_from_wod_labels(parsed.laser_labels)
            annotate_segments.annotate_frame(parsed, frame, prev, boxes=boxes)
            prev = (boxes, frame["pose"], frame["timestamp_micros"])
    result["label_only_seconds_per_frame"] = bench.elapsed(label_all)[1] / len(decoded)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in result.items()}))


if __name__ == "__main__":
    main()
