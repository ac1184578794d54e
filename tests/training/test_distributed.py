"""N replicas compute what one replica computes (reference: `replica_reference.Reference`)."""
import keras
import numpy as np
import pytest
import tensorflow as tf

from replica_reference import GLOBAL_BATCH, Reference, batches, replica_config

from ff3d_tf.config import replace_config
from ff3d_tf.training import cluster
from ff3d_tf.training.trainer import Trainer


def _distributed(strategy, batch):
    return iter(strategy.experimental_distribute_dataset(tf.data.Dataset.from_tensors(batch).unbatch()
                                                         .batch(GLOBAL_BATCH)))


def _assert_same(trainer, ref):
    assert len(trainer.model.variables) == len(ref.model.variables)
    for a, b in zip(trainer.model.variables, ref.model.variables):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6, err_msg=a.path)
    for a, b in zip(trainer.optimizer.variables, ref.optimizer.variables):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7, err_msg=a.path)


def _two_replicas():
    """The product's one strategy per process and devices (`cluster.mirrored_strategy`): the file's models of
    several sizes each train on it, as a second MirroredStrategy in a process failed (see there)."""
    return cluster.mirrored_strategy(("/cpu:0", "/cpu:1"))


# Without recomputation in `make test-slow` only: two replicas without it are also checked by the DeltaFlow test below
# and the GRU head's (tests/training/test_gru_head_training.py).
@pytest.mark.parametrize("remat", [pytest.param(False, marks=pytest.mark.slow), True])
def test_two_replicas_equal_the_reference(tiny_segment, tiny_config, tmp_path, remat):
    """Also with the encoder's activations recomputed in the backward (`model.remat_encoder`), against a reference
    that holds them."""
    cfg = replica_config(tiny_config)
    batch = batches(tiny_segment, cfg, 1)[0]
    trainer = Trainer(replace_config(cfg, {"model.remat_encoder": remat}), str(tmp_path / "m"), [tiny_segment],
                      strategy=_two_replicas(), log_fn=lambda s: None)
    assert trainer.strategy.num_replicas_in_sync == 2
    ref = Reference(cfg, trainer.model.get_weights())
    loss = float(trainer.step(_distributed(trainer.strategy, batch)))
    ref_loss = ref.step(batch)
    np.testing.assert_allclose(loss, ref_loss, rtol=1e-5)
    assert int(trainer.global_step.numpy()) == 1 and int(trainer.nonfinite_total.numpy()) == 0
    _assert_same(trainer, ref)
    # The BatchNorm statistics really differ per replica (else the mean rule above would not be tested).
    assert not np.allclose(batch["points_xyz_t0"][0], batch["points_xyz_t0"][1])


@pytest.mark.parametrize("loss", ["l2", "deflow", "deltaflow"])
def test_each_loss_over_two_replicas_is_the_loss_of_their_batch(loss):
    """Each replica's loss (its samples' losses over the global batch), summed over two replicas, is the loss of the
    whole batch on one device: every term is per sample (DeltaFlow's instances are numbered within a sample)."""
    from ff3d_tf.model.losses import batch_flow_loss
    rng = np.random.default_rng(3)
    n = 64
    flow_true = rng.choice([0.0, 0.7, 6.0], (GLOBAL_BATCH, n, 1)) * rng.normal(size=(GLOBAL_BATCH, n, 3))
    batch = {"flow_mps_t0": flow_true.astype(np.float32),
             "flow_mps_pred": (flow_true + rng.normal(size=flow_true.shape)).astype(np.float32),
             "class_id_t0": rng.integers(-1, 5, (GLOBAL_BATCH, n)).astype(np.int32),
             "point_mask_t0": np.arange(n)[None, :] < np.array([[n], [n - 9]]),
             "instance_id_t0": rng.integers(-1, 6, (GLOBAL_BATCH, n)).astype(np.int32)}

    def replica_loss(b):
        outputs = {"flow_mps": b["flow_mps_pred"], "point_valid": tf.ones_like(b["point_mask_t0"])}
        return batch_flow_loss(b, outputs, 0.1, GLOBAL_BATCH, loss=loss)

    strategy = _two_replicas()
    per_replica = strategy.run(tf.function(replica_loss), args=(next(_distributed(strategy, batch)),))
    two = float(strategy.reduce(tf.distribute.ReduceOp.SUM, per_replica, axis=None))
    one = float(replica_loss({k: tf.constant(v) for k, v in batch.items()}))
    assert one > 0
    np.testing.assert_allclose(two, one, rtol=1e-6)


