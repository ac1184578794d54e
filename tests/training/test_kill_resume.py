"""tools/train.py killed with SIGKILL at any moment, then rerun: final weights equal an uninterrupted run's, bitwise.

Each run is a subprocess on the tiny config, checkpointing every step. A kill moment is a condition on the run's
stdout or its checkpoint files, polled every millisecond (no fixed sleeps): a step's log line, the temporary folder
of a checkpoint being written (inside the write), a checkpoint's index appearing (files written, state file not yet).
"""
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import tensorflow as tf

from conftest import ROOT, TINY_OVERRIDES

NUM_STEPS = 5


def _command(data_dir, model_dir, compile_mode):
    sets = TINY_OVERRIDES + (f"train.num_steps={NUM_STEPS}", "train.checkpoint_every_steps=1",
                             "train.log_every_steps=1", "train.eval_every_steps=0", "train.keep_checkpoints=2",
                             f"model.compile={compile_mode}")
    return [sys.executable, "tools/train.py", "--config", "", "--data_dir", data_dir, "--model_dir", str(model_dir),
            *[a for s in sets for a in ("--set", s)]]


class TrainRun:
    """tools/train.py as a subprocess, its stdout collected line by line."""

    def __init__(self, data_dir, model_dir, compile_mode="none"):  # none: no XLA compile time, the fast case
        self.t0 = time.perf_counter()
        self.model_dir = str(model_dir)
        self.proc = subprocess.Popen(_command(data_dir, model_dir, compile_mode), cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True)
        self.lines = []
        self.reader = threading.Thread(target=lambda: self.lines.extend(self.proc.stdout), daemon=True)
        self.reader.start()

    def finish(self, kill_when=None, timeout_s=600) -> float:
        """Waits for the run; with `kill_when(lines, checkpoint_files)`, SIGKILLs it the moment that turns true.

        Returns the seconds since start. A run that ends before its kill moment, or fails, fails the test.
        """
        ckpt_dir = os.path.join(self.model_dir, "checkpoints")
        killed = False
        try:
            while self.proc.poll() is None and time.perf_counter() - self.t0 < timeout_s:
                if kill_when is not None:
                    files = os.listdir(ckpt_dir) if os.path.isdir(ckpt_dir) else []
                    if kill_when(list(self.lines), files):
                        self.proc.send_signal(signal.SIGKILL)
                        killed = True
                        break
                time.sleep(0.001)
        finally:
            if self.proc.poll() is None and not killed:
                self.proc.kill()
            self.proc.wait()
            self.reader.join(10)
        log = "".join(self.lines)[-3000:]
        if kill_when is not None:
            assert killed, f"the run ended before its kill moment:\n{log}"
        else:
            assert self.proc.returncode == 0, log
        return time.perf_counter() - self.t0


def _final_tensors(model_dir):
    prefix = tf.train.latest_checkpoint(os.path.join(model_dir, "checkpoints"))
    assert prefix.endswith(f"ckpt-{NUM_STEPS}"), prefix
    reader = tf.train.load_checkpoint(prefix)
    return {k: reader.get_tensor(k) for k in reader.get_variable_to_shape_map()
            if not k.startswith(("save_counter", "_CHECKPOINTABLE"))}


def after_step_logged(step):
    return lambda lines, files: any(line.startswith(f"step {step}/") for line in list(lines))


def inside_checkpoint_write(step):
    """TF writes a checkpoint into `ckpt-N_temp/` first, then merges it into ckpt-N.index/.data: kill in between."""
    return lambda lines, files: f"ckpt-{step}_temp" in files or f"ckpt-{step}.index" in files


def checkpoint_index_appeared(step):
    return lambda lines, files: f"ckpt-{step}.index" in files


def _assert_same_as_reference(model_dir, reference):
    got = _final_tensors(model_dir)
    assert sorted(got) == sorted(reference)
    for key, value in reference.items():
        np.testing.assert_array_equal(got[key], value, err_msg=key)
    assert int(got["step/.ATTRIBUTES/VARIABLE_VALUE"]) == NUM_STEPS


def test_killed_inside_a_checkpoint_write_resumes_to_the_same_weights(tiny_segment, tmp_path):
    """Killed inside the ckpt-3 write, and the newest complete checkpoint then truncated (a full disk, a bad copy):
    the rerun moves it aside, resumes from the one before and ends with the uninterrupted run's weights."""
    from ff3d_tf.checkpoints import list_checkpoints
    data_dir = os.path.dirname(tiny_segment)
    reference = TrainRun(data_dir, tmp_path / "reference")  # uninterrupted, side by side with the killed one
    model_dir = tmp_path / "m"
    TrainRun(data_dir, model_dir).finish(inside_checkpoint_write(3))
    left = sorted(os.listdir(model_dir / "checkpoints"))
    newest, older = list_checkpoints(str(model_dir / "checkpoints"))[:2]
    data_file = newest + ".data-00000-of-00001"
    with open(data_file, "r+b") as f:
        f.truncate(os.path.getsize(data_file) // 2)
    restart = TrainRun(data_dir, model_dir)
    seconds = restart.finish()
    reference_seconds = reference.finish()
    text = "".join(restart.lines)
    assert f"checkpoint {newest} is unusable: " in text and f"resuming from the older {older}" in text, text[-3000:]
    assert f"resumed from {older} at step {older.rsplit('-', 1)[1]}" in text, text[-3000:]
    aside = model_dir / "checkpoints" / "damaged" / os.path.basename(newest)
    assert os.path.getsize(aside / os.path.basename(data_file)) > 0 and (aside / "REASON.txt").exists()
    print(f"killed inside the ckpt-3 write, left {left}; {os.path.basename(newest)} truncated; recovery run "
          f"{seconds:.1f} s, uninterrupted run {reference_seconds:.1f} s")
    _assert_same_as_reference(model_dir, _final_tensors(tmp_path / "reference"))


@pytest.mark.slow
def test_killed_at_several_moments_resumes_to_the_same_weights(tiny_segment, tmp_path):
    """The default compile mode (XLA stages); three kills in one run (after a step's log line, just after ckpt-2's
    index appeared, inside the ckpt-4 write), then a run to the end."""
    data_dir = os.path.dirname(tiny_segment)
    reference = TrainRun(data_dir, tmp_path / "reference", compile_mode="auto")
    model_dir = tmp_path / "m"
    moments = [("after step 1 logged", after_step_logged(1)), ("ckpt-2 index appeared", checkpoint_index_appeared(2)),
               ("inside the ckpt-4 write", inside_checkpoint_write(4))]
    for name, moment in moments:
        TrainRun(data_dir, model_dir, compile_mode="auto").finish(moment)
        left = sorted(os.listdir(model_dir / "checkpoints")) if (model_dir / "checkpoints").exists() else []
        print(f"killed {name}: left {left}")
    final = TrainRun(data_dir, model_dir, compile_mode="auto")
    seconds = final.finish()
    reference.finish()
    print(f"final run {seconds:.1f} s: {[ln.strip() for ln in final.lines if 'resumed' in ln or 'unusable' in ln]}")
    _assert_same_as_reference(model_dir, _final_tensors(tmp_path / "reference"))
    # Nothing damaged was deleted: whatever was moved aside is still there with its reason.
    damaged = model_dir / "checkpoints" / "damaged"
    for folder in damaged.iterdir() if damaged.exists() else []:
        assert (folder / "REASON.txt").read_text().strip()
