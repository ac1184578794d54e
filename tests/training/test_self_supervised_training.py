"""Training without flow labels (`data.labels=self`): SeFlow's loss on the pair and TeFlow's over 3 sweeps, either
head, on two replicas (the suite's two logical CPUs), with resume; the input reads the loss table's fields and names
the missing ones; evaluation still scores the records' human labels."""
import os

import numpy as np
import pytest

pytest.importorskip("dufomap")
pytest.importorskip("hdbscan")

from ff3d_tf.config import ConfigError, load_config, replace_config  # noqa: E402
from ff3d_tf.data import pair_records  # noqa: E402
from ff3d_tf.data.wod import write_records  # noqa: E402
from ff3d_tf.labels import self_supervision  # noqa: E402
from ff3d_tf.training import input as training_input  # noqa: E402
from ff3d_tf.training.trainer import Trainer  # noqa: E402


def _prepared(tiny_segment, out, overrides):
    cfg = load_config(None, overrides + ["selfsup.num_threads=1"])
    raw = os.path.join(out, "records")
    manifest = write_records.wod_manifest(cfg)
    pair_records.write_manifest(raw, manifest)
    write_records.write_segment(tiny_segment, raw, cfg, manifest)
    files = [os.path.join(raw, f) for f in os.listdir(raw) if f.endswith(pair_records.FILE_SUFFIX)]
    self_supervision.run_preparation_job(files, os.path.join(out, "prepared"), cfg)
    prepared = [os.path.join(out, "prepared", os.path.basename(f)) for f in files]
    return cfg, files, prepared


def _train_cfg(cfg, **changes):
    # a quarter of the points (the density study's switch, applied to the fields alike): the losses' exact nearest
    # neighbours cost N x M a cloud; the step uncompiled (the losses as one XLA program:
    # tests/model/test_selfsup_losses.py)
    return replace_config(cfg, {"data.source": "pair_records", "data.labels": "self", "train.log_every_steps": 1,
                                "train.checkpoint_every_steps": 2, "train.eval_every_steps": 0,
                                "data.point_keep_fraction": 0.25, "model.compile": "none", **changes})


def _weights(trainer):
    return [v.numpy().copy() for v in trainer.model.trainable_variables]


def test_seflow_trains_resumes_and_evaluates_human_labels(tiny_segment, tiny_config, tmp_path):
    from ff3d_tf.model.forward import ModelPredictor
    from ff3d_tf.training.evaluation import evaluate
    cfg, raw, prepared = _prepared(tiny_segment, str(tmp_path), list(_tiny()))
    cfg = _train_cfg(cfg, **{"train.loss": "seflow"})
    assert training_input.loss_extras(prepared, cfg) == ("dynamic_cluster_t0", "dynamic_cluster_tm1")
    with pytest.raises(ConfigError, match=r"train.loss=seflow needs \['dynamic_cluster_t0', 'dynamic_cluster_tm1'\].*"
                                          r"tools/prepare_self_supervision.py"):
        training_input.loss_extras(raw, cfg)
    first = Trainer(cfg, str(tmp_path / "m"), prepared, log_fn=lambda s: None)
    assert first.strategy.num_replicas_in_sync == 2
    before = _weights(first)
    out = first.train(2)
    assert out["step"] == 2 and np.isfinite(out["loss"]) and out["loss"] > 0
    assert any(not np.allclose(a, b) for a, b in zip(before, _weights(first)))
    resumed = Trainer(cfg, str(tmp_path / "m"), prepared, log_fn=lambda s: None)
    out = resumed.train(3)
    assert out["step"] == 3 and np.isfinite(out["loss"])
    # evaluation reads the human labels of the same records (the synthetic segment's), as with any model
    human = replace_config(cfg, {"data.labels": "human", "train.loss": "l2"})
    metrics, _ = evaluate(human, prepared, ModelPredictor(resumed.model), max_pairs=1, log_fn=None)
    assert metrics["all/all/count"] > 0 and np.isfinite(metrics["all/all/mean_l2_mps"])


@pytest.mark.slow  # another training: ~2 to 4 min on 2 cores (TeFlow's arithmetic: tests/model/test_selfsup_losses.py)
def test_teflow_over_three_sweeps_with_the_gru_head(tiny_segment, tmp_path):
    cfg, _, prepared = _prepared(tiny_segment, str(tmp_path), list(_tiny()) + [
        "data.num_frames=3", "model.temporal=delta"])
    cfg = _train_cfg(cfg, **{"train.loss": "teflow", "model.head": "gru", "model.gru_iterations": 1})
    assert training_input.loss_extras(prepared, cfg) == ("dynamic_cluster_t0", "dynamic_cluster_tm1",
                                                         "dynamic_cluster_tm2")
    trainer = Trainer(cfg, str(tmp_path / "m"), prepared, log_fn=lambda s: None)
    before = _weights(trainer)
    out = trainer.train(2)
    assert out["step"] == 2 and np.isfinite(out["loss"]) and out["loss"] > 0
    assert any(not np.allclose(a, b) for a, b in zip(before, _weights(trainer)))


def _tiny():
    from ff3d_tf.config import TINY_OVERRIDES
    return TINY_OVERRIDES
