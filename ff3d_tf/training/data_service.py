"""tf.data service roles (`tf.data.experimental.service`): a dispatcher and workers that run the training input.

The trainer's side is `input.training_dataset(..., data_service_address=...)`; these start the servers, for
`tools/data_service.py` and for tests (in-process).

Faults: the trainers read with dynamic sharding, so a worker that dies only takes the elements it held (the split
it was reading and its buffered batches: at most once, not exactly once); the others keep feeding the job, and a
restarted worker registers again and is given work. A dispatcher with a `work_dir` runs in fault-tolerant mode: it
journals its state (datasets, jobs, splits handed out) before answering, so restarted on the same port and work dir
it resumes the job, and the trainers and workers reconnect by themselves (they retry the dispatcher's address).
"""
from __future__ import annotations

import dataclasses

import tensorflow as tf


@dataclasses.dataclass
class Server:
    """A started dispatcher or worker: `port`, `target` (grpc://localhost:port for a dispatcher), `join()`."""
    server: object
    port: int
    target: str

    def join(self) -> None:
        self.server.join()

    def stop(self) -> None:
        self.server.stop()


def start_dispatcher(port: int = 0, work_dir: str | None = None) -> Server:
    """A dispatcher on `port` (0: a free one); `work_dir` keeps its state so that a restart resumes its jobs."""
    config = tf.data.experimental.service.DispatcherConfig(port=port, work_dir=work_dir,
                                                           fault_tolerant_mode=bool(work_dir))
    server = tf.data.experimental.service.DispatchServer(config)
    target = server.target
    return Server(server, int(target.rsplit(":", 1)[1]), target)


def start_worker(dispatcher_address: str, port: int = 0, host: str | None = None) -> Server:
    """A worker registered with the dispatcher at host:port (a grpc:// prefix is accepted). `host`: the name the
    trainers reach this worker by (default localhost: trainers on the same machine)."""
    address = dispatcher_address.split("://", 1)[-1]
    server = tf.data.experimental.service.WorkerServer(
        tf.data.experimental.service.WorkerConfig(dispatcher_address=address, port=port,
                                                  worker_address=f"{host}:%port%" if host else None))
    worker_port = int(server._address.rsplit(":", 1)[1])  # noqa: SLF001 - the bound port, when 0 was asked for
    return Server(server, worker_port, f"grpc://{address}")
