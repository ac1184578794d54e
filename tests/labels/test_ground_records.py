"""The ground-mask job over pair records (`ff3d_tf.labels.ground_records`, `tools/add_ground_masks.py`): every sweep of
records of 3 sweeps gets the height rule's mask of its own points, every other field stays; masks the records hold
(Argoverse 2's) are kept bit for bit and only the missing sweeps get the rule; a finished file is skipped and a run
killed between pairs resumes to the same bytes; a bad record stops its file naming file and record, or is skipped and
counted. Small synthetic records written directly (a few hundred points a sweep)."""
import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
import tensorflow as tf

from conftest import ROOT

from ff3d_tf import schema
from ff3d_tf.data import pair_records
from ff3d_tf.data.wod import write_records
from ff3d_tf.data.wod_errors import FrameDecodeError
from ff3d_tf.labels import enrich_records, ground, ground_records

NUM_FRAMES = 3
CLOUDS = schema.sweep_clouds(NUM_FRAMES)  # t0, tm1, tm2
GROUND_KEYS = schema.ground_keys(NUM_FRAMES)  # is_ground_t0, is_ground_tm1, is_ground_tm2


def _sweep(rng, n_ground, n_objects):
    """A road near z = -1.8 m over 16 x 16 m (slightly tilted, a few cm of noise; a few dozen points per column of the
    rule) and objects from 0.8 m above it."""
    road = np.c_[rng.uniform(-8, 8, (n_ground, 2)), np.zeros(n_ground)]
    road[:, 2] = -1.8 + 0.02 * road[:, 0] + rng.normal(0, 0.03, n_ground)
    objects = np.c_[rng.uniform(-6, 6, (n_objects, 2)), rng.uniform(-1.0, 0.5, n_objects)]
    xyz = np.concatenate([road, objects]).astype(np.float32)
    return xyz[rng.permutation(len(xyz))]


def _example(seed, sizes=((300, 40), (280, 50), (260, 30)), av2_masks=False):
    """One record's fields (3 sweeps); with `av2_masks`, random `is_ground_t0`/`is_ground_tm1` standing in for the
    map raster's (not the height rule's, so that a mask recomputed instead of kept shows)."""
    rng = np.random.default_rng(seed)
    ex = {pair_records.TIMESTAMP_KEY: 1_000_000_000 + seed * 100_000_000,
          pair_records.PARTNER_TIMESTAMP_KEY: 900_000_000 + seed * 100_000_000, pair_records.SEQUENCE_KEY: "seq",
          schema.FULL_HISTORY_KEY: seed > 0}
    for cloud, (n_ground, n_objects) in zip(CLOUDS, sizes):
        keys = schema.cloud_keys(cloud)
        xyz = _sweep(rng, n_ground, n_objects) if n_ground + n_objects else np.zeros((0, 3), np.float32)
        ex[keys["xyz"]], ex[keys["features"]] = xyz, rng.random((len(xyz), 2), np.float32)
        ex[keys["pose"]] = np.eye(4)
        ex[keys["pose"]][:3, 3] = [-seed - CLOUDS.index(cloud), 0.0, 0.0]
    n0 = len(ex["points_xyz_t0"])
    ex["flow_mps_t0"] = rng.normal(size=(n0, 3)).astype(np.float32)
    ex["class_id_t0"] = rng.integers(-1, 4, n0).astype(np.int32)
    if av2_masks:
        ex["is_ground_t0"] = rng.random(n0) < 0.5
        ex["is_ground_tm1"] = rng.random(len(ex["points_xyz_tm1_in_t0"])) < 0.5
    return ex


def _write(directory, manifest, examples_by_file):
    pair_records.write_manifest(str(directory), manifest)
    paths = []
    for name, examples in examples_by_file.items():
        path = os.path.join(str(directory), name + pair_records.FILE_SUFFIX)
        pair_records.write_records_atomically(path, [pair_records.serialize_pair(
            ex, manifest.precision, manifest.extras, manifest.num_frames) for ex in examples])
        paths.append(path)
    return paths


def _read(path):
    manifest = pair_records.read_manifest(os.path.dirname(path))
    return [ex for _, ex in enrich_records.read_examples(path, manifest, False, {})]


@pytest.fixture(scope="module")
def wod_manifest(tiny_config):
    """A manifest of WOD records of 3 sweeps without any ground mask."""
    return dataclasses.replace(write_records.wod_manifest(tiny_config), num_frames=NUM_FRAMES)


@pytest.fixture(scope="module")
def wod_records(wod_manifest, tmp_path_factory):
    """Two files of WOD-style records of 3 sweeps (the second file's last record has an empty oldest sweep)."""
    directory = tmp_path_factory.mktemp("wod_records")
    return _write(directory, wod_manifest, {
        "seq_a": [_example(0), _example(1), _example(2)],
        "seq_b": [_example(3), _example(4, sizes=((240, 30), (220, 20), (0, 0)))]})


@pytest.fixture(scope="module")
def wod_job(wod_records, tmp_path_factory):
    """The job (Beam, as the tool runs it) over `wod_records`."""
    out = str(tmp_path_factory.mktemp("wod_ground"))
    return out, ground_records.run_ground_job(wod_records, out, written_by="test")


