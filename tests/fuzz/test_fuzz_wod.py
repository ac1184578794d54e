"""Damaged WOD records and files never crash the reader: each ends as a finite decode or a `FrameDecodeError` naming
file, record and field. `tools/fuzz_reader.py` runs the same with thousands of mutants."""
import zlib

import numpy as np
import pytest

from ff3d_tf.data.wod import waymo
from ff3d_tf.data.wod_errors import FrameDecodeError
from ff3d_tf.fuzz import report as fuzz_report
from ff3d_tf.fuzz import wod, wod_mutants


def test_wod_record_mutants(tiny_records):
    # 20 mutants of each of the 13 kinds, decoded with the default options (the tool cycles through all).
    report = wod.fuzz_records(tiny_records, 20 * len(wod_mutants.KINDS), seed=11, option_sets=wod.ALL_OPTION_SETS[:1])
    assert not report.defects, report.format("defects")
    table = report.table()
    assert set(table) == set(wod_mutants.KINDS)
    # Every kind damaged something the reader noticed: the mutators are not no-ops.
    assert all(counts["named_error"] > 0 for counts in table.values()), report.format("kinds never detected")
    assert report.slowest().seconds < 2.0  # tiny records decode in ~10 ms; the bound catches a loop over a size


def test_wod_file_mutants(tiny_records, tmp_path):
    # Mixed files (one damaged record among good ones) and files cut at random bytes, read whole: the error names
    # the damaged record of this file (a cut file: the record it cuts).
    report = wod.fuzz_files(tiny_records, str(tmp_path), 16, seed=3)
    assert not report.defects, report.format("defects")
    assert report.table()["truncate_file/read_frames"]["named_error"] == 8


def test_an_error_naming_another_record_is_unnamed(tiny_records):
    def fails():
        raise FrameDecodeError("f.tfrecord", 2, "pose", "singular")

    assert wod.classify_decode(fails, "f.tfrecord", 2)[0] == "named_error"
    assert wod.classify_decode(fails, "f.tfrecord", 3)[0] == "unnamed_error"
    assert wod.classify_decode(lambda: 1 / 0, "f.tfrecord", 2)[0] == "crash"


def test_huge_declared_shapes_are_refused_before_allocating(tiny_records):
    from waymo_open_dataset import dataset_pb2
    frame = dataset_pb2.Frame.FromString(tiny_records[1])
    laser = next(las for las in frame.lasers if las.name == 2)
    before = fuzz_report.peak_rss_mib()
    # int32 products that overflow to 0 or to the data size, negative pairs whose product is positive, 2^31-1.
    for dims, data in (((65536, 65536, 4), np.zeros(0)), ((2 ** 31 - 1, 2 ** 31 - 1, 4), np.zeros(4)),
                       ((-24, -72, 4), np.ones(24 * 72 * 4)), ((24, 72 * 2 ** 20, 4), np.ones(24 * 72 * 4))):
        laser.ri_return1.range_image_compressed = zlib.compress(wod_mutants.matrix_bytes(data, dims))
        with pytest.raises(FrameDecodeError, match="field lasers.FRONT..ri_return1.range_image_compressed: "
                                                   "(declared dims must be in|data size disagrees)"):
            waymo.decode_frame(frame.SerializeToString(), source="huge.tfrecord", record_index=1)
    assert fuzz_report.peak_rss_mib() - before < 200  # nothing of the declared size (>= 16 GB) was allocated
