"""Faults of a multi-worker job: a lost worker ends the others fast with one line, SIGTERM preempts every worker at
the same step, restarts resume to the weights of an uninterrupted run.

The multi-process tests run two `tools/train.py` workers on 127.0.0.1 (TF_CONFIG, one CPU replica each, the tiny
model, no XLA) and are slow (TensorFlow's start-up per process). The fast ones check the pieces: naming the lost
task from TensorFlow's real messages (captured from such runs), telling a peer's loss from other errors, the join
barrier.
"""
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
import tensorflow as tf

from conftest import ROOT, TINY_OVERRIDES

from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.training import cluster
from ff3d_tf.training.cluster import EXIT_PEER_LOST, EXIT_PREEMPTED

NUM_STEPS = 12
PEER_TIMEOUT_S = 30
SETS = TINY_OVERRIDES + ("train.log_every_steps=1", "train.eval_every_steps=0", "train.learning_rate=1e-2",
                         "train.checkpoint_every_steps=2", "model.compile=none", f"train.num_steps={NUM_STEPS}",
                         f"train.peer_timeout_s={PEER_TIMEOUT_S}")
TASKS = [("worker", 0, "127.0.0.1:41001"), ("worker", 1, "127.0.0.1:41002")]


# -- the pieces ---------------------------------------------------------------------------------------------------
def test_lost_task_is_named_from_tensorflows_messages():
    # Captured from two-worker runs: SIGSTOP of worker 1 (the coordination service's heartbeat check), SIGKILL of
    # worker 0 (a refused connection), SIGSTOP of worker 0 (the service's host: only the RPC is named).
    heartbeat = ("Collective ops is aborted by: Error reported from /job:worker/task:1: The following tasks are "
                 "unhealthy (stopped sending heartbeats):\n/job:worker/replica:0/task:1\nThe tasks have crashed.")
    refused = ("Collective ops is aborted by: failed to connect to all addresses; last error: UNKNOWN: "
               "ipv4:127.0.0.1:41001: Failed to connect to remote host: Connection refused")
    leader = "Collective ops is aborted by: Deadline Exceeded\n\nRPC: /tensorflow.CoordinationService/Heartbeat"
    assert cluster.lost_task(heartbeat, "worker 0", TASKS) == "worker 1 (127.0.0.1:41002)"
    assert cluster.lost_task(refused, "worker 1", TASKS) == "worker 0 (127.0.0.1:41001)"
    assert cluster.lost_task(leader, "worker 1", TASKS).startswith(
        "worker 0 (127.0.0.1:41001, the coordination service's host")
    # The message names only this worker itself: it is never the lost one.
    assert cluster.lost_task("Error reported from /job:worker/replica:0/task:0", "worker 0", TASKS).startswith(
        "worker 1 (127.0.0.1:41002")


def test_an_unnamed_lost_task_is_found_by_its_closed_port():
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(1)
    alive = f"127.0.0.1:{listener.getsockname()[1]}"
    dead = f"127.0.0.1:{cluster.free_loopback_ports(1)[0]}"
    try:
        tasks = [("worker", 0, alive), ("worker", 1, alive), ("worker", 2, dead)]
        assert cluster.lost_task("Collective has timed out during execution.", "worker 0", tasks) == \
            f"worker 2 ({dead}, its port refuses connections)"
        # Every port open (a stopped or busy peer): the only other worker is named, with what it may be doing.
        named = cluster.lost_task("timed out", "worker 0", tasks[:2])
        assert named.startswith(f"worker 1 ({alive}) (it did not answer")
    finally:
        listener.close()


def test_peer_errors_are_told_from_other_errors():
    assert cluster.is_peer_error(tf.errors.UnavailableError(None, None, "failed to connect"))
    assert cluster.is_peer_error(tf.errors.DeadlineExceededError(None, None, "Collective has timed out"))
    assert cluster.is_peer_error(tf.errors.InternalError(None, None, "Collective ops is aborted by: x"))
    assert not cluster.is_peer_error(tf.errors.InvalidArgumentError(None, None, "Incompatible shapes"))
    assert not cluster.is_peer_error(tf.errors.ResourceExhaustedError(None, None, "OOM when allocating"))
    assert not cluster.is_peer_error(ValueError("not a TF error"))


