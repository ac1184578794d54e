"""A checkpoint knows its config: a tool given a model_dir, a checkpoint prefix or a SavedModel directory and no
--config loads the config saved with it (`tools/_common.load`) and says so; --config wins, --set still applies."""
import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT

PAPER = "configs/fastflow3d_waymo.yaml"


@pytest.fixture
def common(monkeypatch):
    monkeypatch.syspath_prepend(os.path.join(ROOT, "tools"))
    monkeypatch.chdir(ROOT)  # the tools' default configs are relative to the repository
    import _common
    return _common


@pytest.fixture
def model_dir(tiny_config, tmp_path):
    """A model_dir as training leaves it, but for its weights: the tiny config saved beside checkpoints/ckpt-1."""
    from ff3d_tf.checkpoints import CONFIG_NAME
    model_dir = tmp_path / "m"
    (model_dir / "checkpoints").mkdir(parents=True)
    for name in ("ckpt-1.index", "ckpt-1.data-00000-of-00001"):
        (model_dir / "checkpoints" / name).write_bytes(b"")
    tiny_config.save(str(model_dir / CONFIG_NAME))
    return model_dir


def _load(common, argv, flag="--checkpoint"):
    p = common.parser("a tool", PAPER)
    p.add_argument(flag)
    return common.load(p.parse_args(argv))


def test_without_config_the_saved_one_is_loaded_and_named(common, model_dir, tiny_config, capsys):
    for given in (model_dir, model_dir / "checkpoints", model_dir / "checkpoints" / "ckpt-1"):
        assert _load(common, ["--checkpoint", str(given)]) == tiny_config, given
        assert capsys.readouterr().out == (f"config: {model_dir / 'config.yaml'}, the one saved with {given} "
                                           f"(--config chooses another)\n")
    # train.py names its model by --model_dir (a resume).
    assert _load(common, ["--model_dir", str(model_dir)], "--model_dir") == tiny_config
    # --set applies on top of it.
    cfg = _load(common, ["--checkpoint", str(model_dir), "--set", "train.learning_rate=5e-4"])
    assert cfg.train.learning_rate == 5e-4 and cfg.grid == tiny_config.grid


def test_a_given_config_wins(common, model_dir, tiny_config, capsys):
    from ff3d_tf.config import load_config
    assert _load(common, ["--config", PAPER, "--checkpoint", str(model_dir)]) == load_config(PAPER)
    # "" is given too: the built-in defaults.
    assert _load(common, ["--config", "", "--checkpoint", str(model_dir)]) == load_config(None)
    assert "saved with" not in capsys.readouterr().out


def test_the_default_applies_without_a_saved_config(common, tmp_path, capsys):
    from ff3d_tf.config import load_config
    args = common.parser("a tool", PAPER)
    args.add_argument("--checkpoint")
    for argv in ([], ["--checkpoint", str(tmp_path)], ["--checkpoint", str(tmp_path / "missing")]):
        namespace = args.parse_args(argv)
        assert common.load(namespace) == load_config(PAPER) and namespace.config == PAPER
    assert capsys.readouterr().out == ""


def test_the_file_used_is_handed_on(common, model_dir):
    """`args.config` names the file loaded: a tool that passes --config to a child passes that one."""
    p = common.parser("a tool", PAPER)
    p.add_argument("--checkpoint")
    args = p.parse_args(["--checkpoint", str(model_dir)])
    common.load(args)
    assert args.config == str(model_dir / "config.yaml")


def test_a_namespace_not_made_by_the_parser_keeps_its_config(common, model_dir):
    import argparse
    from ff3d_tf.config import load_config
    args = argparse.Namespace(config=PAPER, set=[], checkpoint=str(model_dir))
    assert common.load(args) == load_config(PAPER)


def test_a_saved_model_directory_and_a_remote_model_dir(common, tiny_config, tmp_path):
    import tensorflow as tf
    saved_model = tmp_path / "sm"
    saved_model.mkdir()
    (saved_model / "saved_model.pb").write_bytes(b"")
    tiny_config.save(str(saved_model / "config.yaml"))
    assert _load(common, ["--checkpoint", str(saved_model)]) == tiny_config
    remote = "ram://common_config_test/m"
    tf.io.gfile.makedirs(remote + "/checkpoints")
    tiny_config.save(remote + "/config.yaml")
    assert _load(common, ["--model_dir", remote], "--model_dir") == tiny_config
    with tf.io.gfile.GFile(remote + "/config.yaml", "w") as f:
        f.write("grid: {pillars: 100}\n")
    with pytest.raises(SystemExit, match=r"config error: ram://common_config_test/m/config.yaml: .*pillars"):
        _load(common, ["--model_dir", remote], "--model_dir")


