"""The tools a user runs with models of several sweeps and with the Argoverse 2 challenge's records, each as a
subprocess: tools/predict.py on an Argoverse 2 log and on a WOD segment with models trained on pair records,
tools/eval.py --protocol av2 (its own config beside its results; one line for records that are not Argoverse 2's),
an ONNX export that carries its config, and tools/av2_submission.py resuming only its own interrupted run."""
import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from conftest import AV2_LOG, ROOT, TINY_OVERRIDES

pytestmark = pytest.mark.slow  # each test runs the tools several times: 20-60 s each

THREE_SWEEPS = ("data.num_frames=3", "model.temporal=delta")


def _tool(*args):
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def _ok(*args):
    run = _tool(*args)
    assert run.returncode == 0, run.stderr[-3000:]
    return run.stdout


def _one_line_error(*args) -> str:
    """The tool's last line of stderr, after checking that it failed without a traceback."""
    run = _tool(*args)
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr[-3000:]
    return run.stderr.strip().splitlines()[-1]


def _model_dir(path, *sets):
    """A model_dir as training leaves it (a checkpoint and its config), of the tiny model with `sets`."""
    import tensorflow as tf
    from ff3d_tf.checkpoints import CONFIG_NAME
    from ff3d_tf.config import load_config
    from ff3d_tf.model import build_model
    cfg = load_config(None, (*TINY_OVERRIDES, *sets))
    model = build_model(cfg, compile_mode="none")
    tf.train.Checkpoint(model=model).save(str(path / "checkpoints" / "ckpt"))
    cfg.save(str(path / CONFIG_NAME))
    return str(path)


def test_predict_on_an_av2_log_in_the_order_of_each_model(tmp_path):
    """Three sweeps of the sample log's two: the model of the previous sweep predicts sweep 1 (sweep 0 in its t-1
    and t-2 slots), the model of the next sweep predicts sweep 0 (sweep 1 in its t-1 slot, sweep 0 in t-2); each
    writes the velocity, and its labels likewise: the log's moving points move the same way in both."""
    previous = _model_dir(tmp_path / "previous", *THREE_SWEEPS)
    nxt = _model_dir(tmp_path / "next", *THREE_SWEEPS, "data.source=pair_records", "data.partner=next")
    mean_velocity = {}
    for model in (previous, nxt):
        out = tmp_path / f"out_{os.path.basename(model)}"
        _ok("tools/predict.py", "--checkpoint", model, "--av2_log", AV2_LOG, "--out_dir", str(out))
        assert sorted(p.name for p in out.glob("*.npz")) == ["frame_0000.npz"]  # the log's one pair
        with np.load(out / "frame_0000.npz") as z:
            assert z["flow_mps_pred"].shape == z["points_xyz_t0"].shape
            moving = np.linalg.norm(z["flow_mps_true"], axis=1) > 1.0  # labelled by the log's cuboids
            assert moving.sum() > 100
            mean_velocity[model] = z["flow_mps_true"][moving].mean(0)
    cosine = mean_velocity[previous] @ mean_velocity[nxt] / np.prod([np.linalg.norm(v) for v in
                                                                      mean_velocity.values()])
    assert cosine > 0.9, mean_velocity  # not minus the velocity from the next sweep's side


def test_predict_a_wod_segment_with_a_model_of_pair_records(tiny_segment, tmp_path):
    """A model trained on pair records (its config's data.source) reads a WOD segment's frames."""
    model = _model_dir(tmp_path / "m", "data.source=pair_records")
    out = _ok("tools/predict.py", "--checkpoint", model, "--input", tiny_segment, "--out_dir", str(tmp_path / "o"))
    assert "wrote 3 frames" in out


