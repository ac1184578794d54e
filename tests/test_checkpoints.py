"""Damaged and mismatched checkpoints: named errors, resume from the newest intact one, damaged files kept aside."""
import dataclasses
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf.checkpoints import restore_model
from ff3d_tf.inference.predictor import load_predictor
from ff3d_tf import checkpoints
from ff3d_tf.checkpoints import CheckpointError
from ff3d_tf.training.trainer import Trainer


LOG: list = []  # the trainers' log lines of the current test


def _trainer(cfg, model_dir):
    return Trainer(cfg, str(model_dir), ["unused.tfrecord"], log_fn=LOG.append)


@pytest.fixture(scope="module")
def saved_dir(tiny_config, tmp_path_factory):
    """A model_dir with ckpt-1, ckpt-2, ckpt-3 (step = N, the weights differ between them); no training needed."""
    model_dir = tmp_path_factory.mktemp("ckpts") / "m"
    trainer = _trainer(tiny_config, model_dir)
    for n in (1, 2, 3):
        trainer.global_step.assign(n)
        kernel = trainer.model.head_z.kernel
        kernel.assign(kernel + 0.01 * n)
        trainer.manager.save(checkpoint_number=n)
    return model_dir


@pytest.fixture
def model_dir(saved_dir, tmp_path):
    target = tmp_path / "m"
    shutil.copytree(saved_dir, target)
    LOG.clear()
    return target


def _ckpt(model_dir, n):
    return str(model_dir / "checkpoints" / f"ckpt-{n}")


def _data(prefix):
    return prefix + ".data-00000-of-00001"


def _truncate(path):
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) // 2)


def test_list_newest_first_and_intact_ones_verify(tiny_config, model_dir):
    found = checkpoints.list_checkpoints(str(model_dir / "checkpoints"))
    assert found == [_ckpt(model_dir, n) for n in (3, 2, 1)]
    trainer = _trainer(tiny_config, model_dir / "other")
    # model, optimizer (iterations, learning rate, 2 moments per trainable variable) and the three counters
    expected = len(trainer.model.variables) + len(trainer.optimizer.variables) + 3
    assert checkpoints.verify_checkpoint(trainer.checkpoint, found[0]) == expected


@pytest.mark.parametrize("damage,reason", [
    ("truncated_data", "cannot be read"),
    ("missing_data", "data file ckpt-3.data-00000-of-* is missing"),
    ("missing_index", "index file ckpt-3.index is missing"),
    ("garbage_index", "index ckpt-3.index cannot be read"),
    ("flipped_bit", "cannot be read")])