def test_two_replicas_equal_the_reference_with_deltaflow(tiny_segment, tiny_config, tmp_path):
    """A training step with DeltaFlow's loss (DeFlow's buckets, its class and instance terms) under two replicas
    equals one model stepping on the same samples."""
    cfg = replace_config(replica_config(tiny_config), {"train.loss": "deltaflow"})
    batch = batches(tiny_segment, cfg, 1)[0]
    # Hand-made instances (WOD segments carry none): per class, the fast and the slow object points.
    speed_mps = np.linalg.norm(batch["flow_mps_t0"], axis=-1)
    batch["instance_id_t0"] = np.where(batch["class_id_t0"] > 0, 2 * batch["class_id_t0"] + (speed_mps > 1.0),
                                       -1).astype(np.int32)
    moving = [np.mean(speed_mps[i][batch["instance_id_t0"][i] == k]) > 0.4
              for i in range(GLOBAL_BATCH) for k in np.unique(batch["instance_id_t0"][i]) if k >= 0]
    assert any(moving)  # the instance term is not empty
    trainer = Trainer(cfg, str(tmp_path / "m"), [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    ref = Reference(cfg, trainer.model.get_weights())
    loss = float(trainer.step(_distributed(trainer.strategy, batch)))
    np.testing.assert_allclose(loss, ref.step(batch), rtol=1e-5)
    _assert_same(trainer, ref)


@pytest.mark.slow  # three compiled steps and a resume: ~65 s; tests/training/test_kill_resume.py resumes in the fast suite
def test_three_steps_with_resume_equal_the_reference(tiny_segment, tiny_config, tmp_path):
    cfg = replica_config(tiny_config)
    three = batches(tiny_segment, cfg, 3)
    model_dir = str(tmp_path / "m")
    first = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    ref = Reference(cfg, first.model.get_weights())
    for b in three[:2]:
        first.step(_distributed(first.strategy, b))
        ref.step(b)
    first.manager.save(checkpoint_number=2)
    resumed = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    resumed.restore_latest()
    assert int(resumed.global_step.numpy()) == 2
    resumed.step(_distributed(resumed.strategy, three[2]))
    ref.step(three[2])
    assert int(resumed.global_step.numpy()) == 3
    _assert_same(resumed, ref)


@pytest.mark.slow  # three compiled training steps of two replicas: minutes on 2 cores (CI's test-distributed runs it)
def test_two_replicas_of_a_three_sweep_model_equal_the_reference_and_resume(tiny_segment, tiny_config, tmp_path):
    """`model.temporal=delta` on 3 sweeps with the GRU head: a step on two replicas is the reference's; a trainer
    restored from its checkpoint holds its state exactly and takes the same next step as the trainer that wrote it."""
    cfg = replace_config(replica_config(tiny_config), {"data.num_frames": 3, "model.temporal": "delta",
                                                       "model.head": "gru", "model.gru_iterations": 1})
    two = batches(tiny_segment, cfg, 2)
    assert "points_xyz_tm2_in_t0" in two[0]
    model_dir = str(tmp_path / "m")
    first = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    ref = Reference(cfg, first.model.get_weights())
    np.testing.assert_allclose(float(first.step(_distributed(first.strategy, two[0]))), ref.step(two[0]), rtol=1e-5)
    _assert_same(first, ref)
    first.manager.save(checkpoint_number=1)
    resumed = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    resumed.restore_latest()
    for a, b in zip(resumed.model.variables + resumed.optimizer.variables,
                    first.model.variables + first.optimizer.variables):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=a.path)
    for trainer in (first, resumed):
        trainer.step(_distributed(trainer.strategy, two[1]))
    for a, b in zip(resumed.model.variables, first.model.variables):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7, err_msg=a.path)


@pytest.mark.parametrize("replicas", [1, 2])
def test_train_loop_under_strategy_learns(tiny_segment, tiny_config, tmp_path, replicas):
    """The whole loop (distributed dataset, sharding, checkpoints) runs under 1 and 2 replicas."""
    cfg = replica_config(tiny_config)
    strategy = _two_replicas() if replicas == 2 else tf.distribute.OneDeviceStrategy("/cpu:0")
    keras.utils.set_random_seed(0)
    out = Trainer(cfg, str(tmp_path / f"r{replicas}"), [tiny_segment], strategy=strategy,
                  log_fn=lambda s: None).train(3)
    assert out["step"] == 3 and np.isfinite(out["loss"])
