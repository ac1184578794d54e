"""The WOD format's building blocks (`ff3d_tf.data.wod.wod_format`): polar geometry shared by NumPy and the graph, and
the wire walk that names a malformed field."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.data.wod import wod_decode, wod_format


def test_polar_geometry_is_shared_by_numpy_and_the_graph():
    # The reader's graph calls the same wod_format formulas as the writers: same values in both backends.
    extrinsic = np.eye(4)
    extrinsic[:2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    np.testing.assert_allclose(wod_format.column_azimuths(tf.constant(7), tf.constant(extrinsic), wod_decode.TF_OPS),
                               wod_format.column_azimuths(7, extrinsic), atol=1e-12)
    # Column 0 of W looks backwards: (W - 0.5) / W * 2 - 1 -> pi * (1 - 1/W), less the 0.3 rad yaw.
    assert wod_format.column_azimuths(7, extrinsic)[0] == pytest.approx(np.pi * (1 - 1 / 7) - 0.3)
    np.testing.assert_allclose(
        wod_format.uniform_inclinations_ascending(tf.constant(4), tf.constant(-0.2, tf.float64),
                                                  tf.constant(0.2, tf.float64), wod_decode.TF_OPS),
        [-0.15, -0.05, 0.05, 0.15], atol=1e-12)  # bin centres of 4 bins over [-0.2, 0.2]
    rng = np.random.default_rng(0)
    rpy, xyz = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    expected = np.einsum("nij,nj->ni", wod_format.rotation_from_rpy(rpy[:, 0], rpy[:, 1], rpy[:, 2]), xyz)
    np.testing.assert_allclose(wod_format.rotate_rpy(rpy, xyz), expected, atol=1e-12)
    np.testing.assert_allclose(wod_format.rotate_rpy(tf.constant(rpy), tf.constant(xyz), wod_decode.TF_OPS), expected,
                               atol=1e-12)


def test_malformed_field_names_the_broken_field(tiny_records):
    from waymo_open_dataset import dataset_pb2
    frame = dataset_pb2.Frame.FromString(tiny_records[0])
    laser = frame.lasers[2]
    laser.ri_return1.range_image_compressed = b"x" * 40
    frame.ClearField("laser_labels")  # the lasers are then the last fields on the wire
    data = bytearray(frame.SerializeToString())
    assert wod_format.malformed_field(bytes(data), dataset_pb2.Frame.DESCRIPTOR, ("Frame", "Laser")) is None
    # Cut inside the last laser: the walk names it (field 5 declares more bytes than remain).
    field, reason = wod_format.malformed_field(bytes(data[:-100]), dataset_pb2.Frame.DESCRIPTOR, ("Laser",))
    assert field.startswith("lasers") and "remain" in reason
