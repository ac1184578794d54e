"""Synthetic sequences in the layout of a user's own sweeps (`ff3d_tf.data.files.sequences`): the synthetic default of
`tools/write_pair_records.py --source files`.

Each sequence is a synthetic WOD segment (`ff3d_tf.data.synthetic.wod`, the same street scenes) written out frame by
frame: the points of the selected lidars and returns as the WOD reader decodes them (`waymo.decode_frame`: vehicle
frame at the frame's time, metres; its intensity), one KITTI-style `<NNNNNN>.bin` per frame, the vehicle poses in
`poses.txt`, the frame times in `timestamps.txt` and, unless `with_boxes` is False, the frames' tracked laser labels as
`boxes.csv` (types vehicle, pedestrian, sign, cyclist; WOD's box: centre, length along the heading, width, height,
heading about +z from +x, in the vehicle frame of its frame: the table's conventions exactly). So the records of a
sequence and those of its segment hold the same points, poses and boxes (`tests/labels/test_own_records.py`).
"""
from __future__ import annotations

import os
import shutil

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data.files import sequences
from ff3d_tf.data.synthetic import wod as synthetic_wod
from ff3d_tf.data.wod import waymo


def boxes_of_frame(frame) -> dict:
    """The boxes dict (`ff3d_tf.labels.box_flow` layout) of a WOD `Frame`'s laser labels of types 1..4, in their
    order (the labels pipeline's `boxes_from_wod_labels`, which this data room cannot import)."""
    labels = [lb for lb in frame.laser_labels if lb.type in schema.OBJECT_CLASSES]
    return {"center": np.array([[lb.box.center_x, lb.box.center_y, lb.box.center_z] for lb in labels],
                               np.float64).reshape(-1, 3),
            "size": np.array([[lb.box.length, lb.box.width, lb.box.height] for lb in labels],
                             np.float64).reshape(-1, 3),
            "heading": np.array([lb.box.heading for lb in labels], np.float64),
            "track_id": np.array([lb.id for lb in labels], dtype=str),
            "class_id": np.array([lb.type for lb in labels], np.int32)}


def write_frames_as_sequence(records, directory: str, with_boxes: bool = True, laser_names=schema.ALL_LASERS,
                             returns=(1,)) -> int:
    """Writes serialized WOD `Frame`s (in order) as a sequence directory (module docstring); returns the sweeps
    written. The directory is written as `<directory>.partial` and renamed when complete."""
    from waymo_open_dataset import dataset_pb2
    tmp = directory.rstrip(os.sep) + ".partial"
    if os.path.exists(tmp):
        shutil.rmtree(tmp)
    clouds, poses, stamps, boxes = [], [], [], {}
    for i, record in enumerate(records):
        decoded = waymo.decode_frame(record, laser_names=laser_names, returns=returns, inference_only=True,
                                     source=directory, record_index=i)
        stem = f"{i:06d}"
        clouds.append((stem, decoded["points_xyz"], decoded["intensity"]))
        poses.append(decoded["pose"])
        stamps.append(int(decoded["timestamp_micros"]) * 1000)
        boxes[stem] = boxes_of_frame(dataset_pb2.Frame.FromString(record))
    sequences.write_sequence(tmp, clouds, poses, stamps, boxes if with_boxes else None)
    os.replace(tmp, directory)
    return len(clouds)


def sequence_name(seed: int, realism: str = "ideal") -> str:
    return f"sequence-synthetic-{seed:05d}" if realism == "ideal" else f"sequence-synthetic-{realism}-{seed:05d}"


def write_synthetic_sequences(out_dir: str, num_sequences: int = 2, sweeps_per_sequence: int = 20, seed: int = 0,
                              lidar_scale: float = 1.0, with_boxes: bool = True, progress=None,
                              realism: str = "ideal") -> list[str]:
    """`num_sequences` sequences `<out_dir>/sequence-synthetic-<seed + k>` (sequence k: the synthetic WOD segment of
    seed + k, under the `realism` profile of `synthetic.realism`); a sequence that exists is kept (resumable).
    `progress(k, n, directory, skipped)` after each."""
    out = []
    for k in range(num_sequences):
        directory = os.path.join(out_dir, sequence_name(seed + k, realism))
        skipped = os.path.isdir(directory)
        if not skipped:
            spec = synthetic_wod.SegmentSpec(seed=seed + k, num_frames=sweeps_per_sequence,
                                             name=os.path.basename(directory).removeprefix("sequence-"),
                                             lidar_scale=lidar_scale, realism=realism)
            write_frames_as_sequence(synthetic_wod.generate_segment(spec), directory, with_boxes)
        out.append(directory)
        if progress is not None:
            progress(k, num_sequences, directory, skipped)
    return out
