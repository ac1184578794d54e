"""Damaged WOD records and TFRecord files for every test of bad input: one place builds them.

Each `CASES` entry damages one valid serialized `Frame` (from the `tiny_records` fixture) one way and says which field
the reader's error must name. `write_records` / `truncate_file` / `append_partial_record` build mixed and cut files.
Random damage (bit flips, huge shapes, ...) lives in `ff3d_tf.fuzz`; these are the fixed, named cases.
"""
import numpy as np
from waymo_open_dataset import dataset_pb2

from ff3d_tf.data.wod.wod_format import encode_matrix
from ff3d_tf.fuzz.wod import write_records  # noqa: F401 - the same writer as the fuzzer's mixed files

NOT_A_FRAME = b"\x0a\xff\xff\xff\x0fthis is not a frame"  # declares a 4 GB field
GARBAGE = b"not a frame"


def replace_laser_field(record: bytes, laser_name: int, ret: int = 1, **changes) -> bytes:
    """`record` with fields of one laser's RangeImage replaced (e.g. range_image_flow_compressed=b"")."""
    frame = dataset_pb2.Frame.FromString(record)
    for laser in frame.lasers:
        if laser.name == laser_name:
            for k, v in changes.items():
                setattr(getattr(laser, f"ri_return{ret}"), k, v)
    return frame.SerializeToString()


def nan_range_image(record: bytes, laser_name: int = 4) -> bytes:
    """A short-range lidar's (24 x 72 at the tiny scale) range image with one NaN intensity."""
    image = np.full((24, 72, 4), 5.0, np.float32)
    image[3, 4, 1] = np.nan
    return replace_laser_field(record, laser_name, range_image_compressed=encode_matrix(image))


def without_flow_labels(record: bytes, laser_name: int = 2) -> bytes:
    return replace_laser_field(record, laser_name, range_image_flow_compressed=b"")


def corrupt_zlib(record: bytes, laser_name: int = 2) -> bytes:
    return replace_laser_field(record, laser_name, range_image_compressed=b"\x78\x9cgarbage")


def mismatched_shapes(record: bytes, laser_name: int = 1) -> bytes:
    """One more beam inclination than the range image has rows."""
    frame = dataset_pb2.Frame.FromString(record)
    next(c for c in frame.context.laser_calibrations if c.name == laser_name).beam_inclinations.append(0.1)
    return frame.SerializeToString()


def flow_shape_mismatch(record: bytes, laser_name: int = 3) -> bytes:
    """A flow image of another shape than its range image."""
    return replace_laser_field(record, laser_name, range_image_flow_compressed=encode_matrix(np.zeros((2, 3, 4))))


def without_laser(record: bytes, laser_name: int = 3) -> bytes:
    frame = dataset_pb2.Frame.FromString(record)
    keep = [las for las in frame.lasers if las.name != laser_name]
    del frame.lasers[:]
    frame.lasers.extend(keep)
    return frame.SerializeToString()


def without_calibration(record: bytes, laser_name: int = 5) -> bytes:
    frame = dataset_pb2.Frame.FromString(record)
    keep = [c for c in frame.context.laser_calibrations if c.name != laser_name]
    del frame.context.laser_calibrations[:]
    frame.context.laser_calibrations.extend(keep)
    return frame.SerializeToString()


def singular_pose(record: bytes) -> bytes:
    frame = dataset_pb2.Frame.FromString(record)
    frame.pose.transform[:] = [0.0] * 16
    return frame.SerializeToString()


def nan_extrinsic(record: bytes, laser_name: int = 2) -> bytes:
    frame = dataset_pb2.Frame.FromString(record)
    next(c for c in frame.context.laser_calibrations if c.name == laser_name).extrinsic.transform[3] = np.inf
    return frame.SerializeToString()


def truncated_record(record: bytes) -> bytes:
    return record[: len(record) // 2]


# name -> (damage, field the error names)
CASES = {
    "not_a_frame": (lambda r: NOT_A_FRAME, "context"),  # field 1 (context) declares more bytes than remain
    "truncated_record": (truncated_record, "lasers"),
    "corrupt_zlib": (corrupt_zlib, "lasers[FRONT].ri_return1.range_image_compressed"),
    "missing_laser": (without_laser, "lasers[SIDE_LEFT]"),
    "missing_calibration": (without_calibration, "laser_calibrations[REAR]"),
    "shape_vs_calibration": (mismatched_shapes, "lasers[TOP].ri_return1.range_image_compressed"),
    "flow_shape_mismatch": (flow_shape_mismatch, "lasers[SIDE_LEFT].ri_return1.range_image_flow_compressed"),
    "nan_range_image": (nan_range_image, "lasers[SIDE_RIGHT].ri_return1.range_image_compressed"),
    "missing_flow_labels": (without_flow_labels, "lasers[FRONT].ri_return1.range_image_flow_compressed"),
    "singular_pose": (singular_pose, "pose"),
    "nan_extrinsic": (nan_extrinsic, "laser_calibrations[FRONT].extrinsic"),
}


def truncate_file(path: str, drop_bytes: int) -> str:
    """Cuts the last `drop_bytes` bytes off a file (a copy interrupted mid-record)."""
    with open(path, "r+b") as f:
        f.truncate(f.seek(0, 2) - drop_bytes)
    return path


def append_partial_record(path: str, source_file: str, nbytes: int = 1000) -> str:
    """Appends the first `nbytes` bytes of another TFRecord file: a truncated trailing record."""
    with open(source_file, "rb") as src:
        head = src.read(nbytes)
    with open(path, "ab") as f:
        f.write(head)
    return path
