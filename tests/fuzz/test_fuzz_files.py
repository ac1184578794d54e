"""Damaged sequences of your own sweeps (point files of every format, poses, timestamps, box tables), read as the
records job reads them, end as a finite read or a `PointFileError` naming the damaged file and field, without
allocating what a lying header claims; and the fuzzer finds a reader that trusts a header."""
import numpy as np

from ff3d_tf.data.files import point_files
from ff3d_tf.fuzz import files


def test_sequence_mutants(tmp_path):
    report = files.fuzz_sequence(str(tmp_path), 2 * len(files.KINDS), seed=3)
    assert not report.defects, report.format("defects")
    table = report.table()
    assert set(table) == set(files.KINDS)
    # every kind but the random bit flips (which may land where any value is valid) damaged what the readers check
    assert all(counts["named_error"] > 0 for kind, counts in table.items() if not kind.startswith("bit_flip")), \
        report.format("kinds never detected")


def test_the_clean_sequence_reads_every_format(tmp_path):
    frames = files.read_sequence_like_the_job(files.write_clean_sequence(str(tmp_path / "clean"), num_points=50))
    assert len(frames) == len(files.SWEEP_NAMES) and all(len(f["points_xyz"]) == 50 for f in frames)
    np.testing.assert_allclose([f["pose"][0, 3] for f in frames], 0.8 * np.arange(len(frames)))


def test_a_reader_that_believes_the_header_is_a_defect(tmp_path, monkeypatch):
    """The reader before its size checks: numpy allocates what an .npy header says before reading (a MemoryError or
    an allocation of gigabytes from a file of kilobytes)."""
    def trusting_read_npy(path):
        return point_files._array_columns(path, np.load(path, allow_pickle=False), "array"), ()
    monkeypatch.setattr(point_files, "_read_npy", trusting_read_npy)
    report = files.fuzz_sequence(str(tmp_path), 10, seed=1, kinds=("npy_shape_lie",))
    assert {r.outcome for r in report.defects} & {"crash", "huge_allocation"}, report.format("no defect found")
