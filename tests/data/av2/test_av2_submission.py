"""Argoverse 2 submissions (ff3d_tf.data.av2.av2_submission): the flow conventions of the three layouts (against
Argoverse's own labels and on a pair with a known rotation), the write -> zip -> validate round trip read back by a
reader written here from the specifications, the plan of sweeps and rows from an official-layout mask archive, and
damaged masks, archives and format files that must fail naming the entry and field."""
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
V1, V2, V3 = (sub.LAYOUTS[k] for k in ("v1", "v2", "v3"))
FLOW = ("flow_tx_m", "flow_ty_m", "flow_tz_m")


def _feather_bytes(columns: dict) -> bytes:
    sink = pa.BufferOutputStream()
    feather.write_feather(pa.table(columns), sink)
    return sink.getvalue().to_pybytes()


def _good_columns(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {**{c: pa.array(rng.normal(0, 1, n).astype(np.float16)) for c in FLOW},
            "is_dynamic": pa.array(rng.random(n) < 0.3)}


def _zip(path, entries: dict) -> str:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
    return str(path)


def official_mask_archive(path, masks: dict, column: str = "mask") -> str:
    """A mask archive in the official layout (av2-api make_mask_files.py): <log_id>/<timestamp_ns>.feather, one bool
    column named `mask` over every point of the sweep, folders as zip entries."""
    entries = {}
    for log_id in sorted({k[0] for k in masks}):
        entries[f"{log_id}/"] = b""
    for (log_id, ts), m in sorted(masks.items()):
        entries[f"{log_id}/{ts}.feather"] = _feather_bytes({column: pa.array(np.asarray(m))})
    return _zip(path, entries)


def spec_read(zip_path: str, entry: str) -> dict:
    """A submission file read as the specifications describe it (not through the module): {column: NumPy}."""
    with zipfile.ZipFile(zip_path) as zf:
        table = feather.read_table(pa.BufferReader(zf.read(entry)))
    return {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.schema.names}


def _rot_z(yaw: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    m = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = t
    return m


# --- conventions -----------------------------------------------------------------------------------------------------

def test_conversion_by_hand():
    p = np.array([[1.0, 2.0, 0.5], [-3.0, 0.0, 1.0]])
    d = np.array([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    # The ego vehicle drives 0.7 m forward: in its new frame a point sits 0.7 m further back, so a still point's
    # v1 flow is (-0.7, 0, 0) and a moving one's is d + (-0.7, 0, 0).
    ego1_from_ego0 = np.eye(4)
    ego1_from_ego0[0, 3] = -0.7
    np.testing.assert_allclose(sub.av2_flow_from_ego_free(p, d, ego1_from_ego0), d + [-0.7, 0, 0], atol=1e-12)
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
    f_label = np.stack([t.column(c).to_numpy() for c in FLOW], -1).astype(np.float64)
    np.testing.assert_allclose(sub.ego_free_from_av2_flow(p, f_label, ego1_from_ego0), ego_free, atol=1e-9)
    np.testing.assert_allclose(sub.av2_flow_from_ego_free(p, ego_free, ego1_from_ego0), f_label, atol=1e-9)


def test_each_layout_on_a_pair_with_a_known_rotation(tmp_path):
    """The ego vehicle turns 30 degrees left and moves (2, 0.5, 0) m between the sweeps: sweep-0 ego coordinates q
    are R^T (q - t) in the sweep-1 ego frame. v1 holds (the point at sweep 1, sweep-1 frame) - p; v2 and v3 hold d."""
    rng = np.random.default_rng(3)
    p = rng.uniform(-20, 20, (9, 3))
    d = np.zeros((9, 3))
    d[::3] = [0.8, -0.3, 0.02]  # three moving points, six static ones
    pose0, pose1 = np.eye(4), _rot_z(np.deg2rad(30), (2.0, 0.5, 0.0))  # ego -> world (= city)
    ego1_from_ego0 = geometry.t0_from_tm1_np(pose1, pose0)
    r, t = pose1[:3, :3], pose1[:3, 3]
    by_hand = (p + d - t) @ r  # R^T (q - t), row vectors
    rows = np.array([True, True, False, True, False, True, True, False, True])
    cols = sub.sweep_columns(V1, p, d, ego1_from_ego0, rows)
    assert list(cols) == list(V1.columns)
    np.testing.assert_allclose(np.stack([cols[c] for c in FLOW], -1), (by_hand - p)[rows], atol=1e-12)
    np.testing.assert_array_equal(cols["is_dynamic"], (np.arange(9) % 3 == 0)[rows])
    for lay in (V2, V3):
        cols = sub.sweep_columns(lay, p, d, ego1_from_ego0)
        assert list(cols) == list(lay.columns)
        np.testing.assert_array_equal(np.stack([cols[c] for c in FLOW], -1), d)  # ego-motion-free, every point
    assert sub.sweep_columns(V2, p, d, ego1_from_ego0)["is_valid"].all()
    # Written and read back: float16, nothing else changes.
    for lay, entry in ((V1, "log/5.feather"), (V2, "log/0000000005.feather"), (V3, "log/5.feather")):
        cols = sub.sweep_columns(lay, p, d, ego1_from_ego0, rows if lay.mask_rows else None)
        sub.write_sweep(str(tmp_path / lay.name), lay, entry, cols)
        back = sub.read_sweep_file(str(tmp_path / lay.name / entry), lay)
        for c in lay.columns:
            want = cols[c].astype(np.float16) if c in FLOW else cols[c]
            np.testing.assert_array_equal(back[c], want)


# --- round trip of the sample's labels, every layout ------------------------------------------------------------------

def _sample_truth():
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    ego1_from_ego0 = geometry.t0_from_tm1_np(argoverse2.ego_pose(AV2_LOG, stamps[1]),
                                              argoverse2.ego_pose(AV2_LOG, stamps[0]))
    ego_free, p = argoverse2.argoverse_flow_in_paper_convention(AV2_LOG)
    t = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    return stamps, ego1_from_ego0, ego_free, p, t


@pytest.mark.parametrize("name", ["v1", "v2", "v3"])
def test_sample_labels_as_a_submission_score_zero(tmp_path, name):
    """The sample's labels through a mask archive in the official layout (av2-api's rule on the labels' own ground):
    written, zipped, checked, read back by `spec_read` and converted by the specification's arithmetic written here;
    the challenge's EPE against the labels is float16 rounding only."""
    lay = sub.LAYOUTS[name]
    stamps, ego1_from_ego0, ego_free, p, t = _sample_truth()
    is_ground = t.column("is_ground_0").to_numpy(zero_copy_only=False)
    official = (np.abs(p[:, 0]) <= 50) & (np.abs(p[:, 1]) <= 50) & ~is_ground
    assert int(official.sum()) == 78506  # av2-api's rule on Argoverse's own ground labels
    masks = sub.MaskArchive(official_mask_archive(tmp_path / "val-masks.zip", {(LOG_ID, stamps[0]): official}))
    record = sub.RecordSweep(LOG_ID, stamps[0], stamps[1], len(p), "records/sample.pairs.tfrecord")
    (planned,) = sub.plan_submission(lay, [record], masks)
    assert planned.entry == (f"{LOG_ID}/0000000000.feather" if name == "v2" else f"{LOG_ID}/{stamps[0]}.feather")
    rows = masks.checked_mask((LOG_ID, stamps[0]), len(p), record.where) if lay.mask_rows else None
    sub.write_sweep(str(tmp_path / "s"), lay, planned.entry, sub.sweep_columns(lay, p, ego_free, ego1_from_ego0, rows))
    zip_path = str(tmp_path / "s.zip")
    assert sub.make_archive(str(tmp_path / "s"), zip_path, lay, {planned.entry: planned.rows})["rows"] == \
        (78506 if lay.mask_rows else len(p))
    got = spec_read(zip_path, planned.entry)
    assert list(got) == list(lay.columns)
    assert all(got[c].dtype == np.float16 for c in FLOW)
    flow = np.stack([got[c] for c in FLOW], -1).astype(np.float64)
    sel = official if lay.mask_rows else np.ones(len(p), bool)
    if lay.flow_includes_ego_motion:  # the position at sweep 1 in its frame, less p: back into the sweep-0 frame
        q1 = p[sel] + flow
        pred = (np.c_[q1, np.ones(len(q1))] @ np.linalg.inv(ego1_from_ego0).T)[:, :3] - p[sel]
        np.testing.assert_array_equal(got["is_dynamic"], t.column("dynamic").to_numpy(zero_copy_only=False)[sel])
    else:
        pred = flow
        if name == "v2":
            assert got["is_valid"].all() and len(got["is_valid"]) == len(p)
            with zipfile.ZipFile(zip_path) as zf:
                assert json.loads(zf.read("metadata.json")) == {"Is Supervised?": True}
    acc = metrics_av2.AV2FlowAccumulator()
    acc.update(ego_free[sel], pred, t.column("classes").to_numpy().astype(np.int64)[sel])
    r = acc.result()
    # float16 keeps ~11 bits: |f| <= 1.4 m here -> <= 2^-11 * 2 per component, EPE < 2e-3.
    assert r["num_points"] == int(sel.sum()) and 0 <= r["three_way/mean_epe_m"] < 2e-3
    assert r["bucketed/mean_static_epe_m"] < 2e-3
    masks.close()


# --- the plan: sweeps, rows and order from the mask archive -----------------------------------------------------------

def _fake_records(logs: dict[str, int], seed: int = 0) -> list:
    """Records of logs {log_id: sweeps}: every sweep but the last, with point counts drawn per sweep."""
    rng = np.random.default_rng(seed)
    out = []
    for log_id, n in logs.items():
        stamps = 1_000_000_000 * (1 + len(out)) + 100_000_000 * np.arange(n)
        for a, b in zip(stamps[:-1], stamps[1:]):
            out.append(sub.RecordSweep(log_id, int(a), int(b), int(rng.integers(50, 90)), f"rec/{log_id}.pairs.tfrecord"))
    return out


def test_the_plan_follows_the_mask_archive(tmp_path):
    records = _fake_records({"log-b": 7, "log-a": 12})
    by_key = {r.key: r for r in records}
    # The official masks: an every-5th subset (av2-api's order) and masks of any shape; here random, so no rule of
    # this project could produce them.
    rng = np.random.default_rng(1)
    chosen = sub.av2_api_rule_subset(by_key)
    assert [k[0] for k in chosen] == ["log-a", "log-a", "log-a", "log-b"] and chosen[0] == min(by_key)
    official = {k: rng.random(by_key[k].num_points) < 0.4 for k in chosen}
    masks = sub.MaskArchive(official_mask_archive(tmp_path / "m.zip", official))
    v1 = sub.plan_submission(V1, records, masks)
    assert [(p.log_id, p.timestamp_ns) for p in v1] == sorted(official)
    assert [p.rows for p in v1] == [int(official[k].sum()) for k in sorted(official)]
    assert [p.entry for p in v1] == [f"{k[0]}/{k[1]}.feather" for k in sorted(official)]
    v3 = sub.plan_submission(V3, records, masks)
    assert [p.entry for p in v3] == [p.entry for p in v1] and [p.rows for p in v3] == [p.num_points for p in v3]
    # v1's rows are the mask's points in point order.
    key = sorted(official)[1]
    n = by_key[key].num_points
    p, d = rng.normal(0, 5, (n, 3)), np.c_[np.arange(n) * 1e-3, np.zeros((n, 2))]
    cols = sub.sweep_columns(V1, p, d, np.eye(4), masks.checked_mask(key, n, by_key[key].where))
    np.testing.assert_allclose(cols["flow_tx_m"], (np.arange(n) * 1e-3)[official[key]])
    # v2: sweep indices 0, 5, 10 of log-a (11 pairs) and 0, 5 of log-b (6 pairs): ceil(pairs / 5) files a log.
    v2 = sub.plan_submission(V2, records, masks)
    assert [p.entry for p in v2] == ["log-a/0000000000.feather", "log-a/0000000005.feather",
                                     "log-a/0000000010.feather", "log-b/0000000000.feather",
                                     "log-b/0000000005.feather"]
    assert [p.rows for p in v2] == [p.num_points for p in v2]
    # Without masks (local validation): av2-api's subset; v1's rows decided when written.
    fallback = sub.plan_submission(V1, records, None)
    assert [(p.log_id, p.timestamp_ns) for p in fallback] == chosen and {p.rows for p in fallback} == {None}
    masks.close()


def test_av2_api_rule_mask():
    p = np.array([[50.0, -50.0, 0.0], [50.01, 0.0, 0.0], [0.0, -50.5, 1.0], [3.0, 4.0, 0.0], [1.0, 1.0, 0.0]])
    g = np.array([False, False, False, True, False])
    np.testing.assert_array_equal(sub.av2_api_rule_mask(p, g), [True, False, False, False, True])


# --- bad masks, bad records ------------------------------------------------------------------------------------------

def test_bad_mask_archives_fail_naming_the_entry(tmp_path):
    records = _fake_records({"log-a": 7})
    k0, k1 = records[0].key, records[5].key
    good = {k0: np.ones(records[0].num_points, bool), k1: np.zeros(records[5].num_points, bool)}
    # A mask of the wrong length: the mask entry and the record's file, both named.
    path = official_mask_archive(tmp_path / "len.zip", {**good, k1: np.ones(records[5].num_points + 1, bool)})
    with pytest.raises(sub.SubmissionFormatError, match="but the sweep's pair record in rec/log-a.pairs.tfrecord") as e:
        sub.plan_submission(V1, records, sub.MaskArchive(path))
    assert e.value.path == f"{path}:log-a/{k1[1]}.feather" and e.value.field == "mask length"
    # A sweep of the masks without a record: both named.
    path = official_mask_archive(tmp_path / "missing.zip", {**good, ("log-z", 5): np.ones(3, bool)})
    with pytest.raises(sub.SubmissionFormatError, match="no pair record of this sweep in rec") as e:
        sub.plan_submission(V3, records, sub.MaskArchive(path))
    assert e.value.path == f"{path}:log-z/5.feather" and e.value.field == "sweep"
    # A column that is not boolean, two columns, nulls: the entry and the column named.
    for cols, field, reason in (({"mask": pa.array(np.ones(records[0].num_points, np.uint8))}, "column mask",
                                 "type uint8, a mask column is bool"),
                                ({"mask": pa.array(np.ones(3, bool)), "x": pa.array(np.ones(3, bool))}, "columns",
                                 "exactly one boolean column"),
                                ({"m": pa.array([True, None], pa.bool_())}, "column m", "1 null values")):
        path = _zip(tmp_path / "col.zip", {f"log-a/{k0[1]}.feather": _feather_bytes(cols)})
        with pytest.raises(sub.SubmissionFormatError, match=reason) as e:
            sub.plan_submission(V1, records, sub.MaskArchive(path))
        assert e.value.path == f"{path}:log-a/{k0[1]}.feather" and e.value.field == field
    # A corrupt zip, a zip without masks, a misnamed mask, an unreadable mask file.
    corrupt = tmp_path / "corrupt.zip"
    corrupt.write_bytes(b"PK\x03\x04 not a zip at all")
    with pytest.raises(sub.SubmissionFormatError, match="not a readable zip archive of masks") as e:
        sub.MaskArchive(str(corrupt))
    assert e.value.path == str(corrupt) and "3d_scene_flow" in str(e.value)
    with pytest.raises(sub.SubmissionFormatError, match="no <log_id>/<timestamp_ns>.feather masks"):
        sub.MaskArchive(_zip(tmp_path / "empty.zip", {"README.txt": b"hi"}))
    with pytest.raises(sub.SubmissionFormatError, match="must be <log_id>/<timestamp_ns>.feather") as e:
        sub.MaskArchive(_zip(tmp_path / "name.zip", {"log-a/007.feather": b""}))
    assert e.value.path.endswith("name.zip:log-a/007.feather")
    path = _zip(tmp_path / "garbage.zip", {f"log-a/{k0[1]}.feather": b"ARROW1 then nothing"})
    with pytest.raises(sub.SubmissionFormatError, match="not a readable Feather") as e:
        sub.MaskArchive(path).mask(k0)
    assert e.value.path == f"{path}:log-a/{k0[1]}.feather"


def test_v2_needs_every_pair_of_a_log(tmp_path):
    records = _fake_records({"log-a": 9})
    del records[3]  # a pair the records skipped: positions in the log are unknown after it
    with pytest.raises(sub.SubmissionFormatError, match="must hold every pair of the log") as e:
        sub.plan_submission(V2, records, None)
    assert e.value.path == "rec/log-a.pairs.tfrecord" and e.value.field == "log log-a"
    with pytest.raises(sub.SubmissionFormatError, match="a second record of this sweep"):
        sub.plan_submission(V1, records + records[:1], None)


# --- av2-api's format JSON -------------------------------------------------------------------------------------------

def test_expected_counts_from_json_and_the_check_against_it(tmp_path):
    path = tmp_path / "val_submission_format.json"
    path.write_text(json.dumps({"log-a/100.feather": 7, "log-a/200.feather": 0}))
    fmt = sub.expected_counts_from_json(str(path))
    assert fmt == {"log-a/100.feather": 7, "log-a/200.feather": 0}
    sub.check_against_format_json(V1, {"log-a/100.feather": 7, "log-a/200.feather": None}, fmt, str(path))
    sub.check_against_format_json(V3, {"log-a/100.feather": 70, "log-a/200.feather": 50}, fmt, str(path))  # names
    with pytest.raises(sub.SubmissionFormatError, match="7 rows expected, the official mask selects 8") as e:
        sub.check_against_format_json(V1, {"log-a/100.feather": 8, "log-a/200.feather": 0}, fmt, str(path))
    assert e.value.path == f"{path}:log-a/100.feather" and e.value.field == "rows"
    with pytest.raises(sub.SubmissionFormatError, match="does not plan") as e:
        sub.check_against_format_json(V1, {"log-a/100.feather": 7}, fmt, str(path))
    assert e.value.path == f"{path}:log-a/200.feather"
    with pytest.raises(sub.SubmissionFormatError, match="not in the format JSON"):
        sub.check_against_format_json(V3, {**fmt, "log-b/1.feather": 3}, fmt, str(path))
    with pytest.raises(sub.SubmissionFormatError, match="names sweeps by index"):
        sub.check_against_format_json(V2, {}, fmt, str(path))
    for bad, field in (({"log-a/01.feather": 3}, "key 'log-a/01.feather'"), ({"log-a/1.feather": -1},
                                                                             "key 'log-a/1.feather'"),
                       ({"log-a/1.feather": True}, "key 'log-a/1.feather'"), ([1, 2], "file")):
        path.write_text(json.dumps(bad))
        with pytest.raises(sub.SubmissionFormatError) as e:
            sub.expected_counts_from_json(str(path))
        assert e.value.path == str(path) and e.value.field == field
    path.write_text("{not json")
    with pytest.raises(sub.SubmissionFormatError, match="not JSON"):
        sub.expected_counts_from_json(str(path))


# --- archives ---------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("case, columns, field, reason", [
    ("wrong dtype", {**_good_columns(5), "flow_ty_m": pa.array(np.zeros(5, np.float32))},
     "column flow_ty_m", "type float, expected halffloat"),
    ("dynamic not bool", {**_good_columns(5), "is_dynamic": pa.array(np.zeros(5, np.uint8))},
     "column is_dynamic", "expected bool"),
    ("missing column", {k: v for k, v in _good_columns(5).items() if k != "flow_tz_m"}, "column flow_tz_m", "missing"),
    ("extra column", {**_good_columns(5), "classes": pa.array(np.zeros(5, np.uint8))}, "column classes",
     "not allowed"),
    ("wrong row count", _good_columns(4), "rows", "4 rows, the sweep's official mask has 5 points"),
    ("null value", {**_good_columns(2), "flow_tx_m": pa.array([np.float16(1), None], pa.float16())},
     "column flow_tx_m", "1 null values"),
    ("non-finite flow", {**_good_columns(3), "flow_tx_m": pa.array(np.array([0, np.inf, 0], np.float16))},
     "column flow_tx_m", "non-finite value at row 1"),
])
def test_damaged_v1_files_fail_naming_the_field(tmp_path, case, columns, field, reason):
    expected = {"log/1.feather": 5} if case not in ("null value", "non-finite flow") else None
    path = _zip(tmp_path / "s.zip", {"log/1.feather": _feather_bytes(columns)})
    with pytest.raises(sub.SubmissionFormatError, match=reason) as e:
        sub.validate_archive(path, V1, expected)
    assert e.value.path == f"{path}:log/1.feather" and e.value.field == field, case


def test_v2_and_v3_files_are_checked_against_their_layout(tmp_path):
    flows = {c: pa.array(np.zeros(4, np.float16)) for c in FLOW}
    v3_with_dynamic = _zip(tmp_path / "a.zip", {"log/1.feather": _feather_bytes({**flows, "is_dynamic":
                                                                                 pa.array(np.zeros(4, bool))})})
    with pytest.raises(sub.SubmissionFormatError, match="not allowed") as e:
        sub.validate_archive(v3_with_dynamic, V3)
    assert e.value.field == "column is_dynamic"
    meta = json.dumps({"Is Supervised?": True}).encode()
    v2_good = {"metadata.json": meta, "log/0000000000.feather": _feather_bytes({"is_valid": pa.array(np.ones(4, bool)),
                                                                                **flows})}
    assert sub.validate_archive(_zip(tmp_path / "b.zip", v2_good), V2, {"log/0000000000.feather": 4}) == \
        {"sweeps": 1, "rows": 4, "logs": 1}
    for entries, bad_entry, field, reason in (
            ({k: v for k, v in v2_good.items() if k != "metadata.json"}, "metadata.json", "file", "missing"),
            ({**v2_good, "metadata.json": b'{"Is Supervised?": "yes"}'}, "metadata.json", "Is Supervised?",
             "expected"),
            ({**v2_good, "log/0000000003.feather": b""}, "log/0000000003.feather", "file", "multiple of 5"),
            ({**v2_good, "log/5.feather": b""}, "log/5.feather", "file", "unexpected file"),
            ({"metadata.json": meta, "log/0000000000.feather": _feather_bytes(flows)}, "log/0000000000.feather",
             "column is_valid", "missing")):
        path = _zip(tmp_path / "c.zip", entries)
        with pytest.raises(sub.SubmissionFormatError, match=reason) as e:
            sub.validate_archive(path, V2)
        assert e.value.path == f"{path}:{bad_entry}" and e.value.field == field, reason


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
        sub.validate_archive(path, V1, {"log/1.feather": 5})
    assert e.value.path == f"{path}:{bad_entry}" and e.value.field == "file", case


def test_unreadable_archives(tmp_path):
    not_zip = tmp_path / "s.zip"
    not_zip.write_bytes(b"PK not really a zip")
    with pytest.raises(sub.SubmissionFormatError, match="not a readable zip archive") as e:
        sub.validate_archive(str(not_zip), V1)
    assert e.value.path == str(not_zip)
    garbage = _zip(tmp_path / "g.zip", {"log/1.feather": b"ARROW1 but then nothing"})
    with pytest.raises(sub.SubmissionFormatError, match="not a readable Feather") as e:
        sub.validate_archive(garbage, V1)
    assert e.value.path == f"{garbage}:log/1.feather"
    # A flipped byte in a stored entry: the zip's CRC check fails on reading it.
    good = bytearray(open(_zip(tmp_path / "c.zip", {"log/1.feather": _feather_bytes(_good_columns(50))}), "rb").read())
    at = good.index(b"ARROW1") + 100
    good[at] ^= 0xFF
    (tmp_path / "c.zip").write_bytes(bytes(good))
    with pytest.raises(sub.SubmissionFormatError, match="unreadable entry"):
        sub.validate_archive(str(tmp_path / "c.zip"), V1)


def test_make_archive_checks_before_it_replaces(tmp_path):
    root = tmp_path / "s"
    sub.write_sweep(str(root), V1, "log/1.feather", sub.sweep_columns(V1, np.zeros((3, 3)), np.zeros((3, 3)),
                                                                       np.eye(4), np.ones(3, bool)))
    zip_path = str(tmp_path / "s.zip")
    with open(zip_path, "wb") as f:
        f.write(b"previous archive")
    # Wrong expected count: the new archive fails validation, the previous file stays, no temporary is left.
    with pytest.raises(sub.SubmissionFormatError, match="3 rows, the sweep's official mask has 4") as e:
        sub.make_archive(str(root), zip_path, V1, {"log/1.feather": 4})
    assert e.value.path == f"{zip_path}:log/1.feather"
    assert open(zip_path, "rb").read() == b"previous archive" and not os.path.exists(zip_path + ".tmp")
    # A stray file in the folder is named before anything is zipped.
    (root / "log" / "notes.txt").write_text("x")
    with pytest.raises(sub.SubmissionFormatError, match="unexpected file in the submission folder") as e:
        sub.make_archive(str(root), zip_path, V1, {"log/1.feather": 3})
    assert e.value.path == os.path.join(str(root), "log/notes.txt")
    os.remove(root / "log" / "notes.txt")
    seen = []
    assert sub.make_archive(str(root), zip_path, V1, {"log/1.feather": 3}, progress=lambda *a: seen.append(a)) == \
        {"sweeps": 1, "rows": 3, "logs": 1}
    assert seen == [(1, 1)] and sub.read_sweep(zip_path, V1, "log/1.feather")["flow_tx_m"].shape == (3,)
    with pytest.raises(sub.SubmissionFormatError, match="missing"):
        sub.read_sweep(zip_path, V1, "log/2.feather")
    with pytest.raises(sub.SubmissionFormatError, match="not a finite float16") as e:
        sub.write_sweep(str(root), V3, "log/2.feather", {c: np.array([0.0, 1e6]) for c in FLOW})
    assert e.value.field == "column flow_tx_m"
