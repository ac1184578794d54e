"""Frames per second of the graph reader vs the official Python frame_utils path on the same records. JSON out.

python tools/benchmark_input.py --data_dir D --out input_benchmark.json [--frames 10]
"""
import argparse
import json

import _common  # noqa: F401
import tensorflow as tf

from ff3d_tf import bench
from ff3d_tf.data import waymo, wod_decode
from ff3d_tf.data.pairs import list_segment_files


def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--data_dir", required=True)
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--out", default="input_benchmark.json")
    args = p.parse_args()
    from waymo_open_dataset import dataset_pb2
    from waymo_open_dataset.utils import frame_utils
    files = list_segment_files(args.data_dir)
    records = [r for _, r in waymo.iterate_records(files[0])][: args.frames]
    waymo.decode_frame(records[0])  # trace once
    n_ours, eager_s = bench.elapsed(lambda: sum(len(waymo.decode_frame(r)["points_xyz"]) for r in records))
    # The tf.data path used in training: parallel in-graph decode.
    ds = tf.data.Dataset.from_tensor_slices(records).map(
        lambda r: wod_decode.decode_frame_tensors(r, tf.constant("bench"), wod_decode.DecodeOptions())["points_xyz"],
        num_parallel_calls=tf.data.AUTOTUNE)
    next(iter(ds))  # trace and warm up
    n_tfdata, tfdata_s = bench.elapsed(lambda: sum(1 for _ in ds))

    def official_points():
        n = 0
        for r in records:
            frame = dataset_pb2.Frame.FromString(r)
            ri, cp, _, top_pose = frame_utils.parse_range_image_and_camera_projection(frame)
            pts, _ = frame_utils.convert_range_image_to_point_cloud(frame, ri, cp, top_pose)
            n += sum(len(x) for x in pts)
        return n
    n_ref, official_s = bench.elapsed(official_points)
    assert n_ref == n_ours and n_tfdata == len(records), (n_ref, n_ours, n_tfdata)
    n = len(records)
    result = {"frames": n, "points_per_frame": n_ours / n, "official_fps": n / official_s,
              "graph_eager_fps": n / eager_s, "graph_tfdata_fps": n / tfdata_s,
              "speedup_eager": official_s / eager_s, "speedup_tfdata": official_s / tfdata_s}
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in result.items()}))


if __name__ == "__main__":
    main()