def test_the_stop_bitmask_names_the_workers_that_asked():
    tasks = TASKS + [("worker", 2, "127.0.0.1:41003")]
    assert [cluster.stop_request_bit(f"worker {i}", tasks) for i in range(3)] == [1.0, 2.0, 4.0]
    assert cluster.tasks_in_stop_mask(1 + 4, tasks) == "worker 0, worker 2"
    many = [("worker", i, "") for i in range(cluster.MAX_NAMED_STOP_TASKS + 1)]  # more than a float64 bitmask names
    assert cluster.stop_request_bit("worker 52", many) == 1.0 and cluster.tasks_in_stop_mask(1, many) == "a worker"
    # One worker with two replicas (the two logical CPUs of conftest): its request counts once in the job's sum.
    # Reduced by copies, not collective ops: TensorFlow keeps collective instances per process, keyed so that
    # another MirroredStrategy over the same devices later in this process (the trainer tests) would find this
    # float64 instance where it reduces float32.
    strategy = tf.distribute.MirroredStrategy(["/cpu:0", "/cpu:1"],
                                              cross_device_ops=tf.distribute.ReductionToOneDevice())
    run = tf.function(lambda x: strategy.run(lambda s: cluster.replica_stop_requests(s, 2), args=(x,)))
    summed = strategy.experimental_local_results(run(tf.constant(4.0, tf.float64)))
    assert [float(v) for v in summed] == [4.0, 4.0]


def test_short_reason_drops_tensorflows_frame():
    err = tf.errors.UnavailableError(None, None, "Graph execution error:\n\nDetected at node X defined at:\n"
                                     "  File \"a.py\", line 1, in f\n\nCollective ops is aborted by: gone\n"
                                     "\t [[{{node CollectiveReduceV2}}]] [Op:__inference_step]")
    assert cluster.short_reason(err) == "UnavailableError: Collective ops is aborted by: gone"


def test_join_barrier_waits_for_the_others_and_names_the_missing():
    ports = cluster.free_loopback_ports(2)
    tasks = [("worker", i, f"127.0.0.1:{p}") for i, p in enumerate(ports)]
    t0 = time.monotonic()
    assert cluster._join_barrier("worker 0", tasks, timeout_s=0.6) == ["worker 1"]
    assert time.monotonic() - t0 >= 0.6
    # Worker 1 listening (its own barrier's placeholder): the barrier passes.
    other = socket.socket()
    other.bind(("127.0.0.1", ports[1]))
    other.listen(1)
    try:
        assert cluster._join_barrier("worker 0", tasks, timeout_s=30) == []
        # This task's own port taken (an earlier worker still running): a clear error naming it.
        with pytest.raises(RuntimeError, match=f"port {ports[1]} of worker 1 .* is in use"):
            cluster._join_barrier("worker 1", tasks, timeout_s=1)
    finally:
        other.close()


def test_timeouts_must_be_positive(tiny_config):
    for key in ("train.peer_timeout_s", "train.peer_join_timeout_s"):
        with pytest.raises(ConfigError, match=key):
            replace_config(tiny_config, {key: 0})
    assert tiny_config.train.peer_timeout_s <= 120  # the default bound on a lost worker: at most two minutes


# -- processes ----------------------------------------------------------------------------------------------------
class Worker:
    """One `tools/train.py` process; stdout and stderr apart, each line with its time."""

    def __init__(self, cmd, env):
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        self.out, self.err = [], []
        self.ended = None
        self._threads = [threading.Thread(target=self._read, args=(s, d), daemon=True)
                         for s, d in ((self.proc.stdout, self.out), (self.proc.stderr, self.err))]
        for t in self._threads:
            t.start()

    def _read(self, stream, dest):
        for line in stream:
            dest.append((time.monotonic(), line.rstrip("\n")))
        if stream is self.proc.stdout:
            self.proc.wait()
            self.ended = time.monotonic()

    def wait(self, timeout_s):
        try:
            self.proc.wait(timeout=timeout_s)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            for t in self._threads:
                t.join(10)
        return self.proc.returncode

    def text(self):
        return "\n".join(line for _, line in sorted(self.out + self.err))

    def stderr_lines(self):
        # TensorFlow's C++ log lines (E0000 ..., their continuation lines) are not the tool's own output.
        return [ln for _, ln in self.err if ln.startswith(("error:", "preempted", "interrupted", "Traceback"))]

    def logged(self, prefix):
        return any(line.startswith(prefix) or line.startswith("[worker] " + prefix) for _, line in self.out)


