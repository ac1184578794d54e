"""The self-supervision preparation job (DUFOMap over each log, HDBSCAN clusters of each sweep's dynamic points) and
the enrichment job it runs on: fields per sweep, one value per sweep wherever the records hold it, bad logs named
alone, finished logs intact, resume."""
import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("dufomap")
pytest.importorskip("hdbscan")

from ff3d_tf import schema  # noqa: E402
from ff3d_tf.config import load_config  # noqa: E402
from ff3d_tf.data import beam_job, pair_records  # noqa: E402
from ff3d_tf.data.wod import write_records  # noqa: E402
from ff3d_tf.labels import enrich_records, self_supervision  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SETS = ("selfsup.num_threads=1", "selfsup.sensor_origin_m=[1.43, 0, 2.18]")  # the synthetic TOP lidar's position


def _segment(tmp, name, seed, frames=5):
    from ff3d_tf.data.synthetic import wod as synthetic
    path = os.path.join(tmp, f"segment-{name}.tfrecord")
    synthetic.write_segment(path, synthetic.SegmentSpec(seed=seed, num_frames=frames, lidar_scale=0.25))
    return path


def _records(segments, out, cfg):
    manifest = write_records.wod_manifest(cfg)
    pair_records.write_manifest(out, manifest)
    for segment in segments:
        write_records.write_segment(segment, out, cfg, manifest)
    return sorted(os.path.join(out, f) for f in os.listdir(out) if f.endswith(pair_records.FILE_SUFFIX)), manifest


def _read(path):
    manifest = pair_records.read_manifest(os.path.dirname(path))
    return [ex for _, ex in enrich_records.read_examples(path, manifest, False, {})]


@pytest.fixture(scope="module")
def prepared(tiny_config, tmp_path_factory):
    """Records of 3 sweeps (stack) of two synthetic segments, and their preparation."""
    tmp = str(tmp_path_factory.mktemp("selfsup"))
    cfg = load_config(None, [f"{k}={v}" for k, v in ()] + list(SETS) + ["data.num_frames=3", "model.temporal=stack"])
    segments = [_segment(tmp, "a", 7), _segment(tmp, "b", 8)]
    files, manifest = _records(segments, os.path.join(tmp, "records"), cfg)
    out = os.path.join(tmp, "prepared")
    counts = self_supervision.run_preparation_job(files, out, cfg)
    return files, out, counts, cfg


def test_every_sweep_of_every_record_gets_its_sweeps_values(prepared):
    files, out, counts, _ = prepared
    manifest = pair_records.read_manifest(out)
    fields = ("dynamic_cluster_t0", "dynamic_cluster_tm1", "dynamic_cluster_tm2")
    assert manifest.extras[-3:] == fields and manifest.num_frames == 3
    assert counts["logs"] == 2 and counts["sweeps"] == 10 and counts["records"] == 8 and counts["clusters"] > 0
    for path in files:
        got, inp = _read(os.path.join(out, os.path.basename(path))), _read(path)
        assert len(got) == len(inp) == 4
        by_time = {}
        for g, i in zip(got, inp):
            for k in i:  # every input field kept, unchanged
                np.testing.assert_array_equal(g[k], i[k], err_msg=k)
            by_time[int(g[pair_records.TIMESTAMP_KEY])] = g["dynamic_cluster_t0"]
        for r, g in enumerate(got):
            # the partner (t-1) and the t-2 cloud hold the values of the same sweep where it is a t0; records whose
            # history starts before the log hold its first sweep there
            partner = int(g[pair_records.PARTNER_TIMESTAMP_KEY])
            if partner in by_time:
                np.testing.assert_array_equal(g["dynamic_cluster_tm1"], by_time[partner])
            if r >= 1:
                np.testing.assert_array_equal(g["dynamic_cluster_tm2"], got[r - 1]["dynamic_cluster_tm1"])
            for k in fields:
                v = g[k]
                assert v.min() >= schema.DYNAMIC_CLUSTER_GROUND
                assert len(v) == len(g[schema.cloud_keys(k[len("dynamic_cluster_"):])["xyz"]])


def test_dynamic_flags_find_the_movers_and_clusters_are_hdbscans(prepared):
    """Against the synthetic truth (|flow| >= 0.5 m/s, not ground): most flagged points move; clusters are the
    sweep's dynamic points clustered again by HDBSCAN with the job's settings (an independent call)."""
    import hdbscan
    files, out, _, cfg = prepared
    flagged = moving = both = 0
    for path in files:
        for g in _read(os.path.join(out, os.path.basename(path))):
            value = g["dynamic_cluster_t0"]
            dynamic = value >= schema.DYNAMIC_CLUSTER_NOISE
            truth = (np.linalg.norm(g["flow_mps_t0"], axis=1) >= schema.MOVING_THRESHOLD_MPS) & \
                (value != schema.DYNAMIC_CLUSTER_GROUND)
            flagged, moving, both = flagged + dynamic.sum(), moving + truth.sum(), both + (dynamic & truth).sum()
            if dynamic.sum() >= cfg.selfsup.cluster_min_points:
                again = hdbscan.HDBSCAN(min_cluster_size=cfg.selfsup.cluster_min_points,
                                        cluster_selection_epsilon=cfg.selfsup.cluster_epsilon_m).fit_predict(
                                            g["points_xyz_t0"][dynamic].astype(np.float64))
                np.testing.assert_array_equal(value[dynamic], again + 1)
    assert both / flagged > 0.8 and both / moving > 0.2, (flagged, moving, both)


