"""Training and evaluation with DeFlow's GRU head (`model.head=gru`): two replicas and two workers equal the
one-model reference (`replica_reference.Reference`), its checkpoint restores, a resumed run continues it; evaluation
scores a model and its SavedModel alike and takes the Argoverse 2 protocol."""
import dataclasses
import os

import numpy as np
import pytest
import tensorflow as tf

import test_multiworker as multiworker
from replica_reference import GLOBAL_BATCH, Reference, batches, replica_config

from ff3d_tf.checkpoints import restore_model
from ff3d_tf.config import load_config, replace_config
from ff3d_tf.data import pairs
from ff3d_tf.inference.saved_model import SavedModelPredictor, export_saved_model
from ff3d_tf.model import build_model
from ff3d_tf.model.forward import ModelPredictor
from ff3d_tf.training.evaluation import evaluate, evaluate_av2
from ff3d_tf.training.trainer import Trainer


# One GRU step: the layer's tests (tests/model/test_gru_head.py) check several; here a smaller program to compile for
# each trainer and reference. The two-worker test gives the same overrides to `tools/train.py` (`--set`): the GRU's
# weights are the same whatever the iteration count, so a worker with another count trains a model of the same
# variables but another function.
GRU = {"model.head": "gru", "model.gru_iterations": 1}
GRU_SETS = tuple(f"{k}={v}" for k, v in GRU.items())


def _gru(cfg):
    return replace_config(cfg, GRU)


def _two_replicas():
    # Reduction through one device, not TensorFlow's collectives: a process keeps each collective instance's shape
    # from its first use, and the paper model's trainers of other test files in the same process (pytest-xdist) use
    # the same instance keys with other gradient shapes. tests/training/test_distributed.py tests the collectives.
    return tf.distribute.MirroredStrategy(["/cpu:0", "/cpu:1"], cross_device_ops=tf.distribute.ReductionToOneDevice())


def _distributed(strategy, batch):
    return iter(strategy.experimental_distribute_dataset(tf.data.Dataset.from_tensors(batch).unbatch()
                                                         .batch(GLOBAL_BATCH)))


def _assert_same_variables(model, ref_model):
    assert len(model.variables) == len(ref_model.variables)
    for a, b in zip(model.variables, ref_model.variables):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6, err_msg=a.path)


def _assert_same_optimizer(optimizer, ref_optimizer):
    for a, b in zip(optimizer.variables, ref_optimizer.variables):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7, err_msg=a.path)


def test_two_replicas_equal_the_reference_and_restore_from_the_checkpoint(tiny_segment, tiny_config, tmp_path):
    """A step under two replicas: loss, weights, optimizer state and BatchNorm statistics equal one model stepping on
    the same samples; the checkpoint restores that model (`restore_model`: evaluation's and export's path)."""
    cfg = _gru(replica_config(tiny_config))
    (batch,) = batches(tiny_segment, cfg, 1)
    model_dir = str(tmp_path / "m")
    trainer = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    assert trainer.model.head == "gru" and trainer.strategy.num_replicas_in_sync == 2
    ref = Reference(cfg, trainer.model.get_weights())
    np.testing.assert_allclose(float(trainer.step(_distributed(trainer.strategy, batch))), ref.step(batch), rtol=1e-5)
    _assert_same_variables(trainer.model, ref.model)
    _assert_same_optimizer(trainer.optimizer, ref.optimizer)
    trainer.manager.save(checkpoint_number=1)
    _assert_same_variables(restore_model(cfg, model_dir), ref.model)


@pytest.mark.slow  # three compiles of the training step: ~3 min on 2 busy cores
def test_two_replicas_with_a_resume_equal_the_reference(tiny_segment, tiny_config, tmp_path):
    """A step under two replicas, a checkpoint, a fresh trainer resuming from it, a second step: the losses, weights,
    optimizer state and BatchNorm statistics equal one model stepping on the same samples."""
    cfg = _gru(replica_config(tiny_config))
    two = batches(tiny_segment, cfg, 2)
    model_dir = str(tmp_path / "m")
    first = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    ref = Reference(cfg, first.model.get_weights())
    np.testing.assert_allclose(float(first.step(_distributed(first.strategy, two[0]))), ref.step(two[0]), rtol=1e-5)
    first.manager.save(checkpoint_number=1)
    resumed = Trainer(cfg, model_dir, [tiny_segment], strategy=_two_replicas(), log_fn=lambda s: None)
    resumed.restore_latest()
    assert int(resumed.global_step.numpy()) == 1
    np.testing.assert_allclose(float(resumed.step(_distributed(resumed.strategy, two[1]))), ref.step(two[1]),
                               rtol=1e-5)
    _assert_same_variables(resumed.model, ref.model)
    _assert_same_optimizer(resumed.optimizer, ref.optimizer)


