"""Argoverse 2 end to end through the tools, on the real sample log: pair records, the challenge protocol in
tools/eval.py, and a submission archive read back."""
import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import pyarrow.feather as feather

from conftest import AV2_LOG, ROOT, TINY_OVERRIDES
from ff3d_tf import metrics_av2
from ff3d_tf.data.av2 import argoverse2, av2_submission


def _run(*args):
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def _tiny():
    return [a for o in TINY_OVERRIDES for a in ("--set", o)]


def test_records_and_a_ground_truth_submission_of_the_sample_log(tmp_path):
    records = tmp_path / "records"
    out = _run("tools/write_pair_records.py", "--source", "av2", "--input", AV2_LOG, "--out_dir", str(records),
               *_tiny())
    assert "1 logs" in out and "'pairs': 1" in out
    zip_path = tmp_path / "submission.zip"
    out = _run("tools/av2_submission.py", "--ground_truth", "--data_dir", str(records), "--out", str(zip_path),
               *_tiny())
    assert "checked against the submission format" in out
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    log_id = os.path.basename(AV2_LOG)
    with zipfile.ZipFile(zip_path) as zf:
        assert zf.namelist() == [f"{log_id}/{stamps[0]}.feather"]  # the last sweep has no next sweep
        table = feather.read_table(zf.open(zf.namelist()[0]))
    assert table.schema.names == ["flow_tx_m", "flow_ty_m", "flow_tz_m", "is_dynamic"]
    assert [str(t) for t in table.schema.types] == ["halffloat"] * 3 + ["bool"]
    # One row per eval-mask point (not ground by the log's raster, max(|x|, |y|) < 35 m), in point order.
    labels = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    sweep = argoverse2.read_sweep(AV2_LOG, stamps[0])
    mask = metrics_av2.eval_mask(sweep["points_xyz"], argoverse2.is_ground(AV2_LOG, sweep["points_xyz"],
                                                                           sweep["pose"]))
    assert table.num_rows == int(mask.sum()) > 50_000
    # The submission's flow (ego motion included) against Argoverse's own labels: float16 and labelling tolerance.
    got = av2_submission.read_sweep(str(zip_path), log_id, stamps[0])
    want = np.stack([labels.column(c).to_numpy() for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m")], -1)[mask]
    close = np.linalg.norm(got["flow_m_av2"].astype(np.float64) - want, axis=1) < 0.02
    assert np.mean(close) > 0.99, np.mean(close)
    np.testing.assert_array_equal(got["is_dynamic"][close], labels.column("dynamic").to_numpy()[mask][close])


def test_eval_protocol_av2_with_a_checkpoint(tiny_segment, tmp_path):
    records = tmp_path / "records"
    _run("tools/write_pair_records.py", "--source", "av2", "--input", AV2_LOG, "--out_dir", str(records), *_tiny())
    model_dir = tmp_path / "model"
    _run("tools/train.py", "--config", "configs/synthetic_cpu.yaml", *_tiny(), "--set", "train.num_steps=1",
         "--data_dir", os.path.dirname(tiny_segment), "--model_dir", str(model_dir))
    out = _run("tools/eval.py", "--protocol", "av2", "--config", "configs/synthetic_cpu.yaml", *_tiny(),
               "--set", "data.source=pair_records", "--data_dir", str(records), "--checkpoint", str(model_dir),
               "--out_dir", str(tmp_path / "eval"))
    assert "Argoverse 2 scene flow (2024 protocol)" in out and "zero flow" in out
    result = json.loads((tmp_path / "eval" / "metrics_av2.json").read_text())
    assert result["zero_flow"]["three_way/fg_dynamic_epe_m"] > 0.3
    assert result["model"]["num_points"] == result["zero_flow"]["num_points"] > 50_000


@pytest.mark.slow
def test_a_short_training_on_synthetic_av2_logs_beats_zero_flow(tmp_path):
    """tools/make_synthetic_data.py --format av2 -> write_pair_records -> train.py -> eval.py --protocol av2."""
    cpu = ["--config", "configs/synthetic_cpu.yaml", "--set", "data.point_bucket_base=8192"]
    for split, logs, seed in (("train", "3", "0"), ("val", "1", "7")):
        _run("tools/make_synthetic_data.py", "--format", "av2", "--out_dir", str(tmp_path / "logs"), "--num_logs",
             logs, "--sweeps_per_log", "8", "--split", split, "--seed", seed)
        _run("tools/write_pair_records.py", "--source", "av2", "--input", str(tmp_path / "logs" / split),
             "--out_dir", str(tmp_path / split), *cpu)
    records = ["--set", "data.source=pair_records"]
    _run("tools/train.py", *cpu, *records, "--set", "train.num_steps=200", "--set", "train.eval_every_steps=1000",
         "--data_dir", str(tmp_path / "train"), "--model_dir", str(tmp_path / "model"))
    _run("tools/eval.py", "--protocol", "av2", *cpu, *records, "--data_dir", str(tmp_path / "val"),
         "--checkpoint", str(tmp_path / "model"), "--out_dir", str(tmp_path / "eval"))
    r = json.loads((tmp_path / "eval" / "metrics_av2.json").read_text())
    assert r["model"]["three_way/fg_dynamic_epe_m"] < 0.9 * r["zero_flow"]["three_way/fg_dynamic_epe_m"]
    assert r["paper_model"]["vehicle/moving/mean_l2_mps"] < 0.9 * r["paper_zero_flow"]["vehicle/moving/mean_l2_mps"]
