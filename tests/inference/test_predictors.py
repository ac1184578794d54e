"""One predictor contract (`ff3d_tf.predictor.Predictor`) for every way a model is saved: a checkpoint, its SavedModel,
its ONNX file and its portable XLA export, each loaded by what its path holds (`load_predictor`), give the
checkpoint's flow on the same pairs; tools/eval.py and tools/predict.py take any of them."""
import json
import subprocess
import sys

import numpy as np
import pytest
import tensorflow as tf

from conftest import ROOT, TINY_OVERRIDES
from ff3d_tf.data import pairs
from ff3d_tf.inference.predictor import load_predictor, predictor_kind
from ff3d_tf.model import build_model
from ff3d_tf.predictor import Predictor

pytest.importorskip("jax", reason="the xla extra (pip install .[xla]) provides jax")
pytest.importorskip("onnxruntime", reason="the onnx extra provides onnxruntime")
KINDS = ("checkpoint", "saved_model", "onnx", "xla")


@pytest.fixture(scope="module")
def saved(tiny_config, tiny_segment, tmp_path_factory):
    """({kind: path} of one tiny model saved each way, the segment's pairs as (batch, example))."""
    from ff3d_tf.inference.onnx_export import export_onnx
    from ff3d_tf.inference.saved_model import export_saved_model
    from ff3d_tf.inference.xla_export import export_forward
    tmp = tmp_path_factory.mktemp("saved")
    model = build_model(tiny_config)
    pair_list = list(pairs.padded_singletons(pairs.pair_dataset([tiny_segment], tiny_config),
                                             tiny_config.data.point_bucket_base))
    largest = max(int(batch[k].shape[1]) for batch, _ in pair_list for k in ("point_mask_t0", "point_mask_tm1"))
    paths = {"checkpoint": tf.train.Checkpoint(model=model).save(str(tmp / "model" / "ckpt")),
             "saved_model": export_saved_model(model, str(tmp / "saved_model"), tiny_config.data.point_bucket_base),
             "onnx": export_onnx(model, str(tmp / "model.onnx"))["path"],
             "xla": str(tmp / "xla")}
    export_forward(tiny_config, model, [largest], paths["xla"], log=lambda _: None)
    return paths, pair_list


def test_every_kind_gives_the_checkpoints_flow(saved, tiny_config):
    paths, pair_list = saved
    checkpoint = load_predictor(tiny_config, paths["checkpoint"])
    want = [checkpoint.predict(batch, ex) for batch, ex in pair_list]
    assert len(want) == 3 and all(valid.sum() > 100 for _, valid in want)  # the segment's 3 pairs, mostly valid
    for kind in KINDS:
        assert predictor_kind(paths[kind]) == kind
        predictor = load_predictor(tiny_config, paths[kind])
        assert isinstance(predictor, Predictor), kind
        for (batch, ex), (flow_want, valid_want) in zip(pair_list, want):
            flow, valid = predictor.predict(batch, ex)
            n = int(ex["num_points_t0"])
            assert flow.shape == (n, 3) and valid.shape == (n,) and valid.dtype == bool, kind
            np.testing.assert_array_equal(valid, valid_want, err_msg=kind)
            # float32 rounding of the pillar sums, and (SavedModel, ONNX) of the t-1 cloud moved back to its own frame
            np.testing.assert_allclose(flow, flow_want, rtol=0, atol=1e-4 + 1e-5 * np.abs(flow_want).max(),
                                       err_msg=kind)


def _tool(script, *args):
    sets = [a for s in TINY_OVERRIDES for a in ("--set", s)]
    return subprocess.Popen([sys.executable, script, "--config", "", *sets, *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_eval_and_predict_take_an_onnx_file_and_an_xla_export(saved, tiny_config, tiny_segment, tmp_path):
    paths, pair_list = saved
    runs = [_tool("tools/eval.py", "--data_dir", tiny_segment, "--checkpoint", paths["onnx"], "--out_dir",
                  str(tmp_path / "eval"), "--max_pairs", "2"),
            _tool("tools/predict.py", "--checkpoint", paths["xla"], "--input", tiny_segment, "--out_dir",
                  str(tmp_path / "predict"), "--png_every", "100")]
    for run in runs:
        stdout, stderr = run.communicate(timeout=600)
        assert run.returncode == 0, stderr[-3000:]
    from ff3d_tf.training.evaluation import evaluate
    want, _ = evaluate(tiny_config, [tiny_segment], load_predictor(tiny_config, paths["checkpoint"]), max_pairs=2,
                       log_fn=None)
    got = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert got["all/all/count"] == want["all/all/count"] > 0
    np.testing.assert_allclose(got["all/all/mean_l2_mps"], want["all/all/mean_l2_mps"], rtol=1e-4)
    checkpoint = load_predictor(tiny_config, paths["checkpoint"])
    for i, (batch, ex) in enumerate(pair_list):
        flow_want, valid_want = checkpoint.predict(batch, ex)
        written = np.load(tmp_path / "predict" / f"frame_{i:04d}.npz")
        np.testing.assert_array_equal(written["point_valid"], valid_want)
        np.testing.assert_allclose(written["flow_mps_pred"], flow_want, rtol=0,
                                   atol=1e-4 + 1e-5 * np.abs(flow_want).max())
