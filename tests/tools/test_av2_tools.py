"""Argoverse 2 end to end through the tools, on the real sample log: pair records, submission archives by av2-api's
rule and over a mask archive in the official layout (read back), and the challenge protocol in tools/eval.py over the
same masks."""
import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import pyarrow as pa
import pyarrow.feather as feather

from conftest import AV2_LOG, ROOT, TINY_OVERRIDES
from ff3d_tf.data.av2 import argoverse2

LOG_ID = os.path.basename(AV2_LOG)  # the records' sequence id: the log directory's name
FLOW = ["flow_tx_m", "flow_ty_m", "flow_tz_m"]


def _run(*args):
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout, out.stderr


def _tiny():
    return [a for o in TINY_OVERRIDES for a in ("--set", o)]


@pytest.fixture(scope="module")
def sample_records(tmp_path_factory):
    records = tmp_path_factory.mktemp("av2_tools") / "records"
    out, _ = _run("tools/write_pair_records.py", "--source", "av2", "--input", AV2_LOG, "--out_dir", str(records),
                  *_tiny())
    assert "1 logs" in out and "'pairs': 1" in out
    return records


@pytest.fixture(scope="module")
def sample_masks(tmp_path_factory):
    """A mask archive in the official layout for the sample's first sweep: av2-api's rule (|x|, |y| <= 50 m, not
    ground) on Argoverse's own ground labels, with its format JSON."""
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    p = argoverse2.read_sweep(AV2_LOG, stamps[0])["points_xyz"]
    labels = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    mask = (np.abs(p[:, 0]) <= 50) & (np.abs(p[:, 1]) <= 50) & ~labels.column("is_ground_0").to_numpy(
        zero_copy_only=False)
    folder = tmp_path_factory.mktemp("av2_masks")
    sink = pa.BufferOutputStream()
    feather.write_feather(pa.table({"mask": pa.array(mask)}), sink)
    entry = f"{LOG_ID}/{stamps[0]}.feather"
    with zipfile.ZipFile(folder / "val-masks.zip", "w") as zf:
        zf.writestr(f"{LOG_ID}/", b"")
        zf.writestr(entry, sink.getvalue().to_pybytes())
    (folder / "val_submission_format.json").write_text(json.dumps({entry: int(mask.sum())}))
    return str(folder / "val-masks.zip"), str(folder / "val_submission_format.json"), mask, labels


