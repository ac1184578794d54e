"""The Argoverse 2 challenge protocol of `tools/eval.py --protocol av2` on the real sample log: the ground truth scores
0, zero flow and a model's flow score what the challenge's arithmetic (`ff3d_tf.metrics_av2`, checked against a
straight-line reference of the community evaluator in tests/test_metrics_av2.py) gives on the same points; with the
official masks, exactly their points. And submissions of synthetic Argoverse 2 logs in the three layouts over a mask
archive in the official layout: sweeps, rows and order follow it, and the labels read back score 0."""
import json
import os
import zipfile

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from ff3d_tf import metrics_av2
from ff3d_tf.config import replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.av2.av2_submission import SubmissionFormatError
from ff3d_tf.data.synthetic import av2 as synthetic_av2
from ff3d_tf.labels import av2
from ff3d_tf.training.evaluation import challenge_flow_m, evaluate_av2, write_av2_submission

SAMPLE_LOG_ID = "av2_sample_log"  # the records' sequence id: the log directory's name


class _Fixed:
    """A predictor of flow = scale * label + offset (m/s), valid everywhere but `invalid`."""

    def __init__(self, scale=1.0, offset=(0.0, 0.0, 0.0), invalid=None):
        self.scale, self.offset, self.invalid = scale, np.asarray(offset, np.float32), invalid

    def predict(self, batch, example):
        flow = self.scale * np.asarray(example["flow_mps_t0"]) + self.offset
        valid = np.ones(len(flow), bool)
        if self.invalid is not None:
            valid[self.invalid(np.asarray(example["points_xyz_t0"]))] = False
        return flow, valid


def _records_cfg(cfg):
    return replace_config(cfg, {"data.source": "pair_records"})


def _read_records(records, cfg) -> list[dict]:
    cfg = replace_config(_records_cfg(cfg), {"data.crop_to_grid": False})
    return [{k: v.numpy() for k, v in e.items()} for e in pairs.pair_dataset(
        pairs.list_segment_files(records), cfg, extras=av2.AV2_EXTRAS, metadata=True)]


def _straight(records, cfg, predictor, mask=None):
    """The same numbers without the evaluation loop: the records read directly and fed to the accumulator."""
    (ex,) = _read_records(records, cfg)
    flow, valid = predictor.predict(None, ex)
    flow = np.where(valid[:, None], flow, 0.0)
    acc = metrics_av2.AV2FlowAccumulator()
    if mask is None:
        mask = ~ex["is_ground_t0"] & (np.max(np.abs(ex["points_xyz_t0"][:, :2]), axis=1) < 35.0)
    acc.update(challenge_flow_m(ex["flow_mps_t0"], ex), challenge_flow_m(flow, ex), ex["category_t0"], mask)
    return acc.result(), int(mask.sum())


def _assert_same(got: dict, want: dict):
    assert set(got) == set(want)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-9, err_msg=k)


def test_ground_truth_scores_zero(av2_sample_records, tiny_config):
    r = evaluate_av2(_records_cfg(tiny_config), pairs.list_segment_files(av2_sample_records), _Fixed())
    m = r["model"]
    for k in ("three_way/fg_dynamic_epe_m", "three_way/fg_static_epe_m", "three_way/bg_static_epe_m",
              "three_way/mean_epe_m", "bucketed/mean_static_epe_m", "bucketed/mean_dynamic_norm_epe"):
        assert m[k] == 0.0, k
    assert m["num_sweeps"] == 1 and m["num_points"] > 50_000
    assert r["paper_model"]["all/all/mean_l2_mps"] == 0.0 and r["paper_zero_flow"]["vehicle/moving/mean_l2_mps"] > 3
    # Zero flow is not 0 on the moving points: the sample's vehicles move.
    assert r["zero_flow"]["three_way/fg_dynamic_epe_m"] > 0.3


@pytest.mark.parametrize("predictor", [_Fixed(scale=0.0), _Fixed(scale=0.8, offset=(0.05, -0.02, 0.0)),
                                       _Fixed(scale=1.1, invalid=lambda p: p[:, 0] > 20.0)])
