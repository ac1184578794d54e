"""Frames per second of the graph reader vs the official Python frame_utils path on the same records. JSON out.

python tools/benchmark_input.py --data_dir D --out input_benchmark.json [--frames 10]
"""
import argparse
import json
import time

import _common  # noqa: F401
import tensorflow as tf

from ff3d_tf.data import waymo
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
    t = time.perf_counter()
    n_ours = sum(len(waymo.decode_frame(r)["points_xyz"]) for r in records)
    eager_s = time.perf_counter() - t
    # The tf.data path used in training: parallel in-graph decode.
    ds = tf.data.Dataset.from_tensor_slices(records).map(
        lambda r: waymo.decode_frame_tensors(r, tf.constant("bench"), waymo.DecodeOptions())["points_xyz"],
        num_parallel_calls=tf.data.AUTOTUNE)
    next(iter(ds))  # trace and warm up
    t = time.perf_counter()
    n_tfdata = sum(1 for _ in ds)
    tfdata_s = time.perf_counter() - t
    t = time.perf_counter()
    n_ref = 0
    for r in records:
        frame = dataset_pb2.Frame.FromString(r)
        ri, cp, _, top_pose = frame_utils.parse_range_image_and_camera_projection(frame)
        pts, _ = frame_utils.convert_range_image_to_point_cloud(frame, ri, cp, top_pose)
        n_ref += sum(len(x) for x in pts)
    official_s = time.perf_counter() - t
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