def test_a_bad_log_fails_alone_and_finished_logs_stay(prepared, tmp_path):
    """A log with a missing sweep (a record taken out) and one with a non-rigid pose each fail naming file, record
    and field; the good log is written; the rerun skips it (resume)."""
    files, _, _, cfg = prepared
    inp = tmp_path / "in"
    manifest = pair_records.read_manifest(os.path.dirname(files[0]))
    pair_records.write_manifest(str(inp), manifest)
    good = str(inp / os.path.basename(files[0]))
    with open(files[0], "rb") as f, open(good, "wb") as g:
        g.write(f.read())
    examples = _read(files[1])
    gap = str(inp / ("segment-gap" + pair_records.FILE_SUFFIX))
    pair_records.write_records_atomically(gap, [pair_records.serialize_pair(ex, num_frames=3)
                                                for i, ex in enumerate(examples) if i != 1])
    scaled = [dict(ex) for ex in examples]
    scaled[2]["pose_t0"] = scaled[2]["pose_t0"] * np.diag([1.1, 1.1, 1.1, 1.0])
    bent = str(inp / ("segment-pose" + pair_records.FILE_SUFFIX))
    pair_records.write_records_atomically(bent, [pair_records.serialize_pair(ex, num_frames=3) for ex in scaled])
    out = tmp_path / "out"
    with pytest.raises(beam_job.DataJobError) as caught:
        self_supervision.run_preparation_job([good, gap, bent], str(out), cfg)
    failures = "\n".join(caught.value.failures)
    assert "segment-gap" in failures and "record 1: field timestamp_ns_t0" in failures and "missing" in failures
    assert "segment-pose" in failures and "record 2: field pose_t0" in failures
    assert sorted(os.listdir(out)) == sorted(["config.yaml", pair_records.MANIFEST_NAME, os.path.basename(good),
                                              "self_supervision_counts.json"])
    assert _read(str(out / os.path.basename(good)))[0]["dynamic_cluster_t0"].shape[0] > 0
    # skipped and counted instead; the finished log is not done again
    counts = self_supervision.run_preparation_job([good, gap, bent], str(out), cfg, skip_bad_records=True)
    assert counts["already_done"] == 1 and len(counts["bad_logs"]) == 2


def test_a_log_of_one_pair_and_an_empty_log(tiny_config, tmp_path):
    """Two sweeps (one record) are enough; a records file without records is a log of no sweep, named."""
    cfg = load_config(None, list(SETS))
    files, _ = _records([_segment(str(tmp_path), "two", 9, frames=2)], str(tmp_path / "in"), cfg)
    empty = str(tmp_path / "in" / ("segment-empty" + pair_records.FILE_SUFFIX))
    pair_records.write_records_atomically(empty, [])
    with pytest.raises(beam_job.DataJobError) as caught:
        self_supervision.run_preparation_job(files + [empty], str(tmp_path / "out"), cfg)
    assert caught.value.failures == [f"{empty}: {empty}: record unknown: field file: no records: a log needs at "
                                     "least 2 sweeps"]
    (written,) = _read(str(tmp_path / "out" / os.path.basename(files[0])))
    assert set(np.unique(written["dynamic_cluster_t0"])) <= {-2, -1, 0} | set(range(1, 100))


def test_the_tool_names_a_bad_option_and_prepares(prepared, tmp_path):
    files, _, _, _ = prepared
    run = subprocess.run([sys.executable, "tools/prepare_self_supervision.py", "--input", os.path.dirname(files[0]),
                          "--out_dir", str(tmp_path / "o"), "--set", "selfsup.ground=map"], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 1 and "selfsup.ground='map': must be one of auto, records, height" in run.stderr
    run = subprocess.run([sys.executable, "tools/prepare_self_supervision.py", "--input", os.path.dirname(files[0]),
                          "--out_dir", str(tmp_path / "o"), *[a for s in SETS for a in ("--set", s)]], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    manifest = pair_records.read_manifest(str(tmp_path / "o"))
    assert manifest.written_by.startswith("tools/prepare_self_supervision.py --input ")
    assert dataclasses.replace(manifest, written_by="") == dataclasses.replace(
        pair_records.read_manifest(prepared[1]), written_by="")
