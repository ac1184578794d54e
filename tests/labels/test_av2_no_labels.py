"""Argoverse 2 logs without annotations (the test split): unlabelled pair records hold the labelled records' points in
the same order and the same pairs; a labelled job names the log and says --no_labels; a submission over an
official-layout mask archive is written from them, its rows the mask's."""
import json
import os
import shutil
import subprocess
import sys
import zipfile

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
import tensorflow as tf

from conftest import ROOT, TINY_OVERRIDES
from ff3d_tf.config import replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.synthetic import av2 as synthetic_av2
from ff3d_tf.labels import av2

FLOW = ["flow_tx_m", "flow_ty_m", "flow_tz_m"]
SAME = ("points_xyz_t0", "point_features_t0", "points_xyz_tm1_in_t0", "point_features_tm1", "pose_t0", "pose_tm1",
        "is_ground_t0", "is_ground_tm1", pair_records.TIMESTAMP_KEY, pair_records.PARTNER_TIMESTAMP_KEY,
        pair_records.SEQUENCE_KEY)


def _records(directory):
    """Every record of a records directory as stored (NumPy), whatever its labels."""
    manifest = pair_records.read_manifest(str(directory))
    out = []
    for path in pairs.list_segment_files(str(directory)):
        out += [{k: v.numpy() for k, v in ex.items()}
                for ex in pair_records.records_dataset(path, manifest, manifest.extras)]
    return manifest, out


@pytest.fixture(scope="module")
def test_split(tmp_path_factory):
    """A synthetic log (7 sweeps: 6 pairs), its labelled records, and the log as the test split has it (no
    annotations.feather, no flow labels)."""
    root = tmp_path_factory.mktemp("av2_test_split")
    log_id = synthetic_av2.log_id_for(4)
    labelled_log = synthetic_av2.write_synthetic_log(str(root / "val"), log_id, 7, 4, points_per_sweep=700)
    test_log = str(root / "test" / log_id)
    shutil.copytree(labelled_log, test_log)
    os.remove(os.path.join(test_log, "annotations.feather"))
    os.remove(os.path.join(test_log, "flow_labels.feather"))
    return labelled_log, test_log


def test_unlabelled_records_hold_the_labelled_points_in_order(test_split, tiny_config, tmp_path):
    labelled_log, test_log = test_split
    out_l, out_u = str(tmp_path / "labelled"), str(tmp_path / "unlabelled")
    av2.run_records_job([labelled_log], out_l, tiny_config)
    av2.run_records_job([test_log], out_u, tiny_config, labels=False)
    (m_l, recs_l), (m_u, recs_u) = _records(out_l), _records(out_u)
    assert m_l.human_labels and m_l.extras == av2.AV2_EXTRAS
    assert not m_u.human_labels and m_u.extras == av2.AV2_UNLABELLED_EXTRAS and m_u.partner == "next"
    assert len(recs_l) == len(recs_u) == 6
    for a, b in zip(recs_l, recs_u):
        for key in SAME:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert not np.all(a["flow_mps_t0"] == 0)  # the labelled log has moving things; the test log no labels:
        assert np.all(b["flow_mps_t0"] == 0) and np.all(b["class_id_t0"] == -1)
    # Every point of the sweep, in file order.
    stamps = argoverse2.sweep_timestamps(test_log)
    np.testing.assert_array_equal(recs_u[0]["points_xyz_t0"], argoverse2.read_sweep(test_log, stamps[0])["points_xyz"])
    # A labelled job over the log without annotations: named, with --no_labels, before any work.
    with pytest.raises(argoverse2.Argoverse2FormatError, match="--no_labels") as err:
        av2.run_records_job([test_log], str(tmp_path / "refused"), tiny_config)
    assert err.value.path == os.path.join(test_log, "annotations.feather")
    assert not os.path.exists(tmp_path / "refused")
    with pytest.raises(argoverse2.Argoverse2FormatError, match="--no_labels") as err:  # one log, labelled manifest
        av2.write_log_records(test_log, str(tmp_path / "one"), tiny_config, m_l)
    assert err.value.path == os.path.join(test_log, "annotations.feather")
    # Unlabelled records are not evaluation or training data.
    cfg = replace_config(tiny_config, {"data.source": "pair_records"})
    with pytest.raises(Exception, match="no human flow labels"):
        next(iter(pairs.pair_dataset(pairs.list_segment_files(out_u), cfg)))


def _feather_bytes(columns: dict) -> bytes:
    sink = pa.BufferOutputStream()
    feather.write_feather(pa.table(columns), sink)
    return sink.getvalue().to_pybytes()


class _Fixed:
    """A predictor of a fixed flow (m/s) for every point: no labels needed."""

    def predict(self, batch, example):
        n = int(tf.shape(example["points_xyz_t0"])[0])
        return np.tile(np.array([[-2.0, 0.5, 0.0]], np.float32), (n, 1)), np.ones(n, bool)


def _run(*args):
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