def test_a_test_split_without_masks_ends_with_the_message(sample_records, tmp_path):
    """The tool's own error, not a traceback: the error classes it catches are imported only after the failure
    (TensorFlow must not be imported before `start`)."""
    out = subprocess.run([sys.executable, "tools/av2_submission.py", "--ground_truth", "--leaderboard", "v2",
                          "--split", "test", "--data_dir", str(sample_records), "--out", str(tmp_path / "x.zip"),
                          *_tiny()], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr[-3000:]
    assert out.stderr.strip().splitlines()[-1].startswith("error: a test submission needs the official masks")


def test_v1_submissions_of_the_sample_log(sample_records, sample_masks, tmp_path):
    masks, format_json, mask, labels = sample_masks
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    entry = f"{LOG_ID}/{stamps[0]}.feather"
    # Without masks: av2-api's rule on the records' ground (the log's raster), with a loud note.
    out, err = _run("tools/av2_submission.py", "--ground_truth", "--leaderboard", "v1", "--split", "val",
                    "--data_dir", str(sample_records), "--out", str(tmp_path / "rule.zip"), *_tiny())
    assert "NOTE: no --masks" in err and "local validation only" in out
    with zipfile.ZipFile(tmp_path / "rule.zip") as zf:
        assert zf.namelist() == [entry]  # the last sweep has no next sweep
        assert feather.read_table(zf.open(entry)).num_rows == 78507  # one point more ground in the labels
    # Over the official masks and av2-api's format JSON: their rows, in point order.
    zip_path = tmp_path / "submission.zip"
    out, _ = _run("tools/av2_submission.py", "--ground_truth", "--leaderboard", "v1", "--split", "val", "--masks",
                  masks, "--format_json", format_json, "--data_dir", str(sample_records), "--out", str(zip_path),
                  *_tiny())
    assert "checked against the layout and " + format_json in out
    with zipfile.ZipFile(zip_path) as zf:
        assert zf.namelist() == [entry]
        table = feather.read_table(zf.open(entry))
    assert table.schema.names == FLOW + ["is_dynamic"]
    assert [str(t) for t in table.schema.types] == ["halffloat"] * 3 + ["bool"]
    assert table.num_rows == int(mask.sum()) == 78506
    # The flow (ego motion included) against Argoverse's own labels: float16 and labelling tolerance.
    got = np.stack([table.column(c).to_numpy() for c in FLOW], -1).astype(np.float64)
    want = np.stack([labels.column(c).to_numpy() for c in FLOW], -1)[mask]
    close = np.linalg.norm(got - want, axis=1) < 0.02
    assert np.mean(close) > 0.99, np.mean(close)
    np.testing.assert_array_equal(table.column("is_dynamic").to_numpy(zero_copy_only=False)[close],
                                  labels.column("dynamic").to_numpy(zero_copy_only=False)[mask][close])


@pytest.mark.slow  # trains, then evaluates by the protocol: ~45 s
def test_eval_protocol_av2_with_a_checkpoint(tiny_segment, sample_records, sample_masks, tmp_path):
    masks, _, mask, _ = sample_masks
    model_dir = tmp_path / "model"
    _run("tools/train.py", "--config", "configs/synthetic_cpu.yaml", *_tiny(), "--set", "train.num_steps=1",
         "--data_dir", os.path.dirname(tiny_segment), "--model_dir", str(model_dir))
    out, _ = _run("tools/eval.py", "--protocol", "av2", "--config", "configs/synthetic_cpu.yaml", *_tiny(),
                  "--set", "data.source=pair_records", "--data_dir", str(sample_records), "--checkpoint",
                  str(model_dir), "--out_dir", str(tmp_path / "eval"), "--masks", masks)
    assert "Argoverse 2 scene flow (2024 protocol)" in out and "zero flow" in out and "official masks" in out
    result = json.loads((tmp_path / "eval" / "metrics_av2.json").read_text())
    assert result["zero_flow"]["three_way/fg_dynamic_epe_m"] > 0.3
    assert result["model"]["num_points"] == result["zero_flow"]["num_points"] == int(mask.sum())  # the masks' points


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


@pytest.mark.slow  # trains one step, then submits: ~45 s
def test_a_test_submission_of_a_log_without_annotations(tiny_segment, tiny_config, tmp_path):
    """A synthetic test log (no annotations.feather) -> unlabelled records -> tools/av2_submission.py --split test
    --masks with a checkpoint: the masks' sweeps and rows, checked against the format JSON, read back."""
    from ff3d_tf.data import pair_records
    from ff3d_tf.data.synthetic import av2 as synthetic_av2
    from ff3d_tf.labels import av2
    log_id = synthetic_av2.log_id_for(6)
    log = synthetic_av2.write_synthetic_log(str(tmp_path / "test"), log_id, 7, 6, points_per_sweep=500)
    for name in ("annotations.feather", "flow_labels.feather"):
        os.remove(os.path.join(log, name))
    records = str(tmp_path / "records")
    av2.run_records_job([log], records, tiny_config, labels=False)
    assert not pair_records.read_manifest(records).human_labels
    stamps = argoverse2.sweep_timestamps(log)
    rng = np.random.default_rng(4)
    masks = {ts: rng.random(len(argoverse2.read_sweep(log, ts)["points_xyz"])) < 0.5 for ts in stamps[:-1][::5]}
    with zipfile.ZipFile(tmp_path / "test-masks.zip", "w") as zf:
        for ts, m in masks.items():
            sink = pa.BufferOutputStream()
            feather.write_feather(pa.table({"mask": pa.array(m)}), sink)
            zf.writestr(f"{log_id}/{ts}.feather", sink.getvalue().to_pybytes())
    fmt = tmp_path / "test_submission_format.json"
    fmt.write_text(json.dumps({f"{log_id}/{ts}.feather": int(m.sum()) for ts, m in masks.items()}))
    model_dir = tmp_path / "model"
    _run("tools/train.py", "--config", "configs/synthetic_cpu.yaml", *_tiny(), "--set", "train.num_steps=1",
         "--data_dir", os.path.dirname(tiny_segment), "--model_dir", str(model_dir))
    zip_path = tmp_path / "submission.zip"
    out, _ = _run("tools/av2_submission.py", "--config", "configs/synthetic_cpu.yaml", *_tiny(), "--checkpoint",
                  str(model_dir), "--leaderboard", "v1", "--split", "test", "--masks", str(tmp_path / "test-masks.zip"),
                  "--format_json", str(fmt), "--data_dir", records, "--out", str(zip_path))
    assert "checked against the layout and " + str(fmt) in out
    with zipfile.ZipFile(zip_path) as zf:
        assert sorted(zf.namelist()) == sorted(f"{log_id}/{ts}.feather" for ts in masks)
        for ts, m in masks.items():
            table = feather.read_table(zf.open(f"{log_id}/{ts}.feather"))
            assert table.schema.names == FLOW + ["is_dynamic"] and table.num_rows == int(m.sum())
