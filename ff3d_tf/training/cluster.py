"""The cluster side of a multi-worker job: its strategy, its peers' health, and how it ends when one is lost.

`make_strategy` (MultiWorkerMirroredStrategy when TF_CONFIG is set, behind a join barrier bounded by
`train.peer_join_timeout_s`; MirroredStrategy or one device otherwise); `cluster_tasks` (this task and every task of
the job); `is_peer_error` (a TF error that is a lost peer, not a bug); `lost_task` and `lost_peer_error` (naming the
lost task in one line that says how to resume); the job-wide stop request (`stop_request_bit`,
`replica_stop_requests`, `tasks_in_stop_mask`: a bitmask of the workers that asked to stop); `Watchdog` (the step
bound that exits the process); the exit statuses of `tools/train.py`. The loop that uses them is `trainer.py`.

Faults of a multi-worker job (see README, "Faults and preemption"):
- a lost worker (killed, stopped, unreachable) ends every other worker within `train.peer_timeout_s` with
  `PeerLostError` (one line naming the lost task; `tools/train.py` exits with `EXIT_PEER_LOST`), never with a
  checkpoint of the failed step: the collectives' own timeout, TensorFlow's coordination-service heartbeat and a
  step watchdog bound the wait;
- SIGTERM/SIGINT to any one worker stops all of them after the same step (the trainer all-reduces a "stop" flag
  with the gradients); each saves it and `tools/train.py` exits with `EXIT_PREEMPTED`. Restarting the same commands
  resumes from the chief's newest intact checkpoint.
"""
from __future__ import annotations

import functools
import os
import re
import socket
import sys
import threading
import time

import tensorflow as tf

from ff3d_tf.checkpoints import list_checkpoints


# Exit statuses of tools/train.py (sysexits.h names): a lost peer and a preemption are told apart from a failure (1).
EXIT_PEER_LOST = 69  # EX_UNAVAILABLE: a worker of the job was lost; restart every worker with the same command
EXIT_PREEMPTED = 75  # EX_TEMPFAIL: preempted (SIGTERM/SIGINT); every worker saved the same step; restart me


class PeerLostError(RuntimeError):
    """A multi-worker job lost a worker (or one never joined): this worker stopped without saving a step in flight.

    `lost` names the task ("worker 1 (127.0.0.1:2223)") or says that it is unknown; the message is one line that
    ends by saying how to resume."""

    def __init__(self, message: str, lost: str):
        super().__init__(message)
        self.lost = lost


def _resume_hint(checkpoint_dir: str | None) -> str:
    newest = list_checkpoints(checkpoint_dir) if checkpoint_dir else []
    where = f" (newest now: {newest[0]})" if newest else ""
    return (f"Restart every worker with the same command: training resumes from the chief's newest intact "
            f"checkpoint{where}")


def lost_peer_error(lost: str, step: int, reason: str, waited_s: float, checkpoint_dir: str | None) -> PeerLostError:
    """The error of a worker that lost a peer after `step` (the last step every worker finished)."""
    return PeerLostError(f"lost {lost} after step {step} (noticed after {waited_s:.1f} s: {reason}); this worker "
                         f"stopped without saving the unfinished step. {_resume_hint(checkpoint_dir)}", lost)


def make_strategy(peer_timeout_s: float | None = None, join_timeout_s: float | None = None) -> tf.distribute.Strategy:
    """MultiWorkerMirroredStrategy when TF_CONFIG is set (each collective times out after `peer_timeout_s`; the
    wait for every worker to join ends after `join_timeout_s` with `PeerLostError`), else MirroredStrategy over the
    GPUs (or the logical CPUs), else one device."""
    if os.environ.get("TF_CONFIG"):
        options = tf.distribute.experimental.CommunicationOptions(timeout_seconds=peer_timeout_s)
        resolver = tf.distribute.cluster_resolver.TFConfigClusterResolver()
        cluster = _cluster_of(resolver)
        if cluster is None:
            return tf.distribute.MultiWorkerMirroredStrategy(resolver, communication_options=options)
        me, tasks = cluster

        def not_joined(waited_s, err=None):
            missing = lost_task(getattr(err, "message", "") or "", me, tasks)
            why = f" ({short_reason(err)})" if err is not None else ""
            return PeerLostError(f"the job did not start: {missing} did not join within {waited_s:.0f} s{why} "
                                 f"(train.peer_join_timeout_s). Start every worker with the same command; "
                                 f"training resumes from the chief's newest intact checkpoint", missing)

        t0 = time.monotonic()
        if join_timeout_s:
            missing = _join_barrier(me, tasks, join_timeout_s)
            if missing:
                raise not_joined(time.monotonic() - t0) from None
        try:
            return tf.distribute.MultiWorkerMirroredStrategy(resolver, communication_options=options)
        except tf.errors.OpError as e:
            if not is_peer_error(e):
                raise
            raise not_joined(time.monotonic() - t0, e) from None
    gpus = tf.config.list_logical_devices("GPU")
    if gpus:
        return mirrored_strategy(tuple(d.name for d in gpus))
    cpus = tf.config.list_logical_devices("CPU")
    if len(cpus) > 1:
        return mirrored_strategy(tuple(d.name for d in cpus))
    return tf.distribute.OneDeviceStrategy("/cpu:0")


