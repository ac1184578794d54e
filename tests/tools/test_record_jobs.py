"""tools/write_pair_records.py as a user runs it on data with a missing sweep: an input that fails the project's checks
fails alone, named in one line of the tool's own (no Beam traceback, the message once), the other inputs are written
and the tool exits 1; a job that runs no model takes data.num_frames without a model.temporal; with
data.skip_bad_records the summary counts the examples left out (WOD segments, as Argoverse 2 logs and your own
sequences do) and those whose history reaches before their sequence's start."""
import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, TINY_OVERRIDES
from ff3d_tf import geometry
from ff3d_tf.data.files import sequences


def _tiny(*more):
    return ["--config", "", *[a for o in TINY_OVERRIDES + more for a in ("--set", o)]]


def _write_pair_records(*args):
    return subprocess.run([sys.executable, "tools/write_pair_records.py", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)


def _sequence(directory, times_s):
    rng = np.random.default_rng(len(times_s))
    clouds = [(f"{k:06d}", rng.uniform([-30, -30, -1], [30, 30, 2], (80, 3)), rng.uniform(0, 1, 80))
              for k in range(len(times_s))]
    poses = [geometry.box_matrices_np((0.8 * k, 0.0, 0.0), 0.0)[0] for k in range(len(times_s))]
    return sequences.write_sequence(str(directory), clouds, poses, [int(round(t * 1e9)) for t in times_s])


def test_a_sequence_with_a_missing_sweep_fails_alone_in_one_line(tmp_path):
    _sequence(tmp_path / "seqs" / "a_whole", (0.0, 0.1, 0.2, 0.3))
    gap = _sequence(tmp_path / "seqs" / "b_gap", (0.0, 0.1, 0.3, 0.4))
    # data.num_frames=3 and no model.temporal: the job runs no model.
    run = _write_pair_records("--source", "files", "--input", str(tmp_path / "seqs"), "--out_dir",
                              str(tmp_path / "records"), "--no_labels", *_tiny("data.num_frames=3"))
    assert run.returncode == 1, run.stderr[-3000:]
    assert "Traceback" not in run.stderr and run.stderr.count("a sweep is missing") == 1, run.stderr[-3000:]
    lines = [line for line in run.stderr.splitlines() if line.startswith("error: ")]
    assert lines == [
        f"error: {gap}: {gap}/000002.bin: timestamp: the sweep at 300000000 ns comes 0.200 s after 000001.bin "
        "(timestamps.txt), more than data.max_frame_gap_s = 0.15 s: a sweep is missing (data.skip_bad_records=true "
        "skips the examples across the gap)",
        "error: write_pair_records: 1 of 2 inputs failed (each named above); the others are written, and a rerun "
        "after the fix resumes"], run.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "records").iterdir()) == [
        "a_whole.pairs.tfrecord", "pair_records.json", "write_pair_records_counts.json"]
    counts = json.loads((tmp_path / "records" / "write_pair_records_counts.json").read_text())
    assert counts["pairs"] == 3 and counts["failed_inputs"] == [lines[0][len("error: "):]]


@pytest.mark.slow  # a WOD segment through the Beam job: ~25 s
def test_wod_records_count_the_examples_skipped_across_a_missing_frame(tiny_records, tmp_path):
    """Frames 0, 2, 3 of the tiny segment (frame 1 missing: 0.2 s between 0 and 2). With data.skip_bad_records the
    example of frame 2 (paired with frame 0 across the gap) is left out and counted; frame 3's is written."""
    import tensorflow as tf
    segment = tmp_path / "segments" / "segment-gap.tfrecord"
    segment.parent.mkdir()
    with tf.io.TFRecordWriter(str(segment)) as writer:
        for k in (0, 2, 3):
            writer.write(tiny_records[k])
    run = _write_pair_records("--source", "wod", "--no_labels", "--input", str(segment.parent), "--out_dir",
                              str(tmp_path / "records"), *_tiny("data.skip_bad_records=true"))
    assert run.returncode == 0, run.stderr[-3000:]
    counts = json.loads((tmp_path / "records" / "write_pair_records_counts.json").read_text())
    assert (counts["pairs"], counts["skipped_pairs"]) == (1, 1), counts
    assert "'skipped_pairs': 1" in run.stdout
