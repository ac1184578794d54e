"""Labelling killed with SIGKILL mid-segment, then rerun: outputs byte-identical, no partial file listed as segment."""
import os
import signal
import subprocess
import sys
import time

import pytest

from conftest import ROOT, TINY_SCALE
from ff3d_tf.data.pairs import list_segment_files

NUM_SEGMENTS, FRAMES = 2, 5


@pytest.fixture(scope="module")
def unlabelled_dir(tmp_path_factory):
    """Two small synthetic segments (boxes in laser_labels), the labelling job's input."""
    from ff3d_tf.data.synthetic import wod as synthetic
    folder = tmp_path_factory.mktemp("segments")
    for seed in range(NUM_SEGMENTS):
        synthetic.write_segment(str(folder / f"segment-{seed}.tfrecord"),
                                synthetic.SegmentSpec(seed=20 + seed, num_frames=FRAMES, lidar_scale=TINY_SCALE))
    return folder


def _start(in_dir, out_dir):
    # Its own process group: a kill reaches every process the Beam runner may have started.
    return subprocess.Popen([sys.executable, "tools/annotate_flow.py", "--input", str(in_dir), "--out_dir",
                             str(out_dir)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)


def _partials(out_dir):
    return sorted(f for f in os.listdir(out_dir) if f.endswith(".partial")) if os.path.isdir(out_dir) else []


def _outputs(out_dir):
    return {f: (out_dir / f).read_bytes() for f in sorted(os.listdir(out_dir)) if f.endswith(".tfrecord")}


@pytest.mark.slow  # three labelling processes (~35 s of CPU); tests/training/test_kill_resume.py keeps a fast case
def test_killed_mid_segment_then_rerun_gives_identical_outputs(unlabelled_dir, tmp_path):
    reference_dir, out_dir = tmp_path / "reference", tmp_path / "out"
    reference = _start(unlabelled_dir, reference_dir)  # uninterrupted, side by side
    t_reference = time.perf_counter()
    job = _start(unlabelled_dir, out_dir)
    t0 = time.perf_counter()
    while job.poll() is None and not _partials(out_dir) and time.perf_counter() - t0 < 300:
        time.sleep(0.001)
    assert job.poll() is None, f"the job ended before writing any segment:\n{job.stdout.read().decode()[-3000:]}"
    os.killpg(job.pid, signal.SIGKILL)  # mid-segment: its output is still a .partial file
    job.wait()
    partial = _partials(out_dir)
    assert partial, "a SIGKILL leaves the unfinished segment's .partial behind"
    # The unfinished file is never listed as a segment (training/eval on out_dir would skip it).
    finished = [f for f in os.listdir(out_dir) if f.endswith(".tfrecord")]
    listed = [os.path.basename(f) for f in list_segment_files(str(out_dir))] if finished else []
    assert listed == sorted(finished) and not any(f.endswith(".partial") for f in listed)
    assert not finished or len(finished) < NUM_SEGMENTS

    t1 = time.perf_counter()
    rerun = subprocess.run([sys.executable, "tools/annotate_flow.py", "--input", str(unlabelled_dir), "--out_dir",
                            str(out_dir)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    recovery_s = time.perf_counter() - t1
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert reference.wait(timeout=600) == 0, reference.stdout.read().decode()[-3000:]
    reference_s = time.perf_counter() - t_reference  # an upper bound: waited for after the rerun
    reference.stdout.close()
    job.stdout.close()
    want, got = _outputs(reference_dir), _outputs(out_dir)
    assert sorted(want) == [f"segment-{s}.tfrecord" for s in range(NUM_SEGMENTS)]
    assert sorted(got) == sorted(want)
    for name in want:
        assert got[name] == want[name], f"{name} differs from the uninterrupted run's"
    assert _partials(out_dir) == []  # the rerun replaced the stale .partial
    print(f"killed with {partial} (finished: {finished}); rerun {recovery_s:.1f} s (uninterrupted run <= "
          f"{reference_s:.1f} s), outputs identical")
