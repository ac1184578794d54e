"""Training loop: a step changes weights, resume equals uninterrupted, non-finite steps never reach the weights."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.config import replace_config
from ff3d_tf.training.trainer import NonFiniteLossError, Trainer


def _cfg(tiny_config, **train):
    return replace_config(tiny_config, {"train.log_every_steps": 1, "train.checkpoint_every_steps": 100,
                                        "train.eval_every_steps": 0, **{f"train.{k}": v for k, v in train.items()}})


def _weights(trainer):
    return [v.numpy().copy() for v in trainer.model.trainable_variables]


@pytest.mark.parametrize("root", ["local", "ram://"])
def test_two_steps_change_weights_and_write_config(tiny_segment, tiny_config, tmp_path, root, monkeypatch):
    from ff3d_tf import cpu
    from ff3d_tf.checkpoints import restore_model
    trims = []  # the heap compilation freed goes back to the OS once, after the first step
    monkeypatch.setattr(cpu, "malloc_trim", lambda real=cpu.malloc_trim: trims.append(real()))
    # `ram://` stands in for a cloud model_dir (gs://): checkpoints, config and history go through tf.io.gfile.
    model_dir = str(tmp_path / "m") if root == "local" else f"ram://{tmp_path}/m"
    t = Trainer(_cfg(tiny_config), model_dir, [tiny_segment], log_fn=lambda s: None)
    before = _weights(t)
    out = t.train(2)
    assert out["step"] == 2 and np.isfinite(out["loss"])
    assert trims == [True]
    assert any(not np.allclose(a, b) for a, b in zip(before, _weights(t)))
    assert tf.io.gfile.exists(f"{model_dir}/config.yaml") and tf.io.gfile.exists(f"{model_dir}/train_history.json")
    restored = restore_model(tiny_config, model_dir)
    for a, b in zip(_weights(t), [v.numpy() for v in restored.trainable_variables]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow  # two trainings of four steps: ~90 s; tests/training/test_kill_resume.py resumes in the fast suite
def test_resume_equals_uninterrupted(tiny_segment, tiny_config, tmp_path):
    cfg = _cfg(tiny_config, seed=3)
    one = Trainer(cfg, str(tmp_path / "a"), [tiny_segment], log_fn=lambda s: None)
    one.train(4)
    first = Trainer(cfg, str(tmp_path / "b"), [tiny_segment], log_fn=lambda s: None)
    first.train(2)
    resumed = Trainer(cfg, str(tmp_path / "b"), [tiny_segment], log_fn=lambda s: None)
    assert int(resumed.global_step.numpy()) == 0
    resumed.train(4)
    assert int(resumed.global_step.numpy()) == 4
    for a, b in zip(_weights(one), _weights(resumed)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(one.optimizer.variables, resumed.optimizer.variables):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)


def test_nonfinite_steps_are_skipped_then_stop(tiny_segment, tiny_config, tmp_path, monkeypatch):
    from ff3d_tf.training import trainer as trainer_module
    real_dataset = trainer_module.training_dataset

    def nan_labels(*args, **kwargs):  # the real batches, with NaN flow labels: a real non-finite loss
        return real_dataset(*args, **kwargs).map(lambda b: {**b, "flow_mps_t0": b["flow_mps_t0"] * np.nan})
    monkeypatch.setattr(trainer_module, "training_dataset", nan_labels)
    cfg = _cfg(tiny_config, max_nonfinite_steps_in_row=2)
    t = Trainer(cfg, str(tmp_path / "n"), [tiny_segment], log_fn=lambda s: None)
    before = _weights(t)
    moving_before = [v.numpy().copy() for v in t.model.non_trainable_variables]
    optimizer_before = [np.asarray(v).copy() for v in t.optimizer.variables]
    with pytest.raises(NonFiniteLossError, match="non-finite steps in a row"):
        t.train(5)
    assert int(t.nonfinite_total.numpy()) == 2 and int(t.global_step.numpy()) == 2
    for a, b in zip(before, _weights(t)):
        np.testing.assert_array_equal(a, b)
    # The forward pass did move the BatchNorm statistics: restored too; Adam's slots and iteration count untouched.
    for a, b in zip(moving_before, t.model.non_trainable_variables):
        np.testing.assert_array_equal(a, b.numpy())
    for a, b in zip(optimizer_before, t.optimizer.variables):
        np.testing.assert_array_equal(a, np.asarray(b))


def test_bad_record_stops_training_with_its_name_or_is_skipped(tiny_records, tiny_config, tmp_path):
    import corrupt_records
    from ff3d_tf.data.wod_errors import FrameDecodeError
    path = corrupt_records.write_records(str(tmp_path / "bad.tfrecord"), [
        tiny_records[0], corrupt_records.nan_range_image(tiny_records[1], 4), tiny_records[2], tiny_records[3]])
    t = Trainer(_cfg(tiny_config), str(tmp_path / "m"), [path], log_fn=lambda s: None)
    with pytest.raises(FrameDecodeError, match=r"bad.tfrecord: record 1: field lasers\[SIDE_RIGHT\].ri_return1"):
        t.train(2)
    assert int(t.global_step.numpy()) < 2  # the step whose batch hit the bad record never ran
    skip = replace_config(tiny_config, {"data.skip_bad_records": True})
    out = Trainer(_cfg(skip), str(tmp_path / "s"), [path], log_fn=lambda s: None).train(2)
    assert out["step"] == 2 and np.isfinite(out["loss"])


def test_periodic_evaluation_is_the_evaluation_on_a_few_pairs(tiny_segment, tiny_config, tmp_path):
    from ff3d_tf.model.forward import ModelPredictor
    from ff3d_tf.training.evaluation import SUMMARY_KEYS, evaluate
    cfg = _cfg(tiny_config, eval_num_batches=2)
    t = Trainer(cfg, str(tmp_path / "m"), [tiny_segment], [tiny_segment], log_fn=lambda s: None)
    got = t.evaluate_subset(7)
    want, _ = evaluate(cfg, [tiny_segment], ModelPredictor(t.model), max_pairs=2, log_fn=None)
    every, _ = evaluate(cfg, [tiny_segment], ModelPredictor(t.model), log_fn=None)
    assert 0 < got["all/all/count"] == want["all/all/count"] < every["all/all/count"]  # 2 of the segment's 3 pairs
    np.testing.assert_allclose([got[k] for k in SUMMARY_KEYS], [want[k] for k in SUMMARY_KEYS], rtol=1e-6)
    (events,) = tf.io.gfile.glob(str(tmp_path / "m" / "eval" / "events.out.tfevents.*"))
    written = {(v.tag, e.step) for e in tf.compat.v1.train.summary_iterator(events) for v in e.summary.value}
    assert written == {(k, 7) for k in SUMMARY_KEYS if not np.isnan(got[k])} and written


def test_max_training_segments_caps_the_training_input(tiny_segment, tiny_config, tmp_path):
    from ff3d_tf.training.input import training_dataset, training_files
    missing = str(tmp_path / "missing.tfrecord")  # read only when the cap leaves it in
    capped = replace_config(tiny_config, {"data.max_training_segments": 1})
    assert training_files([tiny_segment, missing], capped) == [tiny_segment]
    assert training_files([tiny_segment, missing], tiny_config) == [tiny_segment, missing]
    batch = next(iter(training_dataset([tiny_segment, missing], capped, 2)))
    assert batch["points_xyz_t0"].shape[0] == 2
    with pytest.raises(tf.errors.NotFoundError):
        next(iter(training_dataset([tiny_segment, missing], tiny_config, 2)))


def test_deltaflow_reads_its_records_extras_and_says_once_when_instances_are_missing(av2_sample_records, tiny_segment,
                                                                                      tiny_config, tmp_path):
    from ff3d_tf.data import pairs
    from ff3d_tf.training import input as training_input
    records = pairs.list_segment_files(av2_sample_records)
    cfg = replace_config(tiny_config, {"train.loss": "deltaflow", "data.source": "pair_records"})
    assert training_input.loss_extras(records, cfg) == ("category_t0", "instance_id_t0")
    assert training_input.loss_notice(records, cfg) is None
    assert training_input.loss_extras(records, replace_config(cfg, {"train.loss": "deflow"})) == ()
    batch = {k: v.numpy()[0] for k, v in next(iter(training_input.training_dataset(records, cfg, 1))).items()}
    ids, real = batch["instance_id_t0"], batch["point_mask_t0"]
    # numbered densely within the pair (0, 1, ... in order of first appearance), -1 outside cuboids and for padding
    assert sorted(set(ids[ids >= 0].tolist())) == list(range(ids.max() + 1))
    _, first = np.unique(ids[ids >= 0], return_index=True)
    assert (np.diff(first) > 0).all()
    np.testing.assert_array_equal(ids[real] >= 0, batch["category_t0"][real] > 0)
    assert (ids[~real] == -1).all()
    # WOD segments carry no instance ids: the trainer says so, once
    wod_cfg = _cfg(replace_config(tiny_config, {"train.loss": "deltaflow"}))
    logged = []
    Trainer(wod_cfg, str(tmp_path / "m"), [tiny_segment], log_fn=logged.append)
    assert [line for line in logged if "instance term" in line] == [training_input.loss_notice([tiny_segment], wod_cfg)]
