"""The training step as portable XLA programs: added to a forward export, run by JAX it trains as TensorFlow's Keras
Adam does; lab/tools/run_xla.py times forward and training step where TensorFlow cannot be imported."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

jax = pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")

import tensorflow as tf  # noqa: E402

from conftest import ROOT, tiny_model_off_initial_values  # noqa: E402
from no_tensorflow import run_without_tf  # noqa: E402
from ff3d_tf import xla_export_dir  # noqa: E402
from ff3d_tf.inference.xla_export import export_forward  # noqa: E402
from ff3d_tf.model import build_model  # noqa: E402
from ff3d_tf.model.losses import batch_flow_loss  # noqa: E402
from ff3d_tf.model.step import make_optimizer  # noqa: E402
from ff3d_tf.schema import MODEL_INPUT_KEYS  # noqa: E402
from ff3d_tf.training import xla_step_runner  # noqa: E402
from ff3d_tf.training.xla_step_export import export_train_steps  # noqa: E402
from ff3d_tf.xla_export_dir import model_weights  # noqa: E402

POINTS = (700,)  # the forward: one tiny-config bucket (base 1024)
TRAIN_POINTS, TRAIN_BATCH = (900,), 2  # one training-step artifact: 2 x 1024 points


@pytest.fixture(scope="module")
def exported_tiny(tiny_config, tmp_path_factory):
    """A tiny model (`tiny_model_off_initial_values`), its forward exported and its training step added, both with
    TensorFlow's reference."""
    model = tiny_model_off_initial_values(tiny_config)
    out_dir = str(tmp_path_factory.mktemp("xla"))
    export_forward(tiny_config, model, POINTS, out_dir, log=lambda _: None, reference=True)
    manifest = export_train_steps(tiny_config, model, out_dir, TRAIN_POINTS, (TRAIN_BATCH,), log=lambda _: None,
                                  reference=True)
    return model, out_dir, manifest


def test_runner_without_tensorflow_writes_latency_json(exported_tiny, tmp_path):
    _, out_dir, manifest = exported_tiny
    assert manifest == json.load(open(os.path.join(out_dir, xla_export_dir.MANIFEST_NAME)))
    out_json = tmp_path / "latency.json"
    stdout = run_without_tf(os.path.join(ROOT, "lab", "tools", "run_xla.py"), out_dir, "--runs", "2", "--warmup", "1",
                            "--points", f"700,{TRAIN_POINTS[0]}", "--precisions", "float32", "--out", str(out_json))
    result = json.loads(out_json.read_text())
    assert result["platform"] == "cpu" and result["num_weights"] == len(manifest["weights"])
    rows = {(r["points"], r["precision"]): r for r in result["latency"]}
    assert sorted(rows) == [(700, "float32")]
    for r in rows.values():
        assert r["runs"] == 2 and 0 < r["min_ms"] <= min(r["median_ms"], r["mean_ms"]) and r["median_host_ms"] > 0
    assert "paper P100 ms" in stdout and "| 700 | float32 |" in stdout
    # The reference: TensorFlow's results at export time, here recomputed by the runner without TensorFlow.
    assert rows[(700, "float32")]["reference"]["max_abs_flow_diff_mps"] < 1e-4
    assert rows[(700, "float32")]["reference"]["valid_mismatches"] == 0
    (train,) = result["train_step"]
    assert (train["batch_size"], train["points"], train["runs"]) == (TRAIN_BATCH, TRAIN_POINTS[0], 2)
    assert train["ms_per_pair"] == pytest.approx(train["median_ms"] / TRAIN_BATCH)
    assert train["reference"]["loss_rel_diff"] < 1e-4 and train["reference"]["grad_norm_rel_diff"] < 1e-3
    assert f"| {TRAIN_BATCH} x {TRAIN_POINTS[0]} | float32 |" in stdout
    assert "- forward 700 points float32: max_abs_flow_diff_mps" in stdout
    assert f"- train step {TRAIN_BATCH} x {TRAIN_POINTS[0]} float32: loss_rel_diff" in stdout


