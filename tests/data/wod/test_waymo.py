"""Reader vs the official Waymo conversion, the decode_frame interface, and bad input."""
import zlib
from types import SimpleNamespace

import numpy as np
import pytest
from waymo_open_dataset import dataset_pb2
from waymo_open_dataset.utils import frame_utils

import corrupt_records
from ff3d_tf import schema
from ff3d_tf.data import wod_errors
from ff3d_tf.data.wod import waymo, wod_decode, wod_format
from ff3d_tf.data.wod.wod_format import encode_matrix


def _official_points(record: bytes, ri_index=0):
    frame = dataset_pb2.Frame.FromString(record)
    ri, cp, _, top_pose = frame_utils.parse_range_image_and_camera_projection(frame)
    pts, _ = frame_utils.convert_range_image_to_point_cloud(frame, ri, cp, top_pose, ri_index=ri_index,
                                                            keep_polar_features=True)
    return np.concatenate(pts)  # [N, 6] range, intensity, elongation, x, y, z


def test_matches_official_conversion_all_lidars(tiny_records):
    for record in tiny_records[:2]:
        frame = dataset_pb2.Frame.FromString(record)
        # Non-trivial calibration: rotated extrinsics, explicit and uniform inclinations, moving per-pixel poses.
        cals = {c.name: c for c in frame.context.laser_calibrations}
        assert len(cals[1].beam_inclinations) > 0 and len(cals[2].beam_inclinations) == 0
        assert abs(np.reshape(cals[3].extrinsic.transform, (4, 4))[2, 1]) > 0.01
        ref = _official_points(record)
        ours = waymo.decode_frame(record)
        assert ours["points_xyz"].shape == (len(ref), 3)
        assert np.max(np.abs(ours["points_xyz"] - ref[:, 3:6])) <= 1e-4
        np.testing.assert_allclose(ours["intensity"], ref[:, 1], atol=1e-6)
        np.testing.assert_allclose(ours["elongation"], ref[:, 2], atol=1e-6)
        counts = [int(np.sum(ours["laser_name"] == n)) for n in (1, 2, 3, 4, 5)]
        assert all(c > 0 for c in counts)
        assert np.all(np.diff(ours["laser_name"]) >= 0)  # ascending laser name


def test_top_pixel_pose_is_applied(tiny_records):
    frame = dataset_pb2.Frame.FromString(tiny_records[1])
    pose = np.frombuffer(zlib.decompress(frame.lasers[0].ri_return1.range_image_pose_compressed), np.uint8)
    assert pose.size > 0
    ours = waymo.decode_frame(tiny_records[1], laser_names=(1,))
    ref = _official_points(tiny_records[1])[: len(ours["points_xyz"])]
    # Moving ego: without the per-pixel correction points at the ends of the spin would be off by ~ego speed * 0.05 s.
    assert np.max(np.abs(ours["points_xyz"] - ref[:, 3:6])) <= 1e-4


def test_decode_frame_interface(tiny_records):
    out = waymo.decode_frame(tiny_records[1])
    expected = {"points_xyz": (np.float32, 2), "intensity": (np.float32, 1), "elongation": (np.float32, 1),
                "flow_mps": (np.float32, 2), "class_id": (np.int32, 1), "laser_name": (np.int32, 1),
                "pose": (np.float64, 2)}
    assert set(out) == set(schema.FRAME_KEYS) == set(expected) | {"timestamp_micros"}
    for key, (dtype, rank) in expected.items():
        assert out[key].dtype == dtype and out[key].ndim == rank, key
    assert out["pose"].shape == (4, 4)
    assert isinstance(out["timestamp_micros"], int)
    assert set(np.unique(out["class_id"])) <= {-1, 0, 1, 2, 3, 4}
    n = len(out["points_xyz"])
    assert all(len(out[k]) == n for k in ("intensity", "elongation", "flow_mps", "class_id", "laser_name"))


