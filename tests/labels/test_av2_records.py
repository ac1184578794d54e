"""Argoverse 2 challenge pair records (sweep t with the next sweep): on the real sample log they reproduce Argoverse's
own flow labels, categories and ground mask; the job resumes; a bad log is named."""
import os

import numpy as np
import pyarrow.feather as feather
import pytest

from conftest import AV2_LOG
from ff3d_tf import schema
from ff3d_tf.config import replace_config
from ff3d_tf.data import pair_records, pairs
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.labels import av2


def _read(out, cfg):
    cfg = replace_config(cfg, {"data.source": "pair_records", "data.crop_to_grid": False})
    return [{k: v.numpy() for k, v in ex.items()} for ex in
            pairs.pair_dataset(pairs.list_segment_files(out), cfg, extras=av2.AV2_EXTRAS, metadata=True)]


def test_sample_record_reproduces_argoverses_labels(av2_sample_records, tiny_config):
    (ex,) = _read(av2_sample_records, tiny_config)
    table = feather.read_table(os.path.join(AV2_LOG, "flow_labels.feather"))
    labels = {name: table.column(name).to_numpy() for name in ("classes", "is_ground_0", "dynamic")}
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    assert (ex[pair_records.TIMESTAMP_KEY], ex[pair_records.PARTNER_TIMESTAMP_KEY]) == tuple(stamps)
    assert ex[pair_records.SEQUENCE_KEY].decode() == os.path.basename(AV2_LOG)
    # t0 = sweep 0, every point, in file order; the partner is sweep 1 moved into sweep 0's frame.
    sweep0 = argoverse2.read_sweep(AV2_LOG, stamps[0])["points_xyz"]
    np.testing.assert_array_equal(ex["points_xyz_t0"], sweep0)
    assert len(ex["points_xyz_tm1_in_t0"]) == len(argoverse2.read_sweep(AV2_LOG, stamps[1])["points_xyz"])
    # The challenge's flow (ego-free displacement to sweep 1) is -flow_mps_t0 * dt: compare with Argoverse's labels.
    dt_s = (stamps[1] - stamps[0]) * 1e-9
    want_m, _ = argoverse2.argoverse_flow_in_paper_convention(AV2_LOG)
    got_m = -ex["flow_mps_t0"].astype(np.float64) * dt_s
    close = np.linalg.norm(got_m - want_m, axis=1) < 0.001
    assert close.mean() > 0.9995, close.mean()  # measured 99.987%; every dynamic point:
    assert close[labels["dynamic"]].all()
    # Categories: Argoverse's `classes` column (0 = no cuboid, i + 1 = category i).
    agree = ex["category_t0"] == labels["classes"]
    assert agree.mean() > 0.9999, agree.mean()  # measured 99.996%
    assert set(np.unique(ex["category_t0"])) >= {0, argoverse2.scene_flow_category_index("REGULAR_VEHICLE")}
    # Ground: the log's raster (one point of 99,229 differs, see argoverse2.is_ground).
    assert np.sum(ex["is_ground_t0"] != labels["is_ground_0"]) <= 1
    # Paper classes of the moving points: vehicles, not background.
    moving = np.linalg.norm(want_m, axis=1) > 0.05
    assert np.mean(ex["class_id_t0"][moving] == schema.CLASS_VEHICLE) > 0.5


def test_job_resumes_and_names_a_bad_log(av2_sample_records, tiny_config, tmp_path):
    manifest = av2.records_manifest(tiny_config)
    assert av2.write_log_records(AV2_LOG, av2_sample_records, tiny_config, manifest) == {"already_done": 1}
    assert av2.list_logs(AV2_LOG) == [AV2_LOG]
    assert av2.list_logs(os.path.dirname(AV2_LOG)) == [AV2_LOG]
    with pytest.raises(FileNotFoundError, match="no Argoverse 2 logs"):
        av2.list_logs(str(tmp_path))
    bad = tmp_path / "bad_log"
    (bad / "sensors" / "lidar").mkdir(parents=True)
    for name in ("315966265259836000.feather", "315966265360032000.feather"):
        (bad / "sensors" / "lidar" / name).write_bytes(b"not feather")
    with pytest.raises(argoverse2.Argoverse2FormatError) as err:
        av2.write_log_records(str(bad), str(tmp_path / "out"), tiny_config, manifest)
    assert err.value.path.endswith("315966265259836000.feather") and err.value.column == "file"
    assert not os.listdir(tmp_path / "out")  # nothing half-written
    skip_cfg = replace_config(tiny_config, {"data.skip_bad_records": True})
    counts = av2.write_log_records(str(bad), str(tmp_path / "out"), skip_cfg, manifest)
    assert counts["pairs"] == 0 and counts["skipped_pairs"] == 1


def test_a_missing_sweep_is_named_before_any_work(tiny_config, tmp_path):
    """The sample log with its second sweep 0.3 s after the first (a sweep missing between them): the log fails
    naming that sweep and the gap, before a record is written; skip_bad_records skips the one pair across it."""
    import shutil
    log = str(tmp_path / os.path.basename(AV2_LOG))
    shutil.copytree(AV2_LOG, log)
    first, second = argoverse2.sweep_timestamps(log)
    late = first + 300_000_000
    lidar = os.path.join(log, "sensors", "lidar")
    os.rename(os.path.join(lidar, f"{second}.feather"), os.path.join(lidar, f"{late}.feather"))
    manifest = av2.records_manifest(tiny_config)
    out = str(tmp_path / "out")
    os.makedirs(out)
    with pytest.raises(argoverse2.Argoverse2FormatError, match=f"at {late} ns comes 0.300 s after {first}.feather"
                       ) as err:
        av2.write_log_records(log, out, tiny_config, manifest)
    assert err.value.path == os.path.join(lidar, f"{late}.feather") and err.value.column == "timestamp_ns"
    assert not os.listdir(out)
    counts = av2.write_log_records(log, out, replace_config(tiny_config, {"data.skip_bad_records": True}), manifest)
    assert counts["pairs"] == 0 and counts["skipped_pairs"] == 1


def test_an_empty_sweep_is_named(tiny_config, tmp_path):
    import shutil
    import pyarrow as pa
    log = tmp_path / "log"
    shutil.copytree(AV2_LOG, log)
    sweep = log / "sensors" / "lidar" / f"{argoverse2.sweep_timestamps(AV2_LOG)[1]}.feather"
    table = feather.read_table(str(sweep))
    feather.write_feather(pa.Table.from_batches([], schema=table.schema), str(sweep))
    with pytest.raises(argoverse2.Argoverse2FormatError, match="empty sweep") as err:
        av2.challenge_pair(str(log), 0, tiny_config)
    assert err.value.path == str(sweep)


def test_sample_record_holds_each_points_cuboid(av2_sample_records, tiny_config):
    """`instance_id_t0`: the cuboid of each t0 point (its index among the sweep's cuboids), -1 outside every cuboid:
    exactly the points with a category, one category per cuboid."""
    (ex,) = _read(av2_sample_records, tiny_config)
    ids, category = ex["instance_id_t0"], ex["category_t0"]
    assert ids.dtype == np.int32
    np.testing.assert_array_equal(ids >= 0, category > 0)
    cuboids = argoverse2.cuboids(AV2_LOG, argoverse2.sweep_timestamps(AV2_LOG)[0])
    assert ids.max() < len(cuboids["heading"])
    for k in np.unique(ids[ids >= 0]):
        (cat,) = np.unique(category[ids == k])
        assert cat == argoverse2.scene_flow_category_index(str(cuboids["category"][k]))