def start_job(data_dir, model_dir, sets=SETS):
    ports = cluster.free_loopback_ports(2)
    workers = []
    for index in range(2):
        tf_config = {"cluster": {"worker": [f"127.0.0.1:{p}" for p in ports]},
                     "task": {"type": "worker", "index": index}}
        env = dict(os.environ, TF_CONFIG=json.dumps(tf_config), PYTHONUNBUFFERED="1")
        cmd = [sys.executable, "tools/train.py", "--config", "", "--data_dir", data_dir, "--model_dir",
               str(model_dir)] + [a for kv in sets for a in ("--set", kv)]
        workers.append(Worker(cmd, env))
    return workers


def wait_for(condition, workers, timeout_s=600):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out:\n" + "\n".join(w.text()[-2000:] for w in workers)
        assert all(w.proc.poll() is None for w in workers), "a worker ended early:\n" + "\n".join(
            w.text()[-3000:] for w in workers)
        time.sleep(0.01)


def fingerprint(worker):
    m = re.search(r"weights sha256 ([0-9a-f]+)", worker.text())
    assert m, worker.text()[-3000:]
    return m[1]


@pytest.fixture(scope="module")
def uninterrupted(tiny_segment, tmp_path_factory):
    """The weights' fingerprint of an uninterrupted two-worker run of NUM_STEPS."""
    workers = start_job(os.path.dirname(tiny_segment), tmp_path_factory.mktemp("reference") / "m")
    for w in workers:
        assert w.wait(900) == 0, w.text()[-3000:]
    prints = [fingerprint(w) for w in workers]
    assert prints[0] == prints[1]
    return prints[0]


def _restart_and_finish(data_dir, model_dir):
    workers = start_job(data_dir, model_dir)
    for w in workers:
        assert w.wait(900) == 0, w.text()[-3000:]
    return workers


@pytest.mark.slow
def test_a_killed_worker_ends_the_other_with_one_line_and_the_restart_equals_an_uninterrupted_run(
        tiny_segment, tmp_path, uninterrupted):
    data_dir, model_dir = os.path.dirname(tiny_segment), tmp_path / "m"
    chief, other = start_job(data_dir, model_dir)
    wait_for(lambda: chief.logged("step 5/") and other.logged("step 5/"), [chief, other])
    other.proc.send_signal(signal.SIGKILL)
    t_kill = time.monotonic()
    code = chief.wait(PEER_TIMEOUT_S + 60)  # the bound, and slack for a loaded machine
    other.wait(30)
    assert code == EXIT_PEER_LOST, chief.text()[-3000:]
    print(f"the chief ended {chief.ended - t_kill:.2f} s after worker 1 was killed")
    lines = chief.stderr_lines()
    assert len(lines) == 1 and lines[0].startswith("error: lost worker 1 (127.0.0.1:"), chief.text()[-3000:]
    assert "Restart every worker with the same command" in lines[0]
    assert "Traceback" not in chief.text()
    # No checkpoint of an unfinished step: each one the chief left is a finished step's (and it verifies on resume).
    restarted = _restart_and_finish(data_dir, model_dir)
    assert all("resumed from" in w.text() for w in restarted)
    assert [fingerprint(w) for w in restarted] == [uninterrupted, uninterrupted]


@pytest.mark.slow
def test_a_stopped_chief_ends_the_other_naming_it(tiny_segment, tmp_path):
    """SIGSTOP: the process is there but silent (its port still accepts connections); the coordination service it
    hosts stops answering heartbeats, and the other worker names it."""
    chief, other = start_job(os.path.dirname(tiny_segment), tmp_path / "m")
    wait_for(lambda: chief.logged("step 3/") and other.logged("step 3/"), [chief, other])
    chief.proc.send_signal(signal.SIGSTOP)
    try:
        code = other.wait(PEER_TIMEOUT_S + 60)
    finally:
        chief.proc.send_signal(signal.SIGKILL)
        chief.wait(30)
    assert code == EXIT_PEER_LOST, other.text()[-3000:]
    lines = other.stderr_lines()
    assert len(lines) == 1 and lines[0].startswith("error: lost worker 0 (127.0.0.1:"), other.text()[-3000:]


