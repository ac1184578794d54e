"""Training input served by tf.data service: an in-process dispatcher and two workers; the trainer learns from it.
Faults: a killed service worker (a process) does not stop training and a new one is given work; a killed
fault-tolerant dispatcher restarted on its port and work dir lets training finish."""
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
import tensorflow as tf

from conftest import ROOT

from ff3d_tf.config import replace_config
from ff3d_tf.data import pairs
from ff3d_tf.model.forward import model_inputs
from ff3d_tf.training.data_service import start_dispatcher, start_worker
from ff3d_tf.model.losses import per_sample_flow_loss
from ff3d_tf.training.trainer import Trainer


@pytest.fixture
def service():
    dispatcher = start_dispatcher()
    workers = [start_worker(dispatcher.target) for _ in range(2)]
    yield dispatcher, workers
    for server in workers + [dispatcher]:
        server.stop()


def _fixed_batch_loss(trainer, batch):
    # Batch statistics (training=True): a few steps barely move BatchNorm's moving averages.
    out = trainer.model(model_inputs(batch), training=True)
    valid = out["point_valid"] & batch["point_mask_t0"]
    return float(tf.reduce_mean(per_sample_flow_loss(batch["flow_mps_t0"], out["flow_mps"], batch["class_id_t0"],
                                                     valid)))


def test_training_learns_from_the_service(service, tiny_segment, tiny_config, tmp_path):
    cfg = replace_config(tiny_config, {"train.global_batch_size": 1, "train.log_every_steps": 1,
                                       "train.eval_every_steps": 0, "train.learning_rate": 1e-2})
    trainer = Trainer(cfg, str(tmp_path / "m"), [tiny_segment], strategy=tf.distribute.OneDeviceStrategy("/cpu:0"),
                      log_fn=lambda s: None, data_service_address=service[0].target)
    fixed = next(iter(pairs.batch_examples(pairs.pair_dataset([tiny_segment], cfg), 3, cfg.data.point_bucket_base)))
    before = _fixed_batch_loss(trainer, fixed)
    out = trainer.train(6)
    assert out["step"] == 6
    after = _fixed_batch_loss(trainer, fixed)
    assert after < 0.8 * before, (before, after)
    # The batches came from the service: both workers registered, and the job ran as tasks on them.
    dispatcher, workers = service
    assert dispatcher.server._num_workers() == 2  # noqa: SLF001 - the servers' own counters
    assert sum(w.server._num_tasks() for w in workers) >= 1  # noqa: SLF001


def _serving_port(line: str) -> int:
    """The port of a role's "... serving on port N[; ...]" line."""
    return int(line.split("port ")[1].split(";")[0])


def test_service_roles_as_processes(tmp_path):
    """`tools/data_service.py` starts a dispatcher and a worker that serve a dataset to this process."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    dispatcher = subprocess.Popen([sys.executable, "tools/data_service.py", "--dispatcher"], cwd=ROOT, env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    worker = None
    try:
        line = dispatcher.stdout.readline()
        assert "dispatcher serving on port" in line, line
        port = _serving_port(line)
        worker = subprocess.Popen([sys.executable, "tools/data_service.py", "--worker", "--dispatcher_address",
                                   f"localhost:{port}"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True)
        assert "worker serving on port" in worker.stdout.readline()
        ds = tf.data.Dataset.range(20).map(lambda x: x * x).apply(tf.data.experimental.service.distribute(
            processing_mode="parallel_epochs", service=f"grpc://localhost:{port}"))
        assert sorted(int(v) for v in ds) == [i * i for i in range(20)]
    finally:
        for p in (worker, dispatcher):
            if p is not None:
                p.terminate()
                p.wait(timeout=30)


def _service_process(*args, stderr=subprocess.DEVNULL):
    proc = subprocess.Popen([sys.executable, "tools/data_service.py", *args], cwd=ROOT,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE, stderr=stderr,
                            text=True)
    lines = []
    threading.Thread(target=lambda: lines.extend((time.monotonic(), ln) for ln in proc.stdout), daemon=True).start()
    deadline = time.monotonic() + 300
    while not any("serving on port" in ln for _, ln in lines):
        assert proc.poll() is None and time.monotonic() < deadline, f"{args} did not start: {lines}"
        time.sleep(0.05)
    return proc, lines


def test_a_worker_stopped_while_a_client_waits_on_it_exits_within_its_bound(tmp_path):
    """SIGTERM to a worker that is producing a client's element which never comes (it opens a FIFO no one writes, so
    its open waits for a writer): TensorFlow's stop alone waits without end (a minute, tried); the worker exits with
    status 1 after --stop_timeout_s, its one line said first, no traceback."""
    fifo = str(tmp_path / "never_written")
    os.mkfifo(fifo)
    stop_timeout_s = 2.0
    procs = []
    try:
        dispatcher, dispatcher_lines = _service_process("--dispatcher")
        procs.append(dispatcher)
        address = f"localhost:{_serving_port(next(ln for _, ln in dispatcher_lines if 'serving on port' in ln))}"
        with open(tmp_path / "worker.err", "w") as err:
            worker, _ = _service_process("--worker", "--dispatcher_address", address,
                                         "--stop_timeout_s", str(stop_timeout_s), stderr=err)
        procs.append(worker)
        procs.append(subprocess.Popen(
            [sys.executable, "-c", "import sys, tensorflow as tf; list(tf.data.TextLineDataset(sys.argv[1]).apply("
             "tf.data.experimental.service.distribute('parallel_epochs', 'grpc://' + sys.argv[2])))", fifo, address],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        deadline = time.monotonic() + 120
        while not _waits_in_fifo_open(worker.pid):  # the worker has started on the client's element
            assert worker.poll() is None and time.monotonic() < deadline, "the worker never opened the FIFO"
            time.sleep(0.1)
        t0 = time.monotonic()
        worker.send_signal(signal.SIGTERM)
        worker.wait(timeout=60)
        took_s = time.monotonic() - t0
        messages = (tmp_path / "worker.err").read_text()
        assert worker.returncode == 1, (worker.returncode, messages)
        assert stop_timeout_s <= took_s < stop_timeout_s + 30, took_s
        assert "worker: stopping; if the server still waits on a client's request after 2 s" in messages, messages
        assert "Traceback" not in messages and "Thread 0x" not in messages, messages
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def _waits_in_fifo_open(pid: int) -> bool:
    """Whether a thread of process `pid` waits in open() for a FIFO's writer (the kernel's wait channel)."""
    tasks = f"/proc/{pid}/task"
    return any(_wait_channel(f"{tasks}/{tid}/wchan") == "wait_for_partner" for tid in os.listdir(tasks))


def _wait_channel(path: str) -> str:
    """A thread's wait channel; "" when the thread ended meanwhile."""
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return ""