def test_model_and_zero_flow_are_the_challenges_arithmetic_on_the_same_points(av2_sample_records, tiny_config,
                                                                               predictor):
    r = evaluate_av2(_records_cfg(tiny_config), pairs.list_segment_files(av2_sample_records), predictor)
    want, n = _straight(av2_sample_records, tiny_config, predictor)
    _assert_same(r["model"], want)
    _assert_same(r["zero_flow"], _straight(av2_sample_records, tiny_config, _Fixed(scale=0.0))[0])
    assert r["model"]["num_points"] == n


def test_other_records_are_refused(tiny_config, tmp_path):
    from ff3d_tf.data import pair_records
    from ff3d_tf.data.wod import write_records
    pair_records.write_manifest(str(tmp_path), write_records.wod_manifest(tiny_config))
    (tmp_path / "x.pairs.tfrecord").write_bytes(b"")
    with pytest.raises(ValueError, match="next sweep"):
        evaluate_av2(_records_cfg(tiny_config), [str(tmp_path / "x.pairs.tfrecord")], _Fixed())
    with pytest.raises(ValueError, match="pair records"):
        evaluate_av2(tiny_config, [str(tmp_path / "x.pairs.tfrecord")], _Fixed())


# --- the official masks ----------------------------------------------------------------------------------------------

def _feather_bytes(columns: dict) -> bytes:
    sink = pa.BufferOutputStream()
    feather.write_feather(pa.table(columns), sink)
    return sink.getvalue().to_pybytes()


def official_mask_archive(path, masks: dict) -> str:
    """A mask archive in the official layout: <log_id>/<timestamp_ns>.feather, one bool column `mask` a point."""
    with zipfile.ZipFile(path, "w") as zf:
        for (log_id, ts), m in sorted(masks.items()):
            zf.writestr(f"{log_id}/{ts}.feather", _feather_bytes({"mask": pa.array(np.asarray(m, bool))}))
    return str(path)


def test_with_official_masks_exactly_their_points_are_scored(av2_sample_records, tiny_config, tmp_path):
    (ex,) = _read_records(av2_sample_records, tiny_config)
    key, n = (SAMPLE_LOG_ID, int(ex[pair_records.TIMESTAMP_KEY])), len(ex["points_xyz_t0"])
    official = np.random.default_rng(5).random(n) < 0.3  # no rule of this project gives these points
    masks = official_mask_archive(tmp_path / "val-masks.zip", {key: official})
    files = pairs.list_segment_files(av2_sample_records)
    predictor = _Fixed(scale=0.8, offset=(0.05, -0.02, 0.0))
    r = evaluate_av2(_records_cfg(tiny_config), files, predictor, masks=masks)
    want, count = _straight(av2_sample_records, tiny_config, predictor, mask=official)
    _assert_same(r["model"], want)
    assert count == r["model"]["num_points"] == int(official.sum()) and masks in r["points"]
    # A mask of another length, a sweep the records do not hold: errors naming the mask entry and the records.
    bad = official_mask_archive(tmp_path / "len.zip", {key: np.ones(n - 1, bool)})
    with pytest.raises(SubmissionFormatError, match=f"{n - 1} values, but the sweep's pair record in") as e:
        evaluate_av2(_records_cfg(tiny_config), files, predictor, masks=bad)
    assert e.value.path == f"{bad}:{key[0]}/{key[1]}.feather" and files[0] in str(e.value)
    bad = official_mask_archive(tmp_path / "more.zip", {key: official, (key[0], key[1] + 1): official})
    with pytest.raises(SubmissionFormatError, match="no pair record of this sweep in") as e:
        evaluate_av2(_records_cfg(tiny_config), files, predictor, masks=bad)
    assert e.value.path == f"{bad}:{key[0]}/{key[1] + 1}.feather" and av2_sample_records in str(e.value)


# --- submissions of synthetic logs in every layout ----------------------------------------------------------------------

class _Labels:
    """The records' own labels as the prediction."""

    def predict(self, batch, example):
        flow = np.asarray(example["flow_mps_t0"])
        return flow, np.ones(len(flow), bool)