def test_every_sweep_gets_the_height_rule_and_every_other_field_stays(wod_records, wod_job):
    out, counts = wod_job
    manifest = pair_records.read_manifest(out)
    assert set(GROUND_KEYS) <= set(manifest.extras) and manifest.num_frames == NUM_FRAMES
    assert manifest.extras == GROUND_KEYS  # the input held none: added in slot order
    for path in wod_records:
        got, want = _read(os.path.join(out, os.path.basename(path))), _read(path)
        assert len(got) == len(want) > 0 and not os.path.exists(os.path.join(out, os.path.basename(path) + ".parts"))
        for g, w in zip(got, want):
            assert set(g) == set(w) | set(GROUND_KEYS)
            for k in w:
                np.testing.assert_array_equal(g[k], w[k], err_msg=k)
            for cloud, key in zip(CLOUDS, GROUND_KEYS):
                points = w[schema.cloud_keys(cloud)["xyz"]]
                expected = ground.height_ground_mask(points) if len(points) else np.zeros(0, bool)
                assert g[key].dtype == bool
                np.testing.assert_array_equal(g[key], expected, err_msg=key)
                np.testing.assert_array_equal(g[key], points[:, 2] < -1.3)  # here the road, not the objects
    assert counts["pairs"] == 5 and counts["masks_computed"] == 15 and counts["masks_kept"] == 0
    assert counts["skipped_records"] == 0 and counts["ground_keys_added"] == list(GROUND_KEYS)
    assert counts["points_computed"] == sum(
        len(ex[schema.cloud_keys(c)["xyz"]]) for p in wod_records for ex in _read(p) for c in CLOUDS)


def test_a_rerun_skips_finished_files(wod_records, wod_job):
    out, _ = wod_job
    outputs = [os.path.join(out, os.path.basename(p)) for p in wod_records]
    before = [(os.stat(p).st_mtime_ns, open(p, "rb").read()) for p in outputs]
    counts = ground_records.run_ground_job(wod_records, out, written_by="test again")
    assert counts["already_done"] == 2 and counts.get("pairs", 0) == 0
    assert [(os.stat(p).st_mtime_ns, open(p, "rb").read()) for p in outputs] == before


def test_a_killed_run_resumes_per_pair_to_the_same_bytes(wod_records, wod_manifest, wod_job, tmp_path, monkeypatch):
    out, _ = wod_job
    path, name = wod_records[0], os.path.basename(wod_records[0])
    out_manifest = ground_records.output_manifest(wod_manifest)
    pair_records.write_manifest(str(tmp_path), out_manifest)
    real, calls = ground_records.height_ground_mask, []

    def dies_in_the_second_pair(points):
        calls.append(1)
        if len(calls) == NUM_FRAMES + 2:
            raise KeyboardInterrupt
        return real(points)

    with monkeypatch.context() as m:
        m.setattr(ground_records, "height_ground_mask", dies_in_the_second_pair)
        with pytest.raises(KeyboardInterrupt):
            ground_records.ground_file(path, str(tmp_path), wod_manifest, out_manifest)
    assert not (tmp_path / name).exists()  # no output file until every pair is done
    assert os.listdir(tmp_path / (name + enrich_records.PARTS_SUFFIX)) == ["000000.npz"]
    calls.clear()
    with monkeypatch.context() as m:
        m.setattr(ground_records, "height_ground_mask", lambda points: (calls.append(1), real(points))[1])
        counts = ground_records.ground_file(path, str(tmp_path), wod_manifest, out_manifest)
    assert len(calls) == 2 * NUM_FRAMES and counts["pairs"] == 3  # the first pair was kept from the killed run
    assert (tmp_path / name).read_bytes() == open(os.path.join(out, name), "rb").read()
    assert ground_records.ground_file(path, str(tmp_path), wod_manifest, out_manifest) == {"already_done": 1}


def test_records_own_masks_are_kept_and_the_missing_sweeps_get_the_rule(tiny_config, tmp_path):
    """Argoverse 2 style: the records hold t0's and the partner's masks (the map raster's); the oldest sweep's is
    added."""
    manifest = dataclasses.replace(write_records.wod_manifest(tiny_config), source="av2", partner="next",
                                   num_frames=NUM_FRAMES, extras=("is_ground_t0", "category_t0", "is_ground_tm1"))
    examples = [_example(seed, av2_masks=True) for seed in (5, 6)]
    for ex in examples:
        ex["category_t0"] = np.full(len(ex["points_xyz_t0"]), 2, np.int32)
    (path,) = _write(tmp_path / "in", manifest, {"log": examples})
    out = tmp_path / "out"
    out_manifest = ground_records.output_manifest(manifest)
    assert out_manifest.extras == ("is_ground_t0", "category_t0", "is_ground_tm1", "is_ground_tm2")
    pair_records.write_manifest(str(out), out_manifest)
    counts = ground_records.ground_file(path, str(out), manifest, out_manifest)
    assert counts["pairs"] == 2 and counts["masks_kept"] == 4 and counts["masks_computed"] == 2
    got, want = _read(str(out / "log.pairs.tfrecord")), _read(path)
    for g, w, ex in zip(got, want, examples):
        for k in w:
            np.testing.assert_array_equal(g[k], w[k], err_msg=k)
        for key in ("is_ground_t0", "is_ground_tm1"):  # bit for bit the records' own, not the rule's
            np.testing.assert_array_equal(g[key], ex[key], err_msg=key)
            assert not np.array_equal(g[key], ground.height_ground_mask(
                ex[schema.cloud_keys(schema.POINT_KEYS[key].cloud)["xyz"]]))
        np.testing.assert_array_equal(g["is_ground_tm2"], ground.height_ground_mask(ex["points_xyz_tm2_in_t0"]))