def test_decoder_steps_alone(tiny_records):
    import tensorflow as tf
    frame = dataset_pb2.Frame.FromString(tiny_records[1])
    source = tf.constant("steps.tfrecord record 0")
    parsed = wod_decode.parse_frame(tf.constant(tiny_records[1]), source)
    assert sorted(parsed.laser_names.numpy()) == [1, 2, 3, 4, 5]
    assert int(parsed.timestamp_micros) == frame.timestamp_micros
    pose, vehicle_from_world = wod_decode.frame_pose(parsed, source)
    np.testing.assert_array_equal(pose, np.reshape(frame.pose.transform, (4, 4)))
    np.testing.assert_allclose(vehicle_from_world @ pose, np.eye(4), atol=1e-9)  # closed-form rigid inverse
    cal = wod_decode.laser_calibration(parsed, 2, source)
    front = next(c for c in frame.context.laser_calibrations if c.name == 2)
    np.testing.assert_array_equal(cal.extrinsic, np.reshape(front.extrinsic.transform, (4, 4)))
    # To points by hand: a 1 x 4 image, identity extrinsic, inclination 0. Column c of W = 4 looks at azimuth
    # ((4 - c - 0.5) / 4 * 2 - 1) * pi; column 2 -> -pi/4, so range 2 m lands at (sqrt 2, -sqrt 2, 0).
    image = np.zeros((1, 4, 4), np.float32)
    image[0, 2] = [2.0, 0.5, 0.1, 0.0]
    identity = wod_decode.LaserCalibration(tf.eye(4, dtype=tf.float64), tf.constant(1), tf.zeros([1], tf.float64),
                                      tf.constant(0.0, tf.float64), tf.constant(0.0, tf.float64))
    pixel_rc, values, xyz = wod_decode.range_image_to_points(tf.constant(image), identity, tf.zeros([1], tf.float64))
    assert pixel_rc.numpy().tolist() == [[0, 2]] and values.numpy()[0, 1] == 0.5
    np.testing.assert_allclose(xyz, [[np.sqrt(2), -np.sqrt(2), 0.0]], atol=1e-12)


def test_second_return_by_config(tiny_records):
    both = waymo.decode_frame(tiny_records[0], returns=(1, 2))
    first = waymo.decode_frame(tiny_records[0], returns=(1,))
    # The synthetic scene has no second returns: same points either way, and return 2 decodes cleanly.
    assert len(both["points_xyz"]) == len(first["points_xyz"])


def test_missing_flow_labels_message(tiny_records):
    record = corrupt_records.without_flow_labels(tiny_records[1], 2)
    with pytest.raises(wod_errors.MissingFlowLabelsError) as err:
        waymo.decode_frame(record, source="seg.tfrecord", record_index=3)
    msg = str(err.value)
    assert "seg.tfrecord" in msg and "record 3" in msg and "range_image_flow_compressed" in msg
    assert "annotate_flow" in msg and "scene-flow release" in msg
    out = waymo.decode_frame(record, inference_only=True)
    assert np.all(out["class_id"] == -1)


@pytest.mark.parametrize("case", sorted(corrupt_records.CASES))
def test_bad_input_names_file_record_field(tiny_records, case):
    damage, field = corrupt_records.CASES[case]
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        waymo.decode_frame(damage(tiny_records[1]), source="bad.tfrecord", record_index=7)
    msg = str(err.value)
    assert "bad.tfrecord: record 7: field " + field in msg, msg
    assert err.value.field == field and err.value.record_index == 7


def test_error_tags_are_the_projects_own(tiny_records):
    # The decoder's checks carry field and source in a tag this module writes and reads back; nothing depends on
    # TensorFlow's wording around it.
    text = "anything TF writes [<<FRAME_DECODE_ERROR|pose|error|not rigid|dir/a b.tfrecord record 12" \
           "|END_FRAME_DECODE_ERROR>>] more TF text"
    tagged = wod_errors.parse_tagged_error(text)
    assert tagged == wod_errors.TaggedError("pose", "error", "not rigid", "dir/a b.tfrecord record 12")
    assert wod_errors.parse_tagged_error("InvalidArgumentError: something else") is None
    # A codec failure has no tag: the field comes from re-reading the record in Python.
    assert waymo.diagnose_record(corrupt_records.corrupt_zlib(tiny_records[1], 2))[0] == \
        "lasers[FRONT].ri_return1.range_image_compressed"
    assert waymo.codec_fault(tiny_records[1]) is None


def test_truncated_tfrecord_and_skip_option(tiny_segment, tiny_records, tmp_path):
    # A file: good record, a record that is not a Frame, good record, then a truncated tail.
    path = corrupt_records.write_records(str(tmp_path / "mixed.tfrecord"),
                                         [tiny_records[0], corrupt_records.GARBAGE, tiny_records[1]])
    corrupt_records.append_partial_record(path, tiny_segment, 1000)  # truncated record
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        list(waymo.read_frames(path))
    assert "mixed.tfrecord" in str(err.value) and "record 1" in str(err.value)
    stats = waymo.ReadStats()
    frames = list(waymo.read_frames(path, skip_bad_records=True, stats=stats))
    assert [idx for _, idx, _ in frames] == [0, 2]
    assert stats.skipped == 2 and stats.decoded == 2
    assert any("record 3" in e and "tfrecord" in e for e in stats.errors)


