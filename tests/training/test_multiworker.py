"""Multi-worker training on localhost: two `tools/train.py` processes with TF_CONFIG (one CPU replica each).

They must end bit-identical to each other and equal to the two-replica reference of `test_distributed` fed the same
pairs (worker w reads shard w of the pairs); only the chief writes into model_dir; a killed pair of workers resumes
from the chief's checkpoint.
"""
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import tensorflow as tf

from conftest import ROOT, TINY_OVERRIDES
from replica_reference import GLOBAL_BATCH, Reference, replica_config

from ff3d_tf.checkpoints import restore_model
from ff3d_tf.config import load_config
from ff3d_tf.training import cluster
from ff3d_tf.training.input import training_dataset

STEPS = 3


def _sets(cfg_overrides):
    return [a for kv in cfg_overrides for a in ("--set", kv)]


SETS = TINY_OVERRIDES + ("train.global_batch_size=2", "train.log_every_steps=1", "train.eval_every_steps=0",
                         "train.learning_rate=1e-2", "train.checkpoint_every_steps=1")
TRAIN_CONFIG = "configs/fastflow3d_waymo.yaml"  # tools/train.py's config without --config


def worker_config(extra_sets=()):
    """The config a worker of `_start_workers` loads (with `extra_sets` added to SETS, as a test adds them)."""
    return load_config(os.path.join(ROOT, TRAIN_CONFIG), SETS + tuple(extra_sets) + (f"train.num_steps={STEPS}",))


def _start_workers(data_dir, model_dir, steps):
    ports = cluster.free_loopback_ports(GLOBAL_BATCH)
    procs = []
    for index in range(GLOBAL_BATCH):
        tf_config = {"cluster": {"worker": [f"127.0.0.1:{p}" for p in ports]},
                     "task": {"type": "worker", "index": index}}
        env = dict(os.environ, TF_CONFIG=json.dumps(tf_config), PYTHONUNBUFFERED="1")
        procs.append(subprocess.Popen(
            [sys.executable, "tools/train.py", "--data_dir", data_dir, "--model_dir", model_dir]
            + _sets(SETS + (f"train.num_steps={steps}",)), cwd=ROOT, env=env, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True))
    return procs


def _finish(procs, timeout=600):
    outs = []
    for p in procs:
        out, _ = p.communicate(timeout=timeout)
        assert p.returncode == 0, out[-3000:]
        outs.append(out)
    return outs


def _reference(tiny_segment, cfg, weights, steps):
    """The reference fed what each worker reads: element s of its shard's per-replica stream at step s."""
    streams = [iter(training_dataset([tiny_segment], cfg, 1, shard=(GLOBAL_BATCH, w))) for w in range(GLOBAL_BATCH)]
    ref = Reference(cfg, weights)
    for _ in range(steps):
        ref.step_samples([{k: v.numpy() for k, v in next(s).items()} for s in streams])
    return ref


def _fingerprints(outs):
    return [re.search(r"weights sha256 ([0-9a-f]+)", o).group(1) for o in outs]


def _initial_weights(cfg):
    import keras
    from ff3d_tf.model import build_model
    keras.utils.set_random_seed(cfg.train.seed)  # what every worker's Trainer does before building its model
    return build_model(cfg, job="train").get_weights()


def _assert_near_reference(trained, ref, initial):
    """Per variable, the trained weights are within a thousandth of the reference's move from `initial` of the
    reference's. Not element by element: Adam moves a weight by about the learning rate a step whatever its gradient's
    size, so where a gradient is near zero the all-reduce's summation order moves that weight by float noise times a
    step (under the zen3 caps, one weight in a few thousand by over 1e-5); a worker that trained on other data, or an
    update lost, moves them all."""
    assert len(trained.variables) == len(ref.model.variables) == len(initial)
    for a, b, w0 in zip(trained.variables, ref.model.variables, initial):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        assert np.linalg.norm(a - b) <= 1e-3 * np.linalg.norm(b - w0) + 1e-6 * np.sqrt(b.size), a.path


def test_two_workers_equal_each_other_and_the_reference(tiny_segment, tiny_config, tmp_path):
    cfg = replica_config(tiny_config)
    model_dir = str(tmp_path / "m")
    outs = _finish(_start_workers(os.path.dirname(tiny_segment), model_dir, STEPS))
    fingerprints = _fingerprints(outs)
    assert fingerprints[0] == fingerprints[1], "workers ended with different weights"
    assert "[worker]" in outs[1] and "[worker]" not in outs[0]
    # Only the chief wrote into model_dir; the other worker's temporary directory is gone.
    assert sorted(os.listdir(model_dir)) == ["checkpoints", "config.yaml", "execution_plan.json", "train",
                                             "train_history.json"]
    assert tf.train.latest_checkpoint(os.path.join(model_dir, "checkpoints")).endswith(f"ckpt-{STEPS}")
    ref = _reference(tiny_segment, cfg, _initial_weights(cfg), STEPS)
    _assert_near_reference(restore_model(cfg, model_dir), ref, _initial_weights(cfg))


@pytest.mark.slow
def test_killed_workers_resume_from_the_chiefs_checkpoint(tiny_segment, tiny_config, tmp_path):
    cfg = replica_config(tiny_config)
    model_dir = str(tmp_path / "m")
    procs = _start_workers(os.path.dirname(tiny_segment), model_dir, 2 * STEPS)
    ckpt_dir = os.path.join(model_dir, "checkpoints")
    deadline = time.time() + 600
    while not (os.path.isdir(ckpt_dir) and any(f.startswith("ckpt-2.index") for f in os.listdir(ckpt_dir))):
        assert time.time() < deadline and all(p.poll() is None for p in procs), "no checkpoint 2 appeared"
        time.sleep(0.2)
    for p in procs:
        p.send_signal(signal.SIGKILL)
        p.wait()
    outs = _finish(_start_workers(os.path.dirname(tiny_segment), model_dir, 2 * STEPS))
    assert all("resumed from" in o for o in outs)
    fingerprints = _fingerprints(outs)
    assert fingerprints[0] == fingerprints[1]
    ref = _reference(tiny_segment, cfg, _initial_weights(cfg), 2 * STEPS)
    _assert_near_reference(restore_model(cfg, model_dir), ref, _initial_weights(cfg))