def test_records_holding_every_mask_are_copied(tiny_config, tmp_path):
    manifest = dataclasses.replace(write_records.wod_manifest(tiny_config), source="av2", partner="next",
                                   extras=("is_ground_t0", "is_ground_tm1"))
    examples = [_example(7, av2_masks=True)]
    for ex in examples:
        for k in schema.past_sweep_keys(NUM_FRAMES) + (schema.FULL_HISTORY_KEY,):
            ex.pop(k, None)
    (path,) = _write(tmp_path / "in", manifest, {"log": examples})
    assert ground_records.missing_ground_keys(manifest) == ()
    out_manifest = ground_records.output_manifest(manifest)
    assert out_manifest == manifest
    pair_records.write_manifest(str(tmp_path / "out"), out_manifest)
    counts = ground_records.ground_file(path, str(tmp_path / "out"), manifest, out_manifest)
    assert counts["pairs"] == 1 and counts["masks_kept"] == 2 and counts["masks_computed"] == 0
    (got,), (want,) = _read(str(tmp_path / "out" / "log.pairs.tfrecord")), _read(path)
    assert set(got) == set(want)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def _with_a_bad_record(path, directory, manifest):
    """A copy of the records file `path` (and its manifest) in `directory` whose second record is not a pair
    record."""
    pair_records.write_manifest(str(directory), manifest)
    bad = os.path.join(str(directory), os.path.basename(path))
    with tf.io.TFRecordWriter(bad) as writer:
        for i, record in enumerate(tf.data.TFRecordDataset(path)):
            writer.write(b"not a pair record" if i == 1 else record.numpy())
    return bad


def test_a_bad_record_is_named_or_skipped_and_counted(wod_records, wod_manifest, tmp_path):
    bad = _with_a_bad_record(wod_records[0], tmp_path / "in", wod_manifest)
    out_manifest = ground_records.output_manifest(wod_manifest)
    pair_records.write_manifest(str(tmp_path / "out"), out_manifest)
    with pytest.raises(FrameDecodeError, match="record 1") as err:
        ground_records.ground_file(bad, str(tmp_path / "out"), wod_manifest, out_manifest)
    assert bad in str(err.value)
    assert not (tmp_path / "out" / os.path.basename(bad)).exists()
    counts = ground_records.ground_file(bad, str(tmp_path / "out"), wod_manifest, out_manifest,
                                        skip_bad_records=True)
    assert counts["pairs"] == 2 and counts["skipped_records"] == 1
    assert len(_read(str(tmp_path / "out" / os.path.basename(bad)))) == 2


def test_non_finite_points_are_named():
    ex = _example(8)
    ex["points_xyz_tm2_in_t0"][3, 2] = np.nan
    with pytest.raises(FrameDecodeError, match=r"f\.tfrecord: record 4: field points_xyz_tm2_in_t0: .*non-finite"):
        ground_records.ground_of_record(ex, GROUND_KEYS, "f.tfrecord", 4)


def test_the_tool_names_a_bad_file_then_skips_its_bad_record(wod_records, wod_manifest, tmp_path):
    """tools/add_ground_masks.py: a bad record fails its file alone (exit 1, naming file and record; the good file is
    written); rerun with --skip_bad_records, the good file is skipped and the bad one written without the record."""
    inp = tmp_path / "in"
    bad = _with_a_bad_record(wod_records[1], inp, wod_manifest)
    good = os.path.join(str(inp), "good" + pair_records.FILE_SUFFIX)
    with open(wod_records[0], "rb") as src, open(good, "wb") as dst:
        dst.write(src.read())
    out = tmp_path / "out"
    command = [sys.executable, "tools/add_ground_masks.py", "--data_dir", str(inp), "--out_dir", str(out)]
    first = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert first.returncode == 1, first.stderr[-3000:]
    assert f"error: {bad}: {bad}: record 1: " in first.stderr and "Traceback" not in first.stderr
    assert (out / "good.pairs.tfrecord").exists() and not (out / os.path.basename(bad)).exists()
    second = subprocess.run(command + ["--skip_bad_records"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "'already_done': 1" in second.stdout and "'skipped_records': 1" in second.stdout
    assert "added by the height rule: is_ground_t0, is_ground_tm1, is_ground_tm2" in second.stdout
    assert len(_read(str(out / os.path.basename(bad)))) == 1
    assert pair_records.read_manifest(str(out)).extras == GROUND_KEYS