@functools.cache
def mirrored_strategy(devices: tuple[str, ...]) -> tf.distribute.MirroredStrategy:
    """One MirroredStrategy per process and devices: each new one numbers its collectives from the same start, and
    TensorFlow matched a second trainer's collectives with the first's of the same number, so a second model of
    another size in the process failed its first step ("Shape mismatch in the collective instance")."""
    return tf.distribute.MirroredStrategy(list(devices))


def cluster_tasks(strategy: tf.distribute.Strategy) -> tuple[str, list[tuple[str, int, str]]] | None:
    """(this task's name, [(job, index, address) of every task]) of a job of several workers; None otherwise."""
    if not isinstance(strategy, tf.distribute.MultiWorkerMirroredStrategy):
        return None
    return _cluster_of(strategy.cluster_resolver)


def _cluster_of(resolver) -> tuple[str, list[tuple[str, int, str]]] | None:
    spec = resolver.cluster_spec().as_dict()
    tasks = [(job, i, addr) for job in sorted(spec) for i, addr in
             (enumerate(spec[job]) if isinstance(spec[job], list) else sorted(spec[job].items()))]
    if len(tasks) < 2:
        return None
    return f"{resolver.task_type} {resolver.task_id}", tasks


_TASK_RE = re.compile(r"/job:(\w+)/replica:\d+/task:(\d+)")
_ADDRESS_RE = re.compile(r"(?:ipv4:|//|\s|^)((?:\d{1,3}\.){3}\d{1,3}:\d+|localhost:\d+|\[[0-9a-f:]+\]:\d+)")
# The TF errors a lost peer shows up as: a refused or reset connection, a collective or heartbeat timeout, the
# coordination service's error (after a peer missed its heartbeats), or collectives aborted because of either.
_PEER_ERROR_TYPES = (tf.errors.UnavailableError, tf.errors.DeadlineExceededError, tf.errors.CancelledError,
                     tf.errors.AbortedError)
_PEER_ERROR_WORDS = re.compile(r"heartbeat|unhealthy|Collective ops is aborted|CoordinationService|coordination "
                               r"service|incarnation|Failed to connect|Connection refused|Connection reset|Socket "
                               r"closed|RecvBuf|CompleteInstance|CompleteGroup|timed out", re.IGNORECASE)


def free_loopback_ports(n: int) -> list[int]:
    """`n` distinct ports of 127.0.0.1 that were free a moment ago: a local job's TF_CONFIG (tests, the soak tool)."""
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def is_peer_error(err: BaseException) -> bool:
    """Whether a TF error of a multi-worker job is the loss of a peer (not a bug or a bad input of this worker)."""
    if not isinstance(err, tf.errors.OpError):
        return False
    return isinstance(err, _PEER_ERROR_TYPES) or bool(_PEER_ERROR_WORDS.search(err.message or ""))


def _reachable(address: str, timeout_s: float = 1.0) -> bool:
    host, port = address.rsplit(":", 1)
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


def lost_task(message: str, me: str, tasks: list[tuple[str, int, str]]) -> str:
    """The task a lost-peer error is about, as "worker 1 (127.0.0.1:2223)": the first other task the message names
    (by /job:x/task:i or by address), else the first whose port refuses a connection (a dead process); a task that
    is stopped or hung still accepts connections, so then it is "an unnamed peer"."""
    by_name = {f"{job} {i}": addr for job, i, addr in tasks}
    named = [f"{m[0]} {int(m[1])}" for m in _TASK_RE.findall(message)]
    by_address = {addr.replace("localhost", "127.0.0.1"): f"{job} {i}" for job, i, addr in tasks}
    named += [by_address[a.replace("localhost", "127.0.0.1")] for a in _ADDRESS_RE.findall(message)
              if a.replace("localhost", "127.0.0.1") in by_address]
    for task in named:
        if task != me and task in by_name:
            return f"{task} ({by_name[task]})"
    leader = "chief 0" if "chief 0" in by_name else "worker 0"  # where TF's coordination service runs
    if "CoordinationService" in message and leader != me:
        return f"{leader} ({by_name[leader]}, the coordination service's host: it stopped answering heartbeats)"
    for task, addr in by_name.items():
        if task != me and not _reachable(addr):
            return f"{task} ({addr}, its port refuses connections)"
    others = [f"{t} ({a})" for t, a in by_name.items() if t != me]
    silent = "stopped, hung, or busy for longer than train.peer_timeout_s, e.g. in the chief's evaluation"
    if len(others) == 1:
        return f"{others[0]} (it did not answer: {silent})"
    return f"a peer that did not answer ({silent}); every peer's port still accepts connections: {', '.join(others)}"


def short_reason(err: BaseException) -> str:
    """The error's type and its first line that is not TensorFlow's frame (\"Graph execution error\", \"Detected at
    node\", the Python frames, the node name), at most 200 characters."""
    text = getattr(err, "message", None) or str(err)
    lines = [ln.strip() for ln in text.splitlines()]
    frame = ("Graph execution error", "Detected at node", "File \"", "[[")
    first = next((ln for ln in lines if ln and not ln.startswith(frame)), "")
    first = first.split(" [[", 1)[0]
    return f"{type(err).__name__}: {first[:200]}"


