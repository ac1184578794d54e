"""Your own sequences end to end through the tools, on the synthetic default in their layout
(`tools/make_synthetic_data.py --format files`): records labelled from the box table (the synthetic scene's own flow),
20 training steps, evaluation; and without boxes, NSFP pseudo-labels (ZeroFlow's route) into 20 training steps."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, TINY_OVERRIDES, TINY_SCALE
from ff3d_tf.data import pair_records
from ff3d_tf.data.synthetic import files as synthetic_files, wod as synthetic_wod
from ff3d_tf.data.wod import waymo

SWEEPS = 4


def _run(*args):
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def _tiny(*more):
    return ["--config", "", *[a for o in TINY_OVERRIDES + more for a in ("--set", o)]]


def _records(out_dir):
    manifest = pair_records.read_manifest(out_dir)
    files = sorted(os.path.join(out_dir, f) for f in os.listdir(out_dir) if f.endswith(pair_records.FILE_SUFFIX))
    return manifest, [{k: v.numpy() for k, v in ex.items()} for f in files
                      for ex in pair_records.records_dataset(f, manifest, manifest.extras)]


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    """(the synthetic sequences, their labelled records)."""
    tmp_path = tmp_path_factory.mktemp("own_tools")
    seqs, records = tmp_path / "seqs", tmp_path / "records"
    _run("tools/make_synthetic_data.py", "--format", "files", "--out_dir", str(seqs), "--num_segments", "1",
         "--frames_per_segment", str(SWEEPS), "--lidar_scale", str(TINY_SCALE))
    (seq,) = os.listdir(seqs)
    assert sorted(os.listdir(seqs / seq)) == [f"{k:06d}.bin" for k in range(SWEEPS)] + [
        "boxes.csv", "poses.txt", "timestamps.txt"]
    out = _run("tools/write_pair_records.py", "--source", "files", "--input", str(seqs), "--out_dir", str(records),
               *_tiny())
    assert "1 sequences" in out and f"'pairs': {SWEEPS - 1}" in out
    manifest, examples = _records(str(records))
    assert manifest.source == "files" and manifest.human_labels and manifest.extras == ("instance_id_t0",)
    # the labels are the synthetic scene's ground truth (its own kinematics, written in the segment's flow channel)
    spec = synthetic_wod.SegmentSpec(seed=0, num_frames=SWEEPS, name="synthetic-00000", lidar_scale=TINY_SCALE)
    truth = [waymo.decode_frame(r) for r in synthetic_wod.generate_segment(spec)]
    for i, ex in enumerate(examples, start=1):
        np.testing.assert_array_equal(ex["points_xyz_t0"], truth[i]["points_xyz"])
        np.testing.assert_array_equal(ex["class_id_t0"], truth[i]["class_id"])
        assert np.abs(ex["flow_mps_t0"] - truth[i]["flow_mps"]).max() <= 1e-3
    return seqs, records


@pytest.mark.slow
def test_records_from_boxes_training_and_evaluation(labelled, tmp_path):
    _, records = labelled
    model = tmp_path / "model"
    _run("tools/train.py", *_tiny("data.source=pair_records", "train.num_steps=20", "train.eval_every_steps=1000"),
         "--data_dir", str(records), "--model_dir", str(model))
    out = _run("tools/eval.py", *_tiny("data.source=pair_records"), "--data_dir", str(records), "--checkpoint",
               str(model), "--out_dir", str(tmp_path / "eval"))
    assert "zero-flow baseline" in out
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert np.isfinite(metrics["all/all/mean_l2_mps"]) and "within_35m/three_way/mean_epe_m" in metrics
    # NSFP without a model, scored the same way
    out = _run("tools/eval.py", "--method", "nsfp", *_tiny("data.source=pair_records", "nsfp.max_iterations=20",
                                                         "nsfp.segment_iterations=20"),
               "--data_dir", str(records), "--max_pairs", "1", "--out_dir", str(tmp_path / "eval_nsfp"))
    assert "nsfp pair 0:" in out
    metrics = json.loads((tmp_path / "eval_nsfp" / "metrics.json").read_text())
    assert np.isfinite(metrics["all/all/mean_l2_mps"]) and "within_35m/three_way/mean_epe_m" in metrics


@pytest.mark.slow
def test_without_boxes_nsfp_pseudo_labels_train_a_model(labelled, tmp_path):
    """Unlabelled records, NSFP pseudo-labels, a model trained on them, scored on the labelled records."""
    seqs, records = labelled
    (seq,) = os.listdir(seqs)
    bare, raw, pseudo = tmp_path / "bare", tmp_path / "raw", tmp_path / "pseudo"
    synthetic_files.write_synthetic_sequences(str(bare), 1, SWEEPS, 0, TINY_SCALE, with_boxes=False)
    assert "boxes.csv" not in os.listdir(bare / seq)
    refused = subprocess.run([sys.executable, "tools/write_pair_records.py", "--source", "files", "--input", str(bare),
                              "--out_dir", str(raw), *_tiny()], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert refused.returncode != 0 and "--no_labels" in refused.stderr
    _run("tools/write_pair_records.py", "--source", "files", "--input", str(bare), "--out_dir", str(raw), "--no_labels",
         *_tiny())
    nsfp = ("nsfp.max_iterations=20", "nsfp.segment_iterations=20", "nsfp.point_bucket_base=1024")
    _run("tools/pseudo_label.py", "--input", str(raw), "--out_dir", str(pseudo), *_tiny(*nsfp))
    manifest, examples = _records(str(pseudo))
    assert manifest.source == "files" and not manifest.human_labels
    assert all(ex["pseudo_valid_t0"].sum() > 0.2 * len(ex["pseudo_valid_t0"]) for ex in examples)
    _run("tools/train.py", *_tiny("data.source=pair_records", "data.labels=pseudo", "train.num_steps=20",
                                  "train.eval_every_steps=1000"), "--data_dir", str(pseudo), "--model_dir",
         str(tmp_path / "zeroflow"))
    _run("tools/eval.py", *_tiny("data.source=pair_records"), "--data_dir", str(records), "--checkpoint",
         str(tmp_path / "zeroflow"), "--out_dir", str(tmp_path / "eval_zeroflow"))
    assert (tmp_path / "eval_zeroflow" / "metrics.json").exists()