def _fault_config(tiny_config):
    return replace_config(tiny_config, {"train.global_batch_size": 1, "train.log_every_steps": 1,
                                        "train.eval_every_steps": 0, "train.checkpoint_every_steps": 1000,
                                        "model.compile": "none"})


def _on_step(actions, steps_at):
    """A log_fn that records when each step ended and runs `actions[step]()` once that step is logged."""
    def log(line):
        if line.startswith("step "):
            step = int(line.split()[1].split("/")[0])
            steps_at.append((time.monotonic(), step))
            if step in actions:
                actions.pop(step)()
    return log


@pytest.mark.slow
def test_a_killed_service_worker_does_not_stop_training_and_a_new_one_gets_work(tiny_segment, tiny_config,
                                                                               tmp_path):
    cfg = _fault_config(tiny_config)
    dispatcher = start_dispatcher()
    staying = start_worker(dispatcher.target)
    victim, _ = _service_process("--worker", "--dispatcher_address", f"localhost:{dispatcher.port}")
    joined = []
    try:
        deadline = time.monotonic() + 60
        while dispatcher.server._num_workers() < 2:  # noqa: SLF001 - the dispatcher's own count
            assert time.monotonic() < deadline, "the worker process never registered"
            time.sleep(0.1)
        steps_at = []
        actions = {3: lambda: (victim.send_signal(signal.SIGKILL), victim.wait()),
                   6: lambda: joined.append(start_worker(dispatcher.target))}
        trainer = Trainer(cfg, str(tmp_path / "m"), [tiny_segment], strategy=tf.distribute.OneDeviceStrategy(
            "/cpu:0"), log_fn=_on_step(actions, steps_at), data_service_address=dispatcher.target)
        out = trainer.train(40)
        assert out["step"] == 40 and not actions, (out, actions)
        assert victim.returncode == -signal.SIGKILL
        # The replacement registered and the dispatcher gave it a task of the running job.
        assert joined[0].server._num_tasks() >= 1  # noqa: SLF001
    finally:
        for server in joined + [staying, dispatcher]:
            server.stop()
        if victim.poll() is None:
            victim.kill()


def _port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.mark.slow
def test_a_restarted_fault_tolerant_dispatcher_lets_training_finish(tiny_segment, tiny_config, tmp_path):
    """The dispatcher (a process, --work_dir) is SIGKILLed after step 3 and started again on its port and work dir;
    the trainer needs it again (dynamic sharding: a worker asks it for every next file), so steps after the
    restart show that the job went on."""
    cfg = _fault_config(tiny_config)
    port, work_dir = _port(), str(tmp_path / "dispatcher")
    first, _ = _service_process("--dispatcher", "--port", str(port), "--work_dir", work_dir)
    workers = [start_worker(f"localhost:{port}") for _ in range(2)]
    restarted = {}

    def restart():
        first.send_signal(signal.SIGKILL)
        first.wait()
        restarted["killed_at"] = time.monotonic()
        restarted["proc"] = proc = subprocess.Popen(
            [sys.executable, "tools/data_service.py", "--dispatcher", "--port", str(port), "--work_dir", work_dir],
            cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            text=True)
        restarted["lines"] = lines = []
        threading.Thread(target=lambda: lines.extend((time.monotonic(), ln) for ln in proc.stdout),
                         daemon=True).start()

    try:
        steps_at = []
        trainer = Trainer(cfg, str(tmp_path / "m"), [tiny_segment], strategy=tf.distribute.OneDeviceStrategy(
            "/cpu:0"), log_fn=_on_step({3: restart}, steps_at), data_service_address=f"grpc://localhost:{port}")
        out = trainer.train(40)
        assert out["step"] == 40
        serving = [t for t, ln in restarted["lines"] if "dispatcher serving on port" in ln]
        assert serving, restarted["lines"]
        killed_at = restarted["killed_at"]
        before = [step for t, step in steps_at if killed_at < t <= serving[0]]
        after = [step for t, step in steps_at if t > serving[0]]
        times = [killed_at] + [t for t, _ in steps_at if t > killed_at]
        print(f"dispatcher down {serving[0] - killed_at:.1f} s; {len(before)} steps meanwhile (buffered input), "
              f"{len(after)} after its restart; longest stall {max(b - a for a, b in zip(times, times[1:])):.1f} s")
        assert after and after[-1] == 40  # the job went on with the restarted dispatcher
        assert os.listdir(work_dir)  # its journal
    finally:
        for server in workers:
            server.stop()
        for proc in (first, restarted.get("proc")):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(30)