@pytest.mark.slow
def test_sigterm_to_one_worker_saves_the_same_step_everywhere_and_resumes_exactly(tiny_segment, tmp_path,
                                                                                   uninterrupted):
    data_dir, model_dir = os.path.dirname(tiny_segment), tmp_path / "m"
    chief, other = start_job(data_dir, model_dir)
    wait_for(lambda: chief.logged("step 3/") and other.logged("step 3/"), [chief, other])
    other.proc.send_signal(signal.SIGTERM)
    codes = [w.wait(PEER_TIMEOUT_S + 60) for w in (chief, other)]
    assert codes == [EXIT_PREEMPTED, EXIT_PREEMPTED], chief.text()[-2000:] + other.text()[-2000:]
    steps = [int(re.search(r"preempted at step (\d+) \(signal to worker 1\); every worker saved step \1",
                           w.text())[1]) for w in (chief, other)]
    assert steps[0] == steps[1] and 3 < steps[0] < NUM_STEPS, steps
    prefix = tf.train.latest_checkpoint(str(model_dir / "checkpoints"))
    assert prefix.endswith(f"ckpt-{steps[0]}")
    assert int(tf.train.load_checkpoint(prefix).get_tensor("step/.ATTRIBUTES/VARIABLE_VALUE")) == steps[0]
    assert not (model_dir / "tmp_worker_1").exists()  # the other worker's own copy is removed
    assert all(w.stderr_lines()[-1].startswith("preempted at step") for w in (chief, other))
    restarted = _restart_and_finish(data_dir, model_dir)
    assert all(f"at step {steps[0]}" in w.text() and "resumed from" in w.text() for w in restarted)
    assert [fingerprint(w) for w in restarted] == [uninterrupted, uninterrupted]


@pytest.mark.slow
def test_a_worker_that_never_joins_ends_the_other(tiny_segment, tmp_path):
    ports = cluster.free_loopback_ports(2)
    tf_config = {"cluster": {"worker": [f"127.0.0.1:{p}" for p in ports]}, "task": {"type": "worker", "index": 0}}
    cmd = [sys.executable, "tools/train.py", "--config", "", "--data_dir", os.path.dirname(tiny_segment),
           "--model_dir", str(tmp_path / "m")] + [a for kv in SETS + ("train.peer_join_timeout_s=5",)
                                                   for a in ("--set", kv)]
    alone = Worker(cmd, dict(os.environ, TF_CONFIG=json.dumps(tf_config), PYTHONUNBUFFERED="1"))
    assert alone.wait(300) == EXIT_PEER_LOST, alone.text()[-3000:]
    lines = alone.stderr_lines()
    assert len(lines) == 1 and lines[0].startswith(
        f"error: the job did not start: worker 1 (127.0.0.1:{ports[1]}, its port refuses connections) did not "
        f"join within"), alone.text()[-3000:]


@pytest.mark.slow
def test_one_process_keeps_its_sigterm_behaviour(tiny_segment, tmp_path):
    """Single-process training: SIGTERM saves the finished step and exits 1 saying to run the command again."""
    cmd = [sys.executable, "tools/train.py", "--config", "", "--data_dir", os.path.dirname(tiny_segment),
           "--model_dir", str(tmp_path / "m")] + [a for kv in SETS for a in ("--set", kv)]
    env = {k: v for k, v in os.environ.items() if k != "TF_CONFIG"}
    run = Worker(cmd, dict(env, PYTHONUNBUFFERED="1"))
    wait_for(lambda: run.logged("step 2/"), [run])
    run.proc.send_signal(signal.SIGTERM)
    assert run.wait(120) == 1, run.text()[-3000:]
    step = int(re.search(r"interrupted by signal 15 at step (\d+); checkpoint", run.text())[1])
    assert run.stderr_lines()[-1] == (f"interrupted at step {step} (checkpoint written); run the same command to "
                                      f"resume")
    assert tf.train.latest_checkpoint(str(tmp_path / "m" / "checkpoints")).endswith(f"ckpt-{step}")