def test_eval_av2_protocol(av2_sample_records, tiny_segment, tiny_config, tmp_path):
    """--protocol av2 writes its config beside its results; WOD records get one line of the tool's own."""
    from ff3d_tf.data import pair_records
    from ff3d_tf.data.wod import write_records
    model = _model_dir(tmp_path / "m")
    records = ["--set", "data.source=pair_records"]
    _ok("tools/eval.py", "--protocol", "av2", "--checkpoint", model, *records, "--data_dir", av2_sample_records,
        "--out_dir", str(tmp_path / "eval"))
    assert sorted(os.listdir(tmp_path / "eval")) == ["eval_config.yaml", "metrics_av2.json"]
    wod = str(tmp_path / "wod_records")
    manifest = write_records.wod_manifest(tiny_config)
    pair_records.write_manifest(wod, manifest)
    write_records.write_segment(tiny_segment, wod, tiny_config, manifest)
    line = _one_line_error("tools/eval.py", "--protocol", "av2", "--checkpoint", model, *records, "--data_dir", wod)
    assert line == (f"error: {wod}: records of wod paired with the previous sweep; the Argoverse 2 protocol needs "
                    "Argoverse 2 records paired with the next sweep (tools/write_pair_records.py --source av2)")


def test_an_onnx_export_carries_its_config(tmp_path):
    """tools/export_onnx.py writes the config into the file; tools/predict.py given the file and no --config or --set
    loads it (its three sweeps) and says so."""
    model = _model_dir(tmp_path / "m", *THREE_SWEEPS)
    onnx = str(tmp_path / "m.onnx")
    _ok("tools/export_onnx.py", "--checkpoint", model, "--out", onnx, "--variant", "single_chunk")
    rng = np.random.default_rng(0)
    for k in range(3):
        (tmp_path / "sweeps").mkdir(exist_ok=True)
        np.save(tmp_path / "sweeps" / f"{k:06d}.npy", rng.uniform([-30, -30, -1], [30, 30, 2], (90, 3)))
    out = _ok("tools/predict.py", "--checkpoint", onnx, "--sweeps_dir", str(tmp_path / "sweeps"), "--out_dir",
              str(tmp_path / "o"))
    assert f"config: the metadata of {onnx}, the one saved with {onnx}" in out
    assert "3 sweeps, 2 examples of 3 sweeps" in out


def test_av2_submission_resumes_only_its_own_run(av2_sample_records, tmp_path):
    """A run interrupted after its sweeps were written (here: its archive refused by a format JSON) leaves them with
    its fingerprint; a run of another model into the same --out refuses them, naming what differs; the same run
    resumes them and removes the folder; then another model's run writes its own flows."""
    model = _model_dir(tmp_path / "m")
    out = str(tmp_path / "submission.zip")
    common = ("tools/av2_submission.py", "--leaderboard", "v1", "--split", "val", "--data_dir", av2_sample_records,
              "--out", out, "--config", "", *[a for o in TINY_OVERRIDES for a in ("--set", o)])
    entry = f"{os.path.basename(AV2_LOG)}/{sorted(os.listdir(os.path.join(AV2_LOG, 'sensors', 'lidar')))[0]}"
    bad_format = tmp_path / "format.json"
    bad_format.write_text(json.dumps({entry: 1}))
    assert "rows" in _one_line_error(*common, "--ground_truth", "--format_json", str(bad_format))
    assert os.path.isfile(os.path.join(out + ".parts", "fingerprint.json"))
    line = _one_line_error(*common, "--checkpoint", model)
    assert line.startswith(f"error: {out}.parts/fingerprint.json: fingerprint: the sweeps here were written by "
                           "another run (model.kind: \"ground_truth\" there, \"checkpoint\" here"), line
    assert line.endswith(f"remove {out}.parts to write them again, or give another --out"), line
    assert "1 already written" in _ok(*common, "--ground_truth")
    assert not os.path.exists(out + ".parts")
    with zipfile.ZipFile(out) as zf:
        labels = zf.read(entry)
    _ok(*common, "--checkpoint", model)
    with zipfile.ZipFile(out) as zf:
        assert zf.read(entry) != labels  # the model's flows, not the labels an earlier run left