# -- the job-wide stop request: every worker learns of a preemption at the same step -------------------------------
MAX_NAMED_STOP_TASKS = 52  # one bit per task (bits 0..51): their float64 sum stays an exact integer


def stop_request_bit(me: str, tasks: list[tuple[str, int, str]]) -> float:
    """The stop request of task `me` ("worker 1") in the job-wide sum: 2 ** its number among `tasks` (1 when the job
    has more tasks than a float64 bitmask can name)."""
    if len(tasks) > MAX_NAMED_STOP_TASKS:
        return 1.0
    return float(2 ** [f"{job} {i}" for job, i, _ in tasks].index(me))


def replica_stop_requests(stop_requested, local_replicas: int):
    """In replica context: the sum over the job of each worker's `stop_requested` (float64: 0 or its
    `stop_request_bit`), counted once per worker (by its first of `local_replicas` replicas): the bitmask of the
    workers that asked to stop. ReduceOp has no MAX."""
    ctx = tf.distribute.get_replica_context()
    first_local = tf.equal(tf.math.floormod(ctx.replica_id_in_sync_group, local_replicas), 0)
    return ctx.all_reduce(tf.distribute.ReduceOp.SUM,
                          tf.where(first_local, stop_requested, tf.zeros_like(stop_requested)))


def tasks_in_stop_mask(mask: int, tasks: list[tuple[str, int, str]]) -> str:
    """The tasks whose bits `mask` holds ("worker 0, worker 2"), or "a worker" when the bitmask cannot say."""
    if len(tasks) > MAX_NAMED_STOP_TASKS:
        return "a worker"
    return ", ".join(f"{job} {i}" for k, (job, i, _) in enumerate(tasks) if mask >> k & 1) or "a worker"


def _join_barrier(me: str, tasks: list[tuple[str, int, str]], timeout_s: float) -> list[str]:
    """Waits until every other task's port accepts a connection; returns the tasks still missing after `timeout_s`
    ([] once all are there).

    TensorFlow's own join (the coordination service's registration, inside the strategy's constructor) holds the
    GIL and waits up to an hour for a worker that never comes. So each worker first listens on its own TF_CONFIG
    port with a plain socket (never accepting: a connection completes in the backlog) and probes the others'; a
    peer counts as there when its placeholder or its TensorFlow server answers. The placeholder is closed before
    TensorFlow binds the port. A worker that dies in the seconds between this barrier and TensorFlow's registration
    still leaves the others in TensorFlow's wait."""
    addresses = {f"{job} {i}": addr for job, i, addr in tasks}
    port = int(addresses[me].rsplit(":", 1)[1])
    placeholder = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    placeholder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        placeholder.bind(("", port))
    except OSError as e:
        placeholder.close()
        raise RuntimeError(f"port {port} of {me} ({addresses[me]}, from TF_CONFIG) is in use ({e.strerror}): an "
                           f"earlier worker of this job may still be running; stop it, or give this task a free "
                           f"port") from None
    try:
        placeholder.listen(64)
        deadline = time.monotonic() + timeout_s
        missing = [t for t in addresses if t != me]
        while missing:
            missing = [t for t in missing if not _reachable(addresses[t], timeout_s=1.0)]
            if not missing or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        return missing
    finally:
        placeholder.close()


class Watchdog:
    """A daemon thread that ends the process when a multi-worker wait (one step; the join of every worker) lasts
    longer than `limit_s` after `arm()`.

    The backstop of the lost-peer bound: the collectives time out by themselves and TensorFlow's coordination
    service notices a worker that stops heartbeating, but a step can also wait outside a collective (on a peer's
    connection setup, on an input that no longer answers) and the join has no bound of its own. The watchdog prints
    the one-line message (`on_expire(seconds)` builds it) and exits with EXIT_PEER_LOST: there is nothing safe to
    save from a step in flight, and a Python exception cannot interrupt the C++ wait."""

    def __init__(self, limit_s: float, on_expire):
        self.limit_s, self.on_expire = limit_s, on_expire
        self._armed_at = None
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="step-watchdog", daemon=True)
        self._thread.start()

    def arm(self) -> None:
        with self._cond:
            self._armed_at = time.monotonic()
            self._cond.notify()

    def disarm(self) -> None:
        with self._cond:
            self._armed_at = None
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._closed, self._armed_at = True, None
            self._cond.notify()
        self._thread.join(5)

    def _run(self) -> None:
        with self._cond:
            while not self._closed:
                if self._armed_at is None:
                    self._cond.wait()
                    continue
                left = self._armed_at + self.limit_s - time.monotonic()
                if left > 0:
                    self._cond.wait(left)
                    continue
                message = self.on_expire(time.monotonic() - self._armed_at)
                print(f"error: {message}", file=sys.stderr, flush=True)
                sys.stdout.flush()
                os._exit(EXIT_PEER_LOST)
