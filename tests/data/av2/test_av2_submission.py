"""Argoverse 2 submissions (ff3d_tf.data.av2.av2_submission): the flow conventions against Argoverse's own labels, the
write -> zip -> validate -> read round trip, and damaged archives that must fail naming the entry and field."""
import json
import os
import warnings
import zipfile

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from ff3d_tf import geometry, metrics_av2
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.av2 import av2_submission as sub

from conftest import ROOT
AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")
LOG_ID = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"  # the sample log's id (its map files carry it)


def _feather_bytes(columns: dict) -> bytes:
    sink = pa.BufferOutputStream()
    feather.write_feather(pa.table(columns), sink)
    return sink.getvalue().to_pybytes()


def _good_columns(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {**{c: pa.array(rng.normal(0, 1, n).astype(np.float16)) for c in sub.FLOW_COLUMNS},
            "is_dynamic": pa.array(rng.random(n) < 0.3)}


def _zip(path, entries: dict) -> str:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
    return str(path)


# --- conventions -----------------------------------------------------------------------------------------------------

def test_conversion_by_hand():
    p = np.array([[1.0, 2.0, 0.5], [-3.0, 0.0, 1.0]])
    d = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    # The ego vehicle drives 0.7 m forward: in its new frame a point sits 0.7 m further back, so a still point's
    # submission flow is (-0.7, 0, 0) and a moving one's is d + (-0.7, 0, 0).
    ego1_from_ego0 = np.eye(4)
    ego1_from_ego0[0, 3] = -0.7
    f = sub.av2_flow_from_ego_free(p, d, ego1_from_ego0)
    np.testing.assert_allclose(f, d + [-0.7, 0, 0], atol=1e-12)
    # A 90 degree yaw of the ego vehicle: (x, y) -> (y, -x) in the new frame.
    turn = np.eye(4)
    turn[:2, :2] = [[0, 1], [-1, 0]]
    f = sub.av2_flow_from_ego_free(p, d, turn)
    np.testing.assert_allclose(p + f, (p + d) @ turn[:3, :3].T, atol=1e-12)
    np.testing.assert_allclose(sub.ego_free_from_av2_flow(p, f, turn), d, atol=1e-12)


def test_conversion_matches_argoverse_labels_on_the_sample():
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    ego1_from_ego0 = geometry.t0_from_tm1_np(argoverse2.ego_pose(AV2_LOG, stamps[1]),
                                              argoverse2.ego_pose(AV2_LOG, stamps[0]))
    ego_free, p = argoverse2.argoverse_flow_in_paper_convention(AV2_LOG)
    t = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    f_label = np.stack([t.column(c).to_numpy() for c in sub.FLOW_COLUMNS], -1).astype(np.float64)
    np.testing.assert_allclose(sub.ego_free_from_av2_flow(p, f_label, ego1_from_ego0), ego_free, atol=1e-9)
    np.testing.assert_allclose(sub.av2_flow_from_ego_free(p, ego_free, ego1_from_ego0), f_label, atol=1e-9)


# --- round trip ------------------------------------------------------------------------------------------------------

def test_write_zip_validate_read_round_trip(tmp_path):
    root = str(tmp_path / "submission")
    rng = np.random.default_rng(1)
    expected, written = {}, {}
    for log_id, stamps, n in (("log-a", (100, 200), 7), ("log_b", (5,), 0), ("log-a", (300,), 3)):
        for ts in stamps:
            flow = rng.normal(0, 2, (n, 3))
            dyn = rng.random(n) < 0.5
            path = sub.write_sweep(root, log_id, ts, flow, dyn)
            assert path == os.path.join(root, log_id, f"{ts}.feather")
            expected[(log_id, ts)], written[(log_id, ts)] = n, (flow, dyn)
    zip_path = str(tmp_path / "submission.zip")
    seen = []
    summary = sub.make_archive(root, zip_path, expected, progress=lambda done, total: seen.append((done, total)))
    assert summary == {"sweeps": 4, "rows": 17, "logs": 2}
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]
    with zipfile.ZipFile(zip_path) as zf:
        assert sorted(zf.namelist()) == ["log-a/100.feather", "log-a/200.feather", "log-a/300.feather",
                                         "log_b/5.feather"]
        table = feather.read_table(pa.BufferReader(zf.read("log-a/100.feather")))
    assert table.schema.names == list(sub.SUBMISSION_COLUMNS)
    assert [str(t) for t in table.schema.types] == ["halffloat"] * 3 + ["bool"]
    assert sub.validate_archive(zip_path, expected) == summary
    assert sub.validate_archive(zip_path) == summary  # format only, no counts
    for (log_id, ts), (flow, dyn) in written.items():
        back = sub.read_sweep(zip_path, log_id, ts)
        assert back["flow_m_av2"].dtype == np.float16 and back["flow_m_av2"].shape == (len(flow), 3)
        np.testing.assert_array_equal(back["flow_m_av2"], flow.astype(np.float16))
        np.testing.assert_array_equal(back["is_dynamic"], dyn)
    assert not os.path.exists(zip_path + ".tmp")