def test_damaged_latest_is_named_moved_aside_and_older_one_resumed(tiny_config, model_dir, damage, reason):
    latest = _ckpt(model_dir, 3)
    if damage == "truncated_data":
        _truncate(_data(latest))
    elif damage == "missing_data":
        os.remove(_data(latest))
    elif damage == "missing_index":
        os.remove(latest + ".index")
    elif damage == "garbage_index":
        with open(latest + ".index", "wb") as f:
            f.write(b"not a table" * 50)
    elif damage == "flipped_bit":
        # A bit in the middle of the data: the tensor's checksum no longer matches.
        with open(_data(latest), "r+b") as f:
            f.seek(os.path.getsize(_data(latest)) // 2)
            byte = f.read(1)[0]
            f.seek(-1, 1)
            f.write(bytes([byte ^ 0x10]))
    kept = {name: open(model_dir / "checkpoints" / name, "rb").read()
            for name in os.listdir(model_dir / "checkpoints") if name.startswith("ckpt-3.")}
    trainer = _trainer(tiny_config, model_dir)
    with pytest.raises(CheckpointError, match=f"checkpoint .*ckpt-3 is unusable: .*{re.escape(reason)}"):
        checkpoints.verify_checkpoint(trainer.checkpoint, latest)
    # Resume at step 2 of 2: the restore block runs, nothing is trained.
    assert trainer.train(num_steps=2)["step"] == 2
    assert any("ckpt-3 is unusable" in line and "resuming from the older" in line for line in LOG), LOG
    assert any(line.startswith(f"resumed from {_ckpt(model_dir, 2)} at step 2") for line in LOG), LOG
    # The damaged files were moved, byte for byte, never deleted; the reason is written beside them.
    aside = model_dir / "checkpoints" / "damaged" / "ckpt-3"
    assert {name: open(aside / name, "rb").read() for name in kept} == kept
    assert reason in (aside / "REASON.txt").read_text()
    assert checkpoints.list_checkpoints(str(model_dir / "checkpoints")) == [_ckpt(model_dir, n) for n in (2, 1)]


def test_no_intact_checkpoint_stops_without_touching_anything(tiny_config, model_dir):
    for n in (1, 2, 3):
        _truncate(_data(_ckpt(model_dir, n)))
    before = sorted(os.listdir(model_dir / "checkpoints"))
    trainer = _trainer(tiny_config, model_dir)
    with pytest.raises(CheckpointError, match=r"none of its 3 checkpoints is intact and fits this model \(ckpt-3: "
                                              r".*ckpt-1: .*Nothing was moved or overwritten"):
        trainer.train(num_steps=5)
    assert sorted(os.listdir(model_dir / "checkpoints")) == before  # no damaged/, no new checkpoint
    assert int(trainer.global_step.numpy()) == 0


def test_checkpoint_of_another_config_names_first_differing_variable(tiny_config, model_dir):
    other = dataclasses.replace(tiny_config, model=dataclasses.replace(tiny_config.model, head_hidden_dim=16))
    # Row Y's kernel is [grid embedding 16 + point feature 16 + point encoding 8 = 40, head_hidden_dim] in the tiny
    # model: 8 saved, 16 here. BFS order over the model's layers reaches head_y first among the differing variables.
    with pytest.raises(CheckpointError, match=r"ckpt-3 is unusable: variable model/head_y/kernel is "
                                              r"float32\[40, 8\] in the checkpoint but float32\[40, 16\] in this "
                                              r"model"):
        restore_model(other, str(model_dir))
    # Training over that model_dir stops too (the checkpoints are not damaged: nothing is moved).
    trainer = _trainer(other, model_dir)
    with pytest.raises(CheckpointError, match="none of its 3 checkpoints is intact and fits this model .*"
                                              "model/head_y/kernel"):
        trainer.train(num_steps=5)
    assert not (model_dir / "checkpoints" / "damaged").exists()


def test_restore_model_names_damaged_checkpoint_and_the_intact_one(tiny_config, model_dir):
    _truncate(_data(_ckpt(model_dir, 3)))
    with pytest.raises(CheckpointError, match=f"{_ckpt(model_dir, 3)} is unusable: .*the newest intact checkpoint "
                                              f"is {_ckpt(model_dir, 2)}"):
        load_predictor(tiny_config, str(model_dir))
    # Nothing moved by a reader; the intact one, named explicitly, restores its own weights.
    assert os.path.exists(_data(_ckpt(model_dir, 3))) and not (model_dir / "checkpoints" / "damaged").exists()
    model = restore_model(tiny_config, _ckpt(model_dir, 2))
    saved = tf.train.load_checkpoint(_ckpt(model_dir, 2))
    np.testing.assert_array_equal(model.head_z.kernel.numpy(),
                                  saved.get_tensor("model/head_z/_kernel/.ATTRIBUTES/VARIABLE_VALUE"))


def test_export_tool_reports_damaged_checkpoint(model_dir, tmp_path):
    from conftest import ROOT, TINY_OVERRIDES
    with open(_ckpt(model_dir, 3) + ".index", "wb") as f:
        f.write(b"\0" * 100)
    sets = [a for s in TINY_OVERRIDES for a in ("--set", s)]
    out = subprocess.run([sys.executable, "tools/export.py", "--config", "", "--checkpoint", str(model_dir), "--out",
                          str(tmp_path / "sm"), *sets], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0
    # A clean message (tools/_common.run), no traceback.
    assert f"error: checkpoint {_ckpt(model_dir, 3)} is unusable: its index ckpt-3.index cannot be read" \
        in out.stderr, out.stderr[-2000:]
    assert "Traceback" not in out.stderr
    assert not (tmp_path / "sm").exists()


def test_saved_config_is_found_from_each_way_of_naming_a_model(tiny_config, model_dir, tmp_path):
    assert checkpoints.saved_config(str(model_dir)) is None  # no config.yaml yet
    saved = str(model_dir / checkpoints.CONFIG_NAME)
    tiny_config.save(saved)
    for given in (model_dir, model_dir / "checkpoints", _ckpt(model_dir, 2)):
        assert checkpoints.saved_config(str(given)) == saved, given
    # A model_dir holding its checkpoints directly; a SavedModel directory holding one; nothing for a missing path.
    flat = tmp_path / "flat"
    shutil.copytree(model_dir / "checkpoints", flat)
    tiny_config.save(str(flat / "config.yaml"))
    assert checkpoints.saved_config(str(flat / "ckpt-1")) == str(flat / "config.yaml")
    assert checkpoints.saved_config(str(tmp_path / "missing")) is None


def test_a_mismatch_names_the_models_own_config(tiny_config, model_dir):
    saved = str(model_dir / checkpoints.CONFIG_NAME)
    tiny_config.save(saved)
    other = dataclasses.replace(tiny_config, model=dataclasses.replace(tiny_config.model, head_hidden_dim=16))
    own = re.escape(f"its own config is {saved} (the tools load it when given no --config; check --config and --set)")
    with pytest.raises(CheckpointError, match=r"model/head_y/kernel is float32\[40, 8\] in the checkpoint but "
                                              r"float32\[40, 16\] in this model .*; " + own) as e:
        restore_model(other, _ckpt(model_dir, 3))
    assert e.value.mismatch
    with pytest.raises(CheckpointError, match=r"none of its 3 checkpoints is intact and fits this model .*" + own):
        _trainer(other, model_dir).train(num_steps=5)
    # A damaged checkpoint is not one of another config: its error does not send the reader to a config.
    _truncate(_data(_ckpt(model_dir, 3)))
    with pytest.raises(CheckpointError) as e:
        restore_model(tiny_config, _ckpt(model_dir, 3))
    assert not e.value.mismatch and "own config" not in str(e.value)


def test_a_model_of_another_definition_with_the_same_variables_is_refused(tiny_config, tmp_path):
    """delta's U-Net input is C wide whatever the number of sweeps, so a delta model of 3 sweeps restores into one of
    5 without a variable that differs: the saved config decides. Training over it and restoring it both stop naming
    the config, the key and both values, and the saved config is not rewritten."""
    def delta(num_frames):
        return dataclasses.replace(tiny_config, data=dataclasses.replace(tiny_config.data, num_frames=num_frames),
                                   model=dataclasses.replace(tiny_config.model, temporal="delta"))
    model_dir = tmp_path / "delta3"
    trainer = _trainer(delta(3), model_dir)
    trainer.manager.save(checkpoint_number=1)
    delta(3).save(str(model_dir / "config.yaml"))
    saved = (model_dir / "config.yaml").read_text()
    why = r"config.yaml is unusable: the model saved here is of another definition: data.num_frames=3 there, 5 here"
    with pytest.raises(CheckpointError, match=why):
        _trainer(delta(5), model_dir)
    with pytest.raises(CheckpointError, match=why):
        restore_model(delta(5), str(model_dir))
    assert (model_dir / "config.yaml").read_text() == saved
    # The same definition restores; a partner the config leaves unset is the saved model's.
    assert restore_model(delta(3), str(model_dir)).partner == "previous"
    nxt = dataclasses.replace(delta(3), data=dataclasses.replace(delta(3).data, partner="next"))
    nxt.save(str(model_dir / "config.yaml"))
    assert restore_model(delta(3), str(model_dir)).partner == "next"
    with pytest.raises(CheckpointError, match="data.partner=next there, previous here"):
        restore_model(dataclasses.replace(nxt, data=dataclasses.replace(nxt.data, partner="previous")),
                      str(model_dir))