@pytest.fixture(scope="module")
def synthetic_split(tiny_config, tmp_path_factory):
    """Records of two synthetic logs (12 and 7 sweeps: 11 and 6 pairs), and an official-layout mask archive: every
    5th pair in av2-api's order, random masks."""
    root = tmp_path_factory.mktemp("av2_synthetic")
    out = str(root / "records")
    manifest = av2.records_manifest(tiny_config)
    pair_records.write_manifest(out, manifest)
    for seed, sweeps in ((1, 12), (2, 7)):
        log_dir = synthetic_av2.write_synthetic_log(str(root / "logs"), synthetic_av2.log_id_for(seed), sweeps, seed,
                                                    points_per_sweep=1200)
        assert av2.write_log_records(log_dir, out, tiny_config, manifest)["pairs"] == sweeps - 1
    examples = {(e[pair_records.SEQUENCE_KEY].decode(), int(e[pair_records.TIMESTAMP_KEY])): e
                for e in _read_records(out, tiny_config)}
    chosen = sorted(examples)[::5]
    rng = np.random.default_rng(2)
    official = {k: rng.random(len(examples[k]["points_xyz_t0"])) < 0.5 for k in chosen}
    masks = official_mask_archive(root / "val-masks.zip", official)
    return out, examples, official, masks


def _spec_columns(zip_path: str, entry: str) -> dict:
    """A submission file read as its specification describes it: {column: NumPy}."""
    with zipfile.ZipFile(zip_path) as zf:
        table = feather.read_table(pa.BufferReader(zf.read(entry)))
    return {c: table.column(c).to_numpy(zero_copy_only=False) for c in table.schema.names}


@pytest.mark.parametrize("leaderboard", ["v1", "v2", "v3"])
def test_a_submission_follows_the_official_masks_and_scores_zero(synthetic_split, tiny_config, tmp_path, leaderboard):
    records, examples, official, masks = synthetic_split
    zip_path = str(tmp_path / "submission.zip")
    summary = write_av2_submission(_records_cfg(tiny_config), pairs.list_segment_files(records), _Labels(), zip_path,
                                   leaderboard, "val", masks=masks, log_fn=lambda s: None)
    with zipfile.ZipFile(zip_path) as zf:
        names = sorted(n for n in zf.namelist() if n.endswith(".feather"))
        meta = zf.read("metadata.json") if leaderboard == "v2" else None
    if leaderboard == "v2":  # the 2024 evaluator's sweeps: indices 0, 5, 10, ... of each log, every point
        by_log = {}
        for key in sorted(examples):
            by_log.setdefault(key[0], []).append(key)
        chosen = {f"{log}/{i:010d}.feather": keys[i] for log, keys in by_log.items() for i in range(0, len(keys), 5)}
        assert len(chosen) == 3 + 2 and json.loads(meta) == {"Is Supervised?": True}
    else:  # the mask archive's sweeps, named by timestamp
        chosen = {f"{k[0]}/{k[1]}.feather": k for k in official}
    assert names == sorted(chosen) and summary["sweeps"] == len(chosen)
    acc = metrics_av2.AV2FlowAccumulator()
    for entry, key in chosen.items():
        ex, got = examples[key], _spec_columns(zip_path, entry)
        p = ex["points_xyz_t0"].astype(np.float64)
        truth = challenge_flow_m(ex["flow_mps_t0"], ex)  # ego-motion-free, metres, sweep-0 ego frame
        rows = official[key] if leaderboard == "v1" else np.ones(len(p), bool)
        flow = np.stack([got[c] for c in ("flow_tx_m", "flow_ty_m", "flow_tz_m")], -1).astype(np.float64)
        assert len(flow) == int(rows.sum())  # one row per mask point (v1) or per point (v2, v3), in point order
        if leaderboard == "v1":  # (the point at the next sweep, in its ego frame) - p: back to the sweep-0 frame
            ego0_from_ego1 = np.linalg.inv(ex["pose_t0"]) @ ex["pose_tm1"]
            q = np.c_[p[rows] + flow, np.ones(len(flow))] @ ego0_from_ego1.T
            flow = q[:, :3] - p[rows]
            np.testing.assert_array_equal(got["is_dynamic"], np.linalg.norm(truth[rows], axis=1) >= 0.05)
        assert list(got) == {"v1": ["flow_tx_m", "flow_ty_m", "flow_tz_m", "is_dynamic"],
                             "v2": ["is_valid", "flow_tx_m", "flow_ty_m", "flow_tz_m"],
                             "v3": ["flow_tx_m", "flow_ty_m", "flow_tz_m"]}[leaderboard]
        np.testing.assert_allclose(flow, truth[rows], atol=2e-3)  # float16 rounding
        acc.update(truth[rows], flow, ex["category_t0"][rows])
    assert acc.result()["three_way/mean_epe_m"] < 1e-3


