"""Fuzzing kept as tests: damaged WOD records and files, Argoverse 2 logs and YAML configs never crash the readers.

Each mutant ends as a finite decode or as the reader's own error naming file, record and field (configs: the key and
what is allowed). `tools/fuzz_reader.py` runs the same with thousands of mutants.
"""
import os
import zlib

import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.data import fuzz, waymo, wod_format

AV2_LOG = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "data",
                       "av2_sample_log")


def _assert_clean(report: fuzz.Report, kinds):
    assert not report.defects, report.format("defects")
    table = report.table()
    assert set(table) == set(kinds)
    # Every kind damaged something the reader noticed: the mutators are not no-ops.
    assert all(counts["named_error"] > 0 for counts in table.values()), report.format("kinds never detected")


def test_wod_record_mutants(tiny_records):
    # 20 mutants of each of the 13 kinds, decoded with the default options (the tool cycles through all).
    report = fuzz.fuzz_wod_records(tiny_records, 20 * len(fuzz.WOD_KINDS), seed=11,
                                   option_sets=fuzz.ALL_OPTION_SETS[:1])
    _assert_clean(report, fuzz.WOD_KINDS)
    assert report.slowest().seconds < 2.0  # tiny records decode in ~10 ms; the bound catches a loop over a size


def test_wod_file_mutants(tiny_records, tmp_path):
    # Mixed files (one damaged record among good ones) and files cut at random bytes, read whole: the error names
    # the damaged record of this file (a cut file: the record it cuts).
    report = fuzz.fuzz_wod_files(tiny_records, str(tmp_path), 16, seed=3)
    assert not report.defects, report.format("defects")
    assert report.table()["truncate_file/read_frames"]["named_error"] == 8


def test_huge_declared_shapes_are_refused_before_allocating(tiny_records):
    from waymo_open_dataset import dataset_pb2
    frame = dataset_pb2.Frame.FromString(tiny_records[1])
    laser = next(las for las in frame.lasers if las.name == 2)
    before = fuzz.peak_rss_mib()
    # int32 products that overflow to 0 or to the data size, negative pairs whose product is positive, 2^31-1.
    for dims, data in (((65536, 65536, 4), np.zeros(0)), ((2 ** 31 - 1, 2 ** 31 - 1, 4), np.zeros(4)),
                       ((-24, -72, 4), np.ones(24 * 72 * 4)), ((24, 72 * 2 ** 20, 4), np.ones(24 * 72 * 4))):
        laser.ri_return1.range_image_compressed = zlib.compress(fuzz._matrix_bytes(data, dims))
        with pytest.raises(waymo.FrameDecodeError, match="field lasers.FRONT..ri_return1.range_image_compressed: "
                                                         "(declared dims must be in|data size disagrees)"):
            waymo.decode_frame(frame.SerializeToString(), source="huge.tfrecord", record_index=1)
    assert fuzz.peak_rss_mib() - before < 200  # nothing of the declared size (>= 16 GB) was allocated


def test_av2_mutants(tmp_path):
    report = fuzz.fuzz_av2(AV2_LOG, str(tmp_path), 6 * len(fuzz.AV2_KINDS), seed=2)
    _assert_clean(report, fuzz.AV2_KINDS)


def test_config_mutants(tmp_path):
    report = fuzz.fuzz_configs(str(tmp_path), 40 * len(fuzz.CONFIG_KINDS), seed=4)
    assert not report.defects, report.format("defects")
    assert all(counts["named_error"] > 0 for counts in report.table().values())


def test_polar_geometry_is_shared_by_numpy_and_the_graph():
    # The reader's graph calls the same wod_format formulas as the writers: same values in both backends.
    extrinsic = np.eye(4)
    extrinsic[:2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    np.testing.assert_allclose(wod_format.column_azimuths(tf.constant(7), tf.constant(extrinsic), waymo.TF_OPS),
                               wod_format.column_azimuths(7, extrinsic), atol=1e-12)
    # Column 0 of W looks backwards: (W - 0.5) / W * 2 - 1 -> pi * (1 - 1/W), less the 0.3 rad yaw.
    assert wod_format.column_azimuths(7, extrinsic)[0] == pytest.approx(np.pi * (1 - 1 / 7) - 0.3)
    np.testing.assert_allclose(
        wod_format.uniform_inclinations_ascending(tf.constant(4), tf.constant(-0.2, tf.float64),
                                                  tf.constant(0.2, tf.float64), waymo.TF_OPS),
        [-0.15, -0.05, 0.05, 0.15], atol=1e-12)  # bin centres of 4 bins over [-0.2, 0.2]
    rng = np.random.default_rng(0)
    rpy, xyz = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    expected = np.einsum("nij,nj->ni", wod_format.rotation_from_rpy(rpy[:, 0], rpy[:, 1], rpy[:, 2]), xyz)
    np.testing.assert_allclose(wod_format.rotate_rpy(rpy, xyz), expected, atol=1e-12)
    np.testing.assert_allclose(wod_format.rotate_rpy(tf.constant(rpy), tf.constant(xyz), waymo.TF_OPS), expected,
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
