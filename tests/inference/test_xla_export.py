"""Portable XLA export of the forward: the artifacts, run by JAX where TensorFlow cannot be imported, give TF's
forward. (The training step's artifacts and the runner tool: tests/training/test_xla_step.py.)"""
import json
import os

import numpy as np
import pytest

jax = pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")

import tensorflow as tf  # noqa: E402

from conftest import ROOT, tiny_model_off_initial_values  # noqa: E402
from no_tensorflow import run_without_tf  # noqa: E402
from ff3d_tf import xla_export_dir  # noqa: E402
from ff3d_tf.inference import xla_artifact  # noqa: E402
from ff3d_tf.inference.xla_export import export_forward  # noqa: E402
from ff3d_tf.model import build_model  # noqa: E402
from ff3d_tf.schema import MODEL_INPUT_KEYS  # noqa: E402

POINTS = (700, 1500)  # tiny config buckets (base 1024): 1024 and 1536

# The JAX side of the comparison: reads the export and the saved inputs, writes the artifact's outputs.
RUN_ON_INPUTS = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from ff3d_tf import xla_export_dir
from ff3d_tf.inference import xla_artifact
export_dir, inputs_path, outputs_path = sys.argv[2:5]
manifest = xla_export_dir.read_manifest(export_dir)
weights = xla_export_dir.load_weights(export_dir, manifest)
saved = np.load(inputs_path)
outputs = {}
for i, entry in enumerate(manifest["artifacts"]):
    exported = xla_artifact.load_forward(export_dir, entry, len(weights))
    assert exported.platforms == ("cpu", "cuda"), exported.platforms
    out = xla_artifact.CompiledForward(exported, weights).numpy([saved[f"{i}_{k}"] for k in manifest["input_keys"]])
    outputs.update({f"{i}_{k}": v for k, v in out.items()})