def test_submission_refusals_and_resume(synthetic_split, tiny_config, tmp_path):
    records, examples, official, masks = synthetic_split
    cfg, files = _records_cfg(tiny_config), pairs.list_segment_files(records)
    with pytest.raises(ValueError, match="test submission needs the official masks.*3d_scene_flow"):
        write_av2_submission(cfg, files, _Labels(), str(tmp_path / "t.zip"), "v1", "test", log_fn=lambda s: None)
    # av2-api's format JSON: the entries and v1's row counts must be the masks'.
    fmt = tmp_path / "val_submission_format.json"
    fmt.write_text(json.dumps({f"{k[0]}/{k[1]}.feather": int(m.sum()) for k, m in official.items()}))
    out = str(tmp_path / "s.zip")
    assert write_av2_submission(cfg, files, _Labels(), out, "v1", "val", masks=masks, format_json=str(fmt),
                                log_fn=lambda s: None)["sweeps"] == len(official)
    first = min(official)
    fmt.write_text(json.dumps({**json.loads(fmt.read_text()), f"{first[0]}/{first[1]}.feather": 1}))
    with pytest.raises(SubmissionFormatError, match="1 rows expected, the official mask selects") as e:
        write_av2_submission(cfg, files, _Labels(), out, "v1", "val", masks=masks, format_json=str(fmt),
                             log_fn=lambda s: None)
    assert e.value.path == f"{fmt}:{first[0]}/{first[1]}.feather"
    # A successful run leaves no folder of parts behind: the next run writes every sweep again.
    assert not os.path.exists(out + ".parts")
    # An interrupted run (here: its archive refused by the format JSON after every sweep was written) leaves its
    # sweeps with its fingerprint.
    fmt.write_text(json.dumps({f"{k[0]}/{k[1]}.feather": int(m.sum()) + 1 for k, m in official.items()}))
    labels = {"kind": "labels"}
    with pytest.raises(SubmissionFormatError, match="rows"):
        write_av2_submission(cfg, files, _Labels(), out, "v1", "val", log_fn=lambda s: None, format_json=str(fmt),
                             model=labels)
    assert sorted(os.listdir(out + ".parts")) == sorted({"fingerprint.json", *(k[0] for k in official)})
    # A run of another model, or over other masks, refuses that folder, naming what differs.
    for other, differs in (({"model": {"kind": "another"}}, "model.kind"), ({"masks": masks}, "masks")):
        with pytest.raises(SubmissionFormatError, match=f"written by another run \\({differs}:") as e:
            write_av2_submission(cfg, files, _Labels(), out, "v1", "val", log_fn=lambda s: None,
                                 **{"model": labels, **other})
        assert e.value.path == os.path.join(out + ".parts", "fingerprint.json")
    # The same run again keeps its sweeps (resume), then removes the folder.
    seen = []
    write_av2_submission(cfg, files, _Labels(), out, "v1", "val", log_fn=seen.append, model=labels)
    assert any(f"{len(official)} already written" in s for s in seen), seen
    assert not os.path.exists(out + ".parts")
    # Without masks on val: av2-api's rule, with a loud note.
    seen = []
    summary = write_av2_submission(cfg, files, _Labels(), str(tmp_path / "rule.zip"), "v1", "val",
                                   log_fn=seen.append)
    assert "local validation only" in seen[0]
    assert summary["notes"] and "local validation only" in summary["notes"][0]
    assert summary["sweeps"] == len(official)  # the same every-5th subset the archive above holds
