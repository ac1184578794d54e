"""Training input served by tf.data service: an in-process dispatcher and two workers; the trainer learns from it."""
import os
import subprocess
import sys

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


def test_service_roles_as_processes(tmp_path):
    """`tools/data_service.py` starts a dispatcher and a worker that serve a dataset to this process."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    dispatcher = subprocess.Popen([sys.executable, "tools/data_service.py", "--dispatcher"], cwd=ROOT, env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    worker = None
    try:
        line = dispatcher.stdout.readline()
        assert "dispatcher serving on port" in line, line
        port = int(line.split("port ")[1].split(";")[0])
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