assert "tensorflow" not in sys.modules or sys.modules["tensorflow"] is None
np.savez(outputs_path, **outputs)
"""


@pytest.fixture(scope="module")
def exported_tiny(tiny_config, tmp_path_factory):
    """A tiny model (`tiny_model_off_initial_values`), exported."""
    model = tiny_model_off_initial_values(tiny_config)
    out_dir = str(tmp_path_factory.mktemp("xla"))
    manifest = export_forward(tiny_config, model, POINTS, out_dir, precisions=("float32", "tf32"), log=lambda _: None)
    return model, out_dir, manifest


def test_artifacts_equal_tf_forward_without_tensorflow(exported_tiny, tmp_path):
    model, out_dir, manifest = exported_tiny
    assert [(e["points"], e["padded_points"], e["precision"]) for e in manifest["artifacts"]] == [
        (700, 1024, "float32"), (1500, 1536, "float32"), (700, 1024, "tf32"), (1500, 1536, "tf32")]
    # One bucket (the runner test below compiles the other): a JAX compile costs seconds on a busy CPU.
    float32 = [e for e in manifest["artifacts"] if e["precision"] == "float32" and e["points"] == 1500]
    export_dir = tmp_path / "float32_only"
    export_dir.mkdir()
    for name in (xla_export_dir.WEIGHTS_NAME, *(e["file"] for e in float32)):
        os.symlink(os.path.join(out_dir, name), export_dir / name)
    (export_dir / xla_export_dir.MANIFEST_NAME).write_text(json.dumps({**manifest, "artifacts": float32}))
    rng = np.random.default_rng(0)
    forward = tf.function(lambda x: model(x, training=False, inline_stages=True), jit_compile=True)
    inputs, reference = {}, {}
    for i, entry in enumerate(float32):
        arrays = xla_export_dir.random_inputs(manifest, entry, rng)
        inputs.update({f"{i}_{k}": a for k, a in zip(MODEL_INPUT_KEYS, arrays)})
        reference[i] = forward(dict(zip(MODEL_INPUT_KEYS, arrays)))
    np.savez(tmp_path / "inputs.npz", **inputs)
    script = tmp_path / "run_on_inputs.py"
    script.write_text(RUN_ON_INPUTS)
    run_without_tf(str(script), ROOT, str(export_dir), str(tmp_path / "inputs.npz"), str(tmp_path / "outputs.npz"))
    got = np.load(tmp_path / "outputs.npz")
    for i, entry in enumerate(float32):
        flow_ref = reference[i]["flow_mps"].numpy()
        valid_ref = reference[i]["point_valid"].numpy()
        # The random clouds cover the grid: every real point is valid, every padding point is not.
        assert valid_ref.sum() == entry["points"] and not valid_ref[0, entry["points"]:].any()
        assert np.abs(flow_ref).max() > 0.1  # random weights: a real (non-zero) flow to compare
        np.testing.assert_array_equal(got[f"{i}_point_valid"], valid_ref)
        np.testing.assert_allclose(got[f"{i}_flow_mps"], flow_ref, rtol=0, atol=1e-4)


@pytest.mark.slow
def test_paper_config_artifact_equals_tf_forward_without_tensorflow(tmp_path):
    """The full-size model (512 x 512 grid, the point loop over chunks) at its smallest bucket, 12,000 points."""
    from ff3d_tf.config import load_config
    cfg = load_config(os.path.join(ROOT, "configs", "fastflow3d_waymo.yaml"))
    model = build_model(cfg)
    manifest = export_forward(cfg, model, [12000], str(tmp_path / "export"), log=lambda _: None)
    (entry,) = manifest["artifacts"]
    arrays = xla_export_dir.random_inputs(manifest, entry, np.random.default_rng(1))
    forward = tf.function(lambda x: model(x, training=False, inline_stages=True), jit_compile=True)
    reference = forward(dict(zip(MODEL_INPUT_KEYS, arrays)))
    np.savez(tmp_path / "inputs.npz", **{f"0_{k}": a for k, a in zip(MODEL_INPUT_KEYS, arrays)})
    script = tmp_path / "run_on_inputs.py"
    script.write_text(RUN_ON_INPUTS)
    run_without_tf(str(script), ROOT, str(tmp_path / "export"), str(tmp_path / "inputs.npz"),
                    str(tmp_path / "outputs.npz"))
    got = np.load(tmp_path / "outputs.npz")
    assert reference["point_valid"].numpy().sum() == 12000
    np.testing.assert_array_equal(got["0_point_valid"], reference["point_valid"].numpy())
    np.testing.assert_allclose(got["0_flow_mps"], reference["flow_mps"].numpy(), rtol=0, atol=1e-4)


def test_precision_is_written_into_the_program(exported_tiny):
    """TF32 off -> convolutions at HIGHEST precision (float32-exact on GPUs); the tf32 artifact leaves them at the
    default precision (not printed)."""
    from jax import export
    _, out_dir, manifest = exported_tiny
    assert manifest["train_artifacts"] == []
    for entry in manifest["artifacts"]:
        with open(os.path.join(out_dir, entry["file"]), "rb") as f:
            text = export.deserialize(bytearray(f.read())).mlir_module()
        assert "stablehlo.convolution" in text
        assert ("precision HIGHEST" in text) == (entry["precision"] == "float32")


def test_bad_exports_are_named(exported_tiny, tmp_path):
    _, out_dir, manifest = exported_tiny
    (tmp_path / xla_export_dir.MANIFEST_NAME).write_text(json.dumps({**manifest, "format": "other/9"}))
    with pytest.raises(xla_export_dir.ExportFormatError, match="manifest.json: field format"):
        xla_export_dir.read_manifest(str(tmp_path))
    wrong = [dict(w) for w in manifest["weights"]]
    wrong[1]["shape"] = [w + 1 for w in wrong[1]["shape"]]
    with pytest.raises(xla_export_dir.ExportFormatError, match=r"weights.npz: array w001 \(.*\) is float32"):
        xla_export_dir.load_weights(out_dir, {**manifest, "weights": wrong})
    with pytest.raises(ValueError, match="precision 'fp8' unknown"):
        export_forward(None, None, [10], str(tmp_path / "x"), precisions=("fp8",))


def test_predictor_runs_a_pair_on_the_smallest_artifact_that_holds_it(exported_tiny, tiny_config):
    """`XlaPredictor` (the `ff3d_tf.predictor.Predictor` of an export): a pair padded to 800 points runs on the 1024
    artifact (224 more masked points change no flow); one of 1600 fits no artifact (1024, 1536) and is named."""
    from ff3d_tf.predictor import Predictor
    model, out_dir, _ = exported_tiny
    predictor = xla_artifact.XlaPredictor(out_dir)
    assert isinstance(predictor, Predictor)
    g = tiny_config.grid
    bounds = (g.x_range_m, g.y_range_m, g.z_range_m)
    rng = np.random.default_rng(5)
    batch = {k: tf.constant(v) for k, v in xla_export_dir.random_clouds(rng, 600, 800, bounds).items()}
    flow, valid = predictor.predict(batch, {"num_points_t0": 600})
    want = model(batch, training=False)
    assert flow.shape == (600, 3) and valid.shape == (600,) and valid.all()
    np.testing.assert_array_equal(valid, want["point_valid"].numpy()[0, :600])
    np.testing.assert_allclose(flow, want["flow_mps"].numpy()[0, :600], rtol=0, atol=1e-4)
    assert list(predictor._compiled) == [xla_artifact.artifact_name(1024, "float32")]
    big = xla_export_dir.random_clouds(rng, 1600, 1600, bounds)
    with pytest.raises(ValueError, match="a pair padded to 1600 points is larger than every artifact"):
        predictor.predict(big, {"num_points_t0": 1600})