def test_encode_matrix_is_byte_identical_to_protobuf():
    # The hand-written wire format must equal what the protobuf serializer writes (packed data, unpacked dims).
    from waymo_open_dataset import dataset_pb2
    cases = [(np.random.default_rng(0).normal(size=(3, 5, 4)).astype(np.float32), dataset_pb2.MatrixFloat),
             (np.zeros((0, 4, 4), np.float32), dataset_pb2.MatrixFloat),
             (np.array([[1, -2], [0, 300]], np.int32), dataset_pb2.MatrixInt32)]
    for array, message in cases:
        expected = message(data=array.ravel().tolist(), shape=dataset_pb2.MatrixShape(dims=array.shape))
        assert zlib.decompress(encode_matrix(array)) == expected.SerializeToString()


def _camera_only_frame(empty_lasers: bool) -> bytes:
    """A WOD v1 Frame as a camera-only release holds it: context, pose, camera calibrations and images, no lidar (or,
    with `empty_lasers`, `lasers` entries that hold only their name)."""
    frame = dataset_pb2.Frame(timestamp_micros=1_550_000_000_000_000)
    frame.context.name = "camera_only"
    frame.pose.transform[:] = np.eye(4).reshape(16).tolist()
    for name in (dataset_pb2.CameraName.FRONT, dataset_pb2.CameraName.FRONT_LEFT):
        frame.context.camera_calibrations.add(name=name, width=1920, height=1280)
        frame.images.add(name=name, image=b"\xff\xd8\xff\xe0 not really a jpeg")
    for name in schema.ALL_LASERS if empty_lasers else ():
        frame.lasers.add(name=name)
    return frame.SerializeToString()


@pytest.mark.parametrize("empty_lasers,what", [(False, "no `lasers`"),
                                               (True, "5 `lasers` entries, none with a range image")])
def test_frame_without_lidar_data_says_so(empty_lasers, what, tmp_path):
    import tensorflow as tf
    record = _camera_only_frame(empty_lasers)
    with pytest.raises(wod_errors.NoLidarDataError) as err:
        waymo.decode_frame(record, source="cam.tfrecord", record_index=4)
    msg = str(err.value)
    assert f"cam.tfrecord: record 4: field lasers: the frame has no lidar data ({what})" in msg, msg
    assert "camera images (2)" in msg and "camera-only WOD release" in msg, msg  # where it seems to come from
    assert "perception release" in msg and "scene-flow release" in msg and "corrupt" not in msg, msg  # what to get
    assert waymo.diagnose_record(record) == ("lasers", err.value.reason)  # the same reason without the decoder's tag
    # From the tf.data pipeline the record is read again for the same reason.
    path = str(tmp_path / "cam.tfrecord")
    with tf.io.TFRecordWriter(path) as writer:
        writer.write(record)
    with pytest.raises(tf.errors.OpError) as op_err:
        list(waymo.frames_dataset(path))
    piped = waymo.pipeline_error(op_err.value, [path])
    assert isinstance(piped, wod_errors.NoLidarDataError) and (piped.path, piped.record_index) == (path, 0)
    assert piped.reason.startswith(err.value.reason)


def test_frame_without_laser_calibrations_names_the_field(tiny_records):
    frame = dataset_pb2.Frame.FromString(tiny_records[1])
    del frame.context.laser_calibrations[:]  # decode_proto refuses an empty list: the decoder's check comes first
    with pytest.raises(wod_errors.FrameDecodeError) as err:
        waymo.decode_frame(frame.SerializeToString(), laser_names=(2,))
    assert err.value.field == "laser_calibrations[FRONT]", str(err.value)


def test_repeated_fields_are_told_apart_with_either_descriptor_api():
    fields = dataset_pb2.Frame.DESCRIPTOR.fields_by_name
    assert wod_format.is_repeated(fields["lasers"]) and not wod_format.is_repeated(fields["pose"])
    # Stand-ins with only `is_repeated` (protobuf 7) or only `label` (older protobuf: LABEL_REPEATED = 3).
    packed_float = b"\x0a\x04" + np.float32(1.5).tobytes()  # field 1, wire type 2: legal for a repeated float only
    for repeated, api in [(True, {"is_repeated": True}), (True, {"label": 3}), (False, {"is_repeated": False}),
                          (False, {"label": 1})]:
        field = SimpleNamespace(name="data", number=1, type=2, message_type=None, **api)  # type 2: float
        assert wod_format.is_repeated(field) == repeated
        message = SimpleNamespace(name="M", fields_by_number={1: field})
        expected = None if repeated else ("data", "wire type 2 where M.data needs 5")
        assert wod_format.malformed_field(packed_float, message, ()) == expected, api