def test_a_job_that_runs_no_model_needs_no_model_temporal(common):
    """data.num_frames=3 alone: a job that runs a model must say how its sweeps meet (model.temporal); a job that
    runs none (records, pseudo-labels, NSFP) takes it as it is, any other fault still named."""
    p = common.parser("a tool", PAPER)
    args = p.parse_args(["--set", "data.num_frames=3"])
    with pytest.raises(SystemExit, match="model.temporal=pair"):
        common.load(args)
    assert common.load(args, runs_model=False).data.num_frames == 3
    with pytest.raises(SystemExit, match="data.num_frames=9"):
        common.load(p.parse_args(["--set", "data.num_frames=9"]), runs_model=False)


def test_an_onnx_file_carries_its_config(common, tiny_config, tmp_path, capsys):
    """tools/export_onnx.py writes the config into the file's metadata (`onnx_export.CONFIG_KEY`): a tool given the
    file and no --config loads it and says so; a file without one (an older export) leaves the default."""
    import onnx
    import yaml
    from ff3d_tf.config import load_config
    from ff3d_tf.inference import onnx_export
    graph = onnx.helper.make_graph([onnx.helper.make_node("Identity", ["x"], ["y"])], "g",
                                   [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
                                   [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])])
    proto = onnx.helper.make_model(graph)
    onnx.save(proto, str(tmp_path / "bare.onnx"))
    onnx.helper.set_model_props(proto, {onnx_export.CONFIG_KEY: yaml.safe_dump(
        json.loads(json.dumps(tiny_config.to_dict())))})
    onnx.save(proto, str(tmp_path / "m.onnx"))
    assert _load(common, ["--checkpoint", str(tmp_path / "m.onnx")]) == tiny_config
    assert capsys.readouterr().out == (f"config: the metadata of {tmp_path / 'm.onnx'}, the one saved with "
                                       f"{tmp_path / 'm.onnx'} (--config chooses another)\n")
    assert _load(common, ["--checkpoint", str(tmp_path / "bare.onnx")]) == load_config(PAPER)


@pytest.mark.slow  # trains, then evaluates through the tool: ~70 s
def test_eval_without_config_uses_the_models_own(tiny_segment, tiny_config, tmp_path):
    """The reported failure: eval given a model_dir trained with a non-default config and no --config stopped on
    the paper config's shapes. Now it loads the model's config.yaml; --config of another config is still named."""
    from ff3d_tf.config import replace_config
    from ff3d_tf.training.trainer import Trainer
    cfg = replace_config(tiny_config, {"train.eval_every_steps": 0})
    model_dir = tmp_path / "m"
    Trainer(cfg, str(model_dir), [tiny_segment], log_fn=lambda s: None).train(1)
    command = [sys.executable, "tools/eval.py", "--data_dir", os.path.dirname(tiny_segment), "--checkpoint",
               str(model_dir), "--out_dir", str(tmp_path / "eval"), "--max_pairs", "1"]
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert f"config: {model_dir / 'config.yaml'}, the one saved with {model_dir}" in out.stdout
    assert (tmp_path / "eval" / "metrics.json").exists()
    assert (tmp_path / "eval" / "eval_config.yaml").exists() and not (tmp_path / "eval" / "config.yaml").exists()
    # The SavedModel exported from it carries the config too, so a tool given the SavedModel loads the same one.
    saved_model = tmp_path / "sm"
    out = subprocess.run([sys.executable, "tools/export.py", "--checkpoint", str(model_dir), "--out", str(saved_model)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    from ff3d_tf.checkpoints import saved_config
    from ff3d_tf.config import load_config
    assert saved_config(str(saved_model)) == str(saved_model / "config.yaml")
    assert load_config(str(saved_model / "config.yaml")) == load_config(str(model_dir / "config.yaml"))
    # --config wins: the paper's model does not fit these weights, and the error names the model's own config.
    out = subprocess.run(command + ["--config", PAPER], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode != 0 and "in the checkpoint but" in out.stderr, out.stderr[-3000:]
    assert f"its own config is {model_dir / 'config.yaml'}" in out.stderr and "Traceback" not in out.stderr
    assert "saved with" not in out.stdout