def test_sample_ground_truth_submission_scores_zero(tmp_path):
    """The sample's labels as a submission: eval-mask rows, Argoverse's flow (ego motion in), its dynamic column;
    read back and scored, the EPE is float16 rounding only."""
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    ego1_from_ego0 = geometry.t0_from_tm1_np(argoverse2.ego_pose(AV2_LOG, stamps[1]),
                                              argoverse2.ego_pose(AV2_LOG, stamps[0]))
    ego_free, p = argoverse2.argoverse_flow_in_paper_convention(AV2_LOG)
    t = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    mask = metrics_av2.eval_mask(p, t.column("is_ground_0").to_numpy(zero_copy_only=False))
    flow_av2 = sub.av2_flow_from_ego_free(p, ego_free, ego1_from_ego0)
    sub.write_sweep(str(tmp_path / "s"), LOG_ID, stamps[0], flow_av2[mask], metrics_av2.is_dynamic(ego_free)[mask])
    zip_path = str(tmp_path / "s.zip")
    assert sub.make_archive(str(tmp_path / "s"), zip_path, {(LOG_ID, stamps[0]): int(mask.sum())})["rows"] == 74289
    back = sub.read_sweep(zip_path, LOG_ID, stamps[0])
    np.testing.assert_array_equal(back["is_dynamic"], t.column("dynamic").to_numpy(zero_copy_only=False)[mask])
    pred = sub.ego_free_from_av2_flow(p[mask], back["flow_m_av2"], ego1_from_ego0)
    acc = metrics_av2.AV2FlowAccumulator()
    acc.update(ego_free[mask], pred, t.column("classes").to_numpy().astype(np.int64)[mask])
    r = acc.result()
    # float16 keeps ~11 bits: |f| <= 1.4 m here -> <= 2^-11 * 2 per component, EPE < 2e-3.
    assert 0 < r["three_way/mean_epe_m"] < 2e-3 and r["bucketed/mean_static_epe_m"] < 2e-3


def test_expected_counts_from_json(tmp_path):
    path = tmp_path / "val_submission_format.json"
    path.write_text(json.dumps({"log-a/100.feather": 7, "log-a/200.feather": 0}))
    assert sub.expected_counts_from_json(str(path)) == {("log-a", 100): 7, ("log-a", 200): 0}
    path.write_text(json.dumps({"log-a/0100.feather": 7}))
    with pytest.raises(sub.SubmissionFormatError, match="key 'log-a/0100.feather'"):
        sub.expected_counts_from_json(str(path))
    path.write_text(json.dumps({"log-a/100.feather": -1}))
    with pytest.raises(sub.SubmissionFormatError, match="row count -1"):
        sub.expected_counts_from_json(str(path))


# --- what must fail --------------------------------------------------------------------------------------------------

def test_write_sweep_rejects_what_float16_cannot_hold(tmp_path):
    flow = np.zeros((4, 3))
    flow[2, 1] = 70000.0
    with pytest.raises(sub.SubmissionFormatError, match="flow_ty_m: 70000.0 at row 2") as e:
        sub.write_sweep(str(tmp_path), "log", 1, flow, np.zeros(4, bool))
    assert e.value.path.endswith(os.path.join("log", "1.feather"))
    with pytest.raises(sub.SubmissionFormatError, match="log_id"):
        sub.write_sweep(str(tmp_path), "../escape", 1, np.zeros((1, 3)), np.zeros(1, bool))
    with pytest.raises(sub.SubmissionFormatError, match="is_dynamic: shape"):
        sub.write_sweep(str(tmp_path), "log", 1, np.zeros((2, 3)), np.zeros(3, bool))
    assert not os.path.exists(tmp_path / "log" / "1.feather")


@pytest.mark.parametrize("case, entries, field, reason", [
    ("wrong dtype", {"log/1.feather": {**_good_columns(5), "flow_ty_m": pa.array(np.zeros(5, np.float32))}},
     "column flow_ty_m", "type float, expected halffloat"),
    ("dynamic not bool", {"log/1.feather": {**_good_columns(5), "is_dynamic": pa.array(np.zeros(5, np.uint8))}},
     "column is_dynamic", "expected bool"),
    ("missing column", {"log/1.feather": {k: v for k, v in _good_columns(5).items() if k != "flow_tz_m"}},
     "column flow_tz_m", "missing"),
    ("extra column", {"log/1.feather": {**_good_columns(5), "classes": pa.array(np.zeros(5, np.uint8))}},
     "column classes", "not allowed"),
    ("wrong row count", {"log/1.feather": _good_columns(4)}, "rows", "4 rows, the sweep's eval mask has 5 points"),
    ("null value", {"log/1.feather": {**_good_columns(2), "flow_tx_m": pa.array([np.float16(1), None],
                                                                                pa.float16())}},
     "column flow_tx_m", "1 null values"),
    ("non-finite flow", {"log/1.feather": {**_good_columns(3), "flow_tx_m": pa.array(np.array([0, np.inf, 0],
                                                                                             np.float16))}},
     "column flow_tx_m", "non-finite value at row 1"),
])
def test_damaged_sweep_files_fail_naming_the_field(tmp_path, case, entries, field, reason):
    expected = {("log", 1): 5} if case != "null value" and case != "non-finite flow" else None
    path = _zip(tmp_path / "s.zip", {name: _feather_bytes(cols) for name, cols in entries.items()})
    with pytest.raises(sub.SubmissionFormatError, match=reason) as e:
        sub.validate_archive(path, expected)
    assert e.value.path == f"{path}:log/1.feather" and e.value.field == field, case