def test_train_step_equals_keras_adam_training(exported_tiny, tiny_config):
    """Two exported training steps (JAX) against two steps of the model trained by TensorFlow with the Trainer's loss
    and optimizer (Keras' Adam): loss, weights, Adam-updated weights and BatchNorm statistics agree."""
    model, out_dir, manifest = exported_tiny
    (entry,) = manifest["train_artifacts"]
    assert (entry["batch_size"], entry["padded_points"], entry["precision"]) == (TRAIN_BATCH, 1024, "float32")
    weights = xla_export_dir.load_weights(out_dir, manifest)
    step = xla_step_runner.CompiledTrainStep(xla_step_runner.load_train_step(out_dir, entry, manifest),
                                             xla_step_runner.initial_train_state(weights, manifest))
    rng = np.random.default_rng(4)
    batch = xla_export_dir.random_inputs(manifest, entry, rng) + xla_step_runner.random_labels(entry, manifest, rng)
    jax_losses = [float(step(step.on_device(batch))[0]) for _ in range(2)]

    reference = build_model(tiny_config)
    reference.set_weights(model.get_weights())
    optimizer = make_optimizer(tiny_config)
    tf_batch = dict(zip(MODEL_INPUT_KEYS + xla_step_runner.TRAIN_LABEL_KEYS, batch))
    tf_losses = []
    for _ in range(2):
        with tf.GradientTape() as tape:
            out = reference({k: tf_batch[k] for k in MODEL_INPUT_KEYS}, training=True)
            loss = batch_flow_loss(tf_batch, out, tiny_config.train.background_weight, TRAIN_BATCH)
        optimizer.apply_gradients(zip(tape.gradient(loss, reference.trainable_variables),
                                      reference.trainable_variables))
        tf_losses.append(float(loss))
    np.testing.assert_allclose(jax_losses, tf_losses, rtol=1e-5)
    assert jax_losses[1] < jax_losses[0]  # lr 1e-3: the second step already sees a lower loss
    num_weights = len(model_weights(model))
    got = [np.asarray(x) for x in step.state[:num_weights]]
    for var, value in zip(model_weights(reference), got):
        # Adam moves each weight by about lr = 1e-3 per step, lr * g / (|g| + eps) in the first: a wrong update (sign,
        # bias correction, epsilon) is off by ~1e-3 in most elements. Where an element's gradient is near 0 its
        # rounding (another summation order) moves that quotient by up to lr, so a rare element may be off by more
        # than rounding (CI saw 1.2e-5 in 1 of 10,368): every element within a quarter of one step's move, and
        # all but 0.1% of them within 1e-5 + 1e-6 x |value| (BatchNorm statistics, up to ~12 here: float32 rounding).
        want = var.numpy()
        off = np.abs(value - want)
        assert off.max() < 2.5e-4, (var.path, off.max())
        assert np.mean(off > 1e-5 + 1e-6 * np.abs(want)) <= 1e-3, (var.path, np.sort(off.ravel())[-5:])
    moved = [np.abs(v - b).max() for v, b in zip(got, weights)]
    assert max(moved) > 1e-3
    assert int(np.asarray(step.state[-1])) == 2  # iterations


def test_precision_is_written_into_the_program(exported_tiny):
    """TF32 off (float32) -> convolutions at HIGHEST precision (float32-exact on GPUs)."""
    from jax import export
    _, out_dir, manifest = exported_tiny
    for entry in manifest["train_artifacts"]:
        with open(os.path.join(out_dir, entry["file"]), "rb") as f:
            text = export.deserialize(bytearray(f.read())).mlir_module()
        assert "stablehlo.convolution" in text
        assert ("precision HIGHEST" in text) == (entry["precision"] == "float32")


def test_training_steps_are_added_to_an_export_of_the_same_model(exported_tiny, tiny_config, tmp_path):
    _, out_dir, _ = exported_tiny
    from ff3d_tf.config import replace_config
    other = build_model(replace_config(tiny_config, {"model.head_hidden_dim": 4}))
    with pytest.raises(ValueError, match="the model's weights differ from the export's"):
        export_train_steps(tiny_config, other, out_dir, TRAIN_POINTS, log=lambda _: None)
    with pytest.raises(xla_export_dir.ExportFormatError, match="no manifest"):
        export_train_steps(tiny_config, other, str(tmp_path), TRAIN_POINTS, log=lambda _: None)
    with pytest.raises(ValueError, match="precision 'fp8' unknown"):
        export_train_steps(None, None, str(tmp_path), TRAIN_POINTS, precisions=("fp8",))