@pytest.mark.slow  # two training processes: ~2 min on 2 busy cores
def test_two_workers_equal_each_other_and_the_reference(tiny_segment, tiny_config, tmp_path, monkeypatch):
    """`tools/train.py` on two workers (TF_CONFIG) with the GRU head: bit-identical workers, equal to the reference
    (the multi-worker test's procedure, `test_multiworker`, with `model.head=gru`)."""
    monkeypatch.setattr(multiworker, "SETS", multiworker.SETS + GRU_SETS)
    cfg = _gru(replica_config(tiny_config))
    model_dir = str(tmp_path / "m")
    outs = multiworker._finish(multiworker._start_workers(os.path.dirname(tiny_segment), model_dir,
                                                          multiworker.STEPS))
    assert load_config(os.path.join(model_dir, "config.yaml")).model == cfg.model, "workers trained another model"
    fingerprints = multiworker._fingerprints(outs)
    assert fingerprints[0] == fingerprints[1], "workers ended with different weights"
    ref = multiworker._reference(tiny_segment, cfg, multiworker._initial_weights(cfg), multiworker.STEPS)
    trained = restore_model(cfg, model_dir)
    assert trained.head == "gru"
    _assert_same_variables(trained, ref.model)


def test_the_workers_are_given_the_references_config(tiny_config):
    """What `tools/train.py` loads from the two-worker test's command line (its default config file and
    `multiworker.SETS` with the GRU's overrides) is the reference's config, but for the keys that only run the
    workers: no CPU, no training (the two-worker test itself is slow)."""
    worker = multiworker.worker_config(GRU_SETS)
    reference = _gru(replica_config(tiny_config))
    only_the_workers = {"num_steps", "checkpoint_every_steps"}
    assert worker.model == reference.model and worker.grid == reference.grid and worker.data == reference.data
    assert ({k: v for k, v in dataclasses.asdict(worker.train).items() if k not in only_the_workers}
            == {k: v for k, v in dataclasses.asdict(reference.train).items() if k not in only_the_workers})


@pytest.mark.slow  # a GRU SavedModel export and two evaluations: ~50 s; the paper head's in tests/training/test_evaluation.py
def test_evaluation_of_a_model_and_its_saved_model_agree(tiny_segment, tiny_config, tmp_path):
    cfg = _gru(tiny_config)
    model = build_model(cfg)
    result, zero = evaluate(cfg, [tiny_segment], ModelPredictor(model), log_fn=lambda s: None)
    saved = SavedModelPredictor(export_saved_model(model, str(tmp_path / "sm"), cfg.data.point_bucket_base))
    result_sm, _ = evaluate(cfg, [tiny_segment], saved, log_fn=lambda s: None)
    assert result["all/all/count"] == zero["all/all/count"] > 0
    for key in ("all/all/count", "vehicle/moving/count", "all/all/mean_l2_mps", "all/moving/frac_l2_le_1.0"):
        np.testing.assert_allclose(result_sm[key], result[key], rtol=1e-4, err_msg=key)


def test_argoverse2_protocol_scores_the_gru_model(av2_sample_records, tiny_config):
    """`evaluate_av2` (the challenge's protocol) with the GRU model's predictor: the model's flow is scored on the
    same points as zero flow, and differs from it."""
    cfg = replace_config(_gru(tiny_config), {"data.source": "pair_records"})
    r = evaluate_av2(cfg, pairs.list_segment_files(av2_sample_records), ModelPredictor(build_model(cfg)))
    assert r["model"]["num_sweeps"] == 1 and r["model"]["num_points"] == r["zero_flow"]["num_points"] > 50_000
    assert np.isfinite(r["model"]["three_way/mean_epe_m"])
    assert r["model"]["three_way/mean_epe_m"] != r["zero_flow"]["three_way/mean_epe_m"]