@pytest.mark.parametrize("case, names, bad_entry, reason", [
    ("extra file", ["log/1.feather", "README.txt"], "README.txt", "unexpected file"),
    ("extra sweep", ["log/1.feather", "log/2.feather"], "log/2.feather", "extra file: not an evaluated sweep"),
    ("missing sweep", [], "log/1.feather", "missing"),
    ("leading zero", ["log/01.feather"], "log/01.feather", "unexpected file"),
    ("nested too deep", ["root/log/1.feather"], "root/log/1.feather", "unexpected file"),
    ("duplicate", ["log/1.feather", "log/1.feather"], "log/1.feather", "duplicate entry"),
])
def test_damaged_archives_fail_naming_the_entry(tmp_path, case, names, bad_entry, reason):
    path = str(tmp_path / "s.zip")
    with zipfile.ZipFile(path, "w") as zf, warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # zipfile warns on the duplicate name, and writes it
        for name in names:
            zf.writestr(name, _feather_bytes(_good_columns(5)) if name.endswith(".feather") else b"hi")
    with pytest.raises(sub.SubmissionFormatError, match=reason) as e:
        sub.validate_archive(path, {("log", 1): 5})
    assert e.value.path == f"{path}:{bad_entry}" and e.value.field == "file", case


def test_unreadable_archives(tmp_path):
    not_zip = tmp_path / "s.zip"
    not_zip.write_bytes(b"PK not really a zip")
    with pytest.raises(sub.SubmissionFormatError, match="not a readable zip archive") as e:
        sub.validate_archive(str(not_zip))
    assert e.value.path == str(not_zip)
    garbage = _zip(tmp_path / "g.zip", {"log/1.feather": b"ARROW1 but then nothing"})
    with pytest.raises(sub.SubmissionFormatError, match="not a readable Feather") as e:
        sub.validate_archive(garbage)
    assert e.value.path == f"{garbage}:log/1.feather"
    # A flipped byte in a stored entry: the zip's CRC check fails on reading it.
    good = bytearray(open(_zip(tmp_path / "c.zip", {"log/1.feather": _feather_bytes(_good_columns(50))}), "rb").read())
    at = good.index(b"ARROW1") + 100
    good[at] ^= 0xFF
    (tmp_path / "c.zip").write_bytes(bytes(good))
    with pytest.raises(sub.SubmissionFormatError, match="unreadable entry"):
        sub.validate_archive(str(tmp_path / "c.zip"))


def test_make_archive_checks_before_it_replaces(tmp_path):
    root = tmp_path / "s"
    sub.write_sweep(str(root), "log", 1, np.zeros((3, 3)), np.zeros(3, bool))
    zip_path = str(tmp_path / "s.zip")
    with open(zip_path, "wb") as f:
        f.write(b"previous archive")
    # Wrong expected count: the new archive fails validation, the previous file stays, no temporary is left.
    with pytest.raises(sub.SubmissionFormatError, match="3 rows, the sweep's eval mask has 4") as e:
        sub.make_archive(str(root), zip_path, {("log", 1): 4})
    assert e.value.path == f"{zip_path}:log/1.feather"
    assert open(zip_path, "rb").read() == b"previous archive" and not os.path.exists(zip_path + ".tmp")
    # A stray file in the folder is named before anything is zipped.
    (root / "log" / "notes.txt").write_text("x")
    with pytest.raises(sub.SubmissionFormatError, match="unexpected file in the submission folder") as e:
        sub.make_archive(str(root), zip_path, {("log", 1): 3})
    assert e.value.path == os.path.join(str(root), "log/notes.txt")
    os.remove(root / "log" / "notes.txt")
    assert sub.make_archive(str(root), zip_path, {("log", 1): 3}) == {"sweeps": 1, "rows": 3, "logs": 1}
    assert sub.read_sweep(zip_path, "log", 1)["flow_m_av2"].shape == (3, 3)
    with pytest.raises(sub.SubmissionFormatError, match="missing"):
        sub.read_sweep(zip_path, "log", 2)