def test_step_runner_imports_no_tensorflow():
    script = ("import sys\nfor name in ('tensorflow', 'keras', 'jax'):\n    sys.modules[name] = None\n"
              f"sys.path.insert(0, {ROOT!r})\nimport ff3d_tf.training.xla_step_runner, ff3d_tf.xla_export_dir\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]


@pytest.mark.slow  # two exports and their JAX compiles: ~100 s on 2 busy cores
def test_gru_head_forward_and_training_step_without_tensorflow(tiny_config, tmp_path):
    """The model with DeFlow's GRU head (`model.head=gru`; its own gradient under the chunk loop) exported as the
    forward and the training step, run by lab/tools/run_xla.py without TensorFlow: both within TensorFlow's
    reference."""
    from ff3d_tf.config import replace_config
    cfg = replace_config(tiny_config, {"model.head": "gru"})
    model = tiny_model_off_initial_values(cfg)
    out_dir = str(tmp_path / "export")
    export_forward(cfg, model, POINTS, out_dir, log=lambda _: None, reference=True)
    manifest = export_train_steps(cfg, model, out_dir, TRAIN_POINTS, (TRAIN_BATCH,), log=lambda _: None,
                                  reference=True)
    assert any("gru/update_gate" in w["path"] for w in manifest["weights"])
    out_json = tmp_path / "latency.json"
    run_without_tf(os.path.join(ROOT, "lab", "tools", "run_xla.py"), out_dir, "--runs", "1", "--warmup", "0",
                   "--precisions", "float32", "--out", str(out_json))
    result = json.loads(out_json.read_text())
    (forward,) = result["latency"]
    assert forward["reference"]["max_abs_flow_diff_mps"] < 1e-4 and forward["reference"]["valid_mismatches"] == 0
    (train,) = result["train_step"]
    assert train["reference"]["loss_rel_diff"] < 1e-4 and train["reference"]["grad_norm_rel_diff"] < 1e-3


@pytest.mark.parametrize("loss,num_frames,temporal", [
    ("seflow", 2, "pair"),
    pytest.param("teflow", 3, "delta", marks=pytest.mark.slow)])  # a second step export: ~1 min more
def test_self_supervised_step_takes_its_fields_and_equals_tensorflow(tiny_config, tmp_path, loss, num_frames,
                                                                     temporal):
    """A self-supervised loss's step exported: its labels are the fields the loss needs (`config.LOSS_SPECS`, one
    per cloud for TeFlow), named in the manifest, and the JAX step's loss on a batch equals TensorFlow's eager loss of
    the same model on it (the export's own reference is checked too)."""
    from ff3d_tf.config import replace_config
    from ff3d_tf.model.losses import LossContext
    cfg = replace_config(tiny_config, {"data.source": "pair_records", "data.labels": "self", "train.loss": loss,
                                       "data.num_frames": num_frames, "model.temporal": temporal})
    model = tiny_model_off_initial_values(cfg)
    out_dir = str(tmp_path / "xla")
    export_forward(cfg, model, POINTS, out_dir, log=lambda _: None)
    manifest = export_train_steps(cfg, model, out_dir, TRAIN_POINTS, (TRAIN_BATCH,), log=lambda _: None,
                                  reference=True)
    clouds = ("t0", "tm1", "tm2")[:num_frames] if loss == "teflow" else ("t0", "tm1")
    assert manifest["train_label_keys"] == ["flow_mps_t0", "class_id_t0", *(f"dynamic_cluster_{c}" for c in clouds)]
    (entry,) = manifest["train_artifacts"]
    weights = xla_export_dir.load_weights(out_dir, manifest)
    step = xla_step_runner.CompiledTrainStep(xla_step_runner.load_train_step(out_dir, entry, manifest),
                                             xla_step_runner.initial_train_state(weights, manifest))
    check = xla_step_runner.check_train_step(step, entry, manifest, xla_export_dir.load_reference(out_dir))
    assert check["loss_rel_diff"] < 1e-5 and check["grad_norm_rel_diff"] < 1e-3, check
    step = xla_step_runner.CompiledTrainStep(xla_step_runner.load_train_step(out_dir, entry, manifest),
                                             xla_step_runner.initial_train_state(weights, manifest))
    rng = np.random.default_rng(7)
    batch = xla_export_dir.random_inputs(manifest, entry, rng) + xla_step_runner.random_labels(entry, manifest, rng)
    jax_loss = float(step(step.on_device(batch))[0])
    tf_batch = dict(zip((*manifest["input_keys"], *manifest["train_label_keys"]), batch))
    inputs = {k: tf_batch[k] for k in manifest["input_keys"]}
    tf_loss = float(batch_flow_loss(tf_batch, model(inputs, training=True), cfg.train.background_weight,
                                    TRAIN_BATCH, loss=loss, context=LossContext.of(cfg)))
    assert tf_loss > 0
    np.testing.assert_allclose(jax_loss, tf_loss, rtol=1e-5)