def _tiny():
    return [a for o in TINY_OVERRIDES for a in ("--set", o)]


@pytest.fixture(scope="module")
def test_records(test_split, tiny_config, tmp_path_factory):
    """Unlabelled records of the test log, an official-layout mask archive (every 5th pair, random masks) and
    av2-api's format JSON."""
    _, test_log = test_split
    root = tmp_path_factory.mktemp("av2_test_records")
    records = str(root / "records")
    av2.run_records_job([test_log], records, tiny_config, labels=False)
    _, recs = _records(records)
    examples = {(r[pair_records.SEQUENCE_KEY].decode(), int(r[pair_records.TIMESTAMP_KEY])): r for r in recs}
    rng = np.random.default_rng(3)
    official = {k: rng.random(len(examples[k]["points_xyz_t0"])) < 0.5 for k in sorted(examples)[::5]}
    masks = str(root / "test-masks.zip")
    with zipfile.ZipFile(masks, "w") as zf:
        for (log_id, ts), m in sorted(official.items()):
            zf.writestr(f"{log_id}/{ts}.feather", _feather_bytes({"mask": pa.array(m)}))
    fmt = root / "test_submission_format.json"
    fmt.write_text(json.dumps({f"{k[0]}/{k[1]}.feather": int(m.sum()) for k, m in official.items()}))
    return records, examples, official, masks, str(fmt)


def test_write_pair_records_names_a_log_without_annotations(test_split, tmp_path):
    _, test_log = test_split
    split = os.path.dirname(test_log)
    records = str(tmp_path / "records")
    out = _run("tools/write_pair_records.py", "--source", "av2", "--input", split, "--out_dir", records, *_tiny())
    assert out.returncode != 0 and os.path.join(test_log, "annotations.feather") in out.stderr
    assert "--no_labels" in out.stderr and not os.path.exists(records)
    out = _run("tools/write_pair_records.py", "--source", "av2", "--input", split, "--out_dir", records,
               "--no_labels", *_tiny())
    assert out.returncode == 0, out.stderr[-3000:]
    assert "'pairs': 6" in out.stdout
    assert not pair_records.read_manifest(records).human_labels


def test_av2_submission_refuses_ground_truth_of_unlabelled_records(test_records, tmp_path):
    records, _, _, masks, _ = test_records
    out = _run("tools/av2_submission.py", "--ground_truth", "--leaderboard", "v1", "--split", "test", "--masks",
               masks, "--data_dir", records, "--out", str(tmp_path / "gt.zip"), *_tiny())
    assert out.returncode != 0 and "--no_labels" in out.stderr and records in out.stderr


@pytest.mark.parametrize("leaderboard", ["v1", "v2", "v3"])
def test_a_test_submission_of_unlabelled_records(test_records, tiny_config, tmp_path, leaderboard):
    """What tools/av2_submission.py --split test --masks runs (write_av2_submission), with a predictor that needs no
    labels: the masks' sweeps (v1, v3; v2 the 2024 evaluator's) and rows (v1), read back."""
    records, examples, official, masks, fmt = test_records
    from ff3d_tf.training.evaluation import write_av2_submission
    cfg = replace_config(tiny_config, {"data.source": "pair_records"})
    zip_path = str(tmp_path / f"{leaderboard}.zip")
    summary = write_av2_submission(cfg, pairs.list_segment_files(records), _Fixed(), zip_path, leaderboard, "test",
                                   masks=masks, format_json=None if leaderboard == "v2" else fmt,
                                   log_fn=lambda s: None)
    with zipfile.ZipFile(zip_path) as zf:
        names = sorted(n for n in zf.namelist() if n.endswith(".feather"))
        tables = {n: feather.read_table(pa.BufferReader(zf.read(n))) for n in names}
    if leaderboard == "v2":  # the 2024 evaluator's sweeps: indices 0 and 5 of the log, every point
        keys = sorted(examples)
        want = {f"{keys[0][0]}/{i:010d}.feather": (keys[i], None) for i in (0, 5)}
    else:  # the mask archive's sweeps; v1 the mask's rows, v3 every point
        want = {f"{k[0]}/{k[1]}.feather": (k, m if leaderboard == "v1" else None) for k, m in official.items()}
    assert names == sorted(want) and summary["sweeps"] == len(want)
    for name, (key, rows) in want.items():
        ex = examples[key]
        n = len(ex["points_xyz_t0"])
        assert tables[name].num_rows == (n if rows is None else int(rows.sum()))
        if leaderboard == "v3":  # the ego-motion-free flow in metres to the next sweep: -flow_mps * dt
            dt_s = (ex[pair_records.PARTNER_TIMESTAMP_KEY] - ex[pair_records.TIMESTAMP_KEY]) * 1e-9
            got = np.stack([tables[name].column(c).to_numpy() for c in FLOW], -1).astype(np.float64)
            np.testing.assert_allclose(got, np.tile([[2.0 * dt_s, -0.5 * dt_s, 0.0]], (n, 1)), atol=1e-3)
