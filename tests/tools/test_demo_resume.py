"""`make demo` interrupted at two different stages (Ctrl-C in training, SIGKILL in the export) resumes and finishes."""
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import tensorflow as tf

from conftest import ROOT, TINY_OVERRIDES, TINY_SCALE

NUM_STEPS = 3


def _command(out_dir):
    sets = TINY_OVERRIDES + (f"train.num_steps={NUM_STEPS}", "train.checkpoint_every_steps=1",
                             "train.eval_every_steps=0", "train.log_every_steps=1")
    return [sys.executable, "tools/demo.py", "--out_dir", str(out_dir), "--config", "", "--train_segments", "1",
            "--val_segments", "1", "--frames_per_segment", "3", "--lidar_scale", str(TINY_SCALE),
            *[a for s in sets for a in ("--set", s)]]


def _demo(out_dir, stop_when=None, stop_signal=signal.SIGKILL, timeout_s=900):
    """Runs the demo in its own process group; sends `stop_signal` to the group when `stop_when(lines)` holds."""
    proc = subprocess.Popen(_command(out_dir), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    t0, stopped = time.perf_counter(), False
    try:
        while proc.poll() is None and time.perf_counter() - t0 < timeout_s:
            if stop_when is not None and stop_when(list(lines)):
                os.killpg(proc.pid, stop_signal)  # as Ctrl-C or a lost machine reaches every stage's process
                stopped = True
                break
            time.sleep(0.005)
    finally:
        if proc.poll() is None and not stopped:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=300)
        reader.join(10)
    text = "".join(lines)
    assert stop_when is None or stopped, f"the demo ended before its stop moment:\n{text[-3000:]}"
    return proc.returncode, text, time.perf_counter() - t0


@pytest.mark.slow
def test_demo_interrupted_in_training_and_in_export_resumes_and_finishes(tmp_path):
    out = tmp_path / "demo"
    ckpt_1 = out / "model" / "checkpoints" / "ckpt-1.index"

    # 1. Ctrl-C (SIGINT to the process group) once training wrote its first checkpoint.
    code, text, _ = _demo(out, lambda lines: ckpt_1.exists(), signal.SIGINT)
    assert code != 0 and "demo: stage train stopped" in text, text[-3000:]
    assert not (out / "stages" / "train.json").exists()

    # 2. Rerun: finished stages skipped, training resumed; SIGKILL once the SavedModel is being written.
    code, text, seconds_2 = _demo(out, lambda lines: (out / "saved_model.partial").exists())
    for k, stage in enumerate(("generate train", "generate val", "dataset statistics"), 1):
        assert f"=== [{k}/7] {stage}: complete" in text, text[-3000:]
    assert "resumed from" in text and f"step {NUM_STEPS}/{NUM_STEPS}" in text, text[-3000:]
    assert "=== [5/7] evaluate done in" in text and not (out / "saved_model").exists()
    assert "s left)" in text  # the time left, estimated from the stages' records

    # 3. Rerun: everything up to the export skipped, the half-written export redone, the demo finishes.
    code, text, seconds_3 = _demo(out)
    assert code == 0, text[-3000:]
    for k, stage in enumerate(("generate train", "generate val", "dataset statistics", "train", "evaluate"), 1):
        assert f"=== [{k}/7] {stage}: complete" in text, text[-3000:]
    assert "demo finished" in text and "=== [6/7] export done" in text and "=== [7/7] predict done" in text
    assert (out / "saved_model" / "saved_model.pb").exists() and not (out / "saved_model.partial").exists()
    assert (out / "predictions" / "frame_0000_bev.png").stat().st_size > 1000
    assert tf.train.latest_checkpoint(str(out / "model" / "checkpoints")).endswith(f"ckpt-{NUM_STEPS}")
    with open(out / "demo_summary.json") as f:
        summary = json.load(f)
    assert len(summary["stage_seconds"]) == 7 and summary["skipped"] == ["generate train", "generate val",
                                                                           "dataset statistics", "train", "evaluate"]
    assert summary["cpu"]["cpu_count"] >= 1 and summary["seconds"] >= summary["stage_seconds"]["export"] > 0
    assert summary["moving_over_zero_flow"] == summary["moving_mean_l2_mps"] / summary["zero_flow_moving_mean_l2_mps"]
    # 4. A fourth run has nothing left to do.
    code, text, seconds_4 = _demo(out)
    assert code == 0 and text.count(": complete (") == 7, text[-3000:]
    print(f"resumed runs: {seconds_2:.0f} s (to the kill), {seconds_3:.0f} s, nothing-to-do run {seconds_4:.0f} s")
