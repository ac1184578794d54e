"""Real LiDAR as your own files: the Argoverse 2 sample log's two sweeps written as a sweeps directory with a box
table (`ff3d_tf.labels.av2_sequences`) give records whose labels are the Argoverse 2 path's; and NSFP without a
model (`tools/predict.py --method nsfp`, no map: ground by the height rule) on the pair as plain files scores, by the
challenge's arithmetic over its 35 m box, what benchmarks/own_records_cpu.json (and docs/datasets.md) say."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import AV2_LOG, ROOT
from ff3d_tf.data import pair_records
from ff3d_tf.data.av2 import argoverse2
from ff3d_tf.data.files import box_table
from ff3d_tf.labels import av2, av2_sequences, own_records
from ff3d_tf.labels.box_flow import bootstrap_flow

BENCH = os.path.join(ROOT, "benchmarks", "own_records_cpu.json")


def test_the_sample_log_as_files_is_labelled_as_the_av2_path_labels_it(tiny_config, tmp_path):
    seq = av2_sequences.write_log_as_sequence(AV2_LOG, str(tmp_path / "log"))
    class_map = box_table.read_class_map(os.path.join(seq, av2_sequences.CLASS_MAP_NAME))
    options = own_records.OwnRecordsOptions(class_map=tuple(class_map.items()))
    out = str(tmp_path / "records")
    counts = own_records.run_records_job([seq], out, tiny_config, options)
    assert counts["pairs"] == 1
    manifest = pair_records.read_manifest(out)
    (path,) = [os.path.join(out, f) for f in os.listdir(out) if f.endswith(pair_records.FILE_SUFFIX)]
    (ex,) = [{k: v.numpy() for k, v in e.items()} for e in
             pair_records.records_dataset(path, manifest, own_records.OWN_EXTRAS)]
    # The Argoverse 2 path's labelled pair (sweep 0 -> sweep 1, the paper's rule, `av2.labelled_pair`).
    f_tm1, f_t0 = av2.labelled_pair(AV2_LOG, 1)
    np.testing.assert_array_equal(ex["points_xyz_t0"], f_t0["points_xyz"])
    np.testing.assert_array_equal(ex["point_features_t0"][:, 0], f_t0["intensity"])  # uint8 / 255, as the reader
    same = (ex["class_id_t0"] == f_t0["class_id"]) & (
        np.linalg.norm(ex["flow_mps_t0"] - f_t0["flow_mps"], axis=1) < 1e-3)
    share = same.mean()
    assert share >= 0.999, share
    objects = f_t0["class_id"] > 0
    assert objects.sum() > 5000 and same[objects].mean() >= 0.999
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    _, _, owner = bootstrap_flow(f_t0["points_xyz"], argoverse2.cuboids(AV2_LOG, stamps[1]),
                                 argoverse2.cuboids(AV2_LOG, stamps[0]), f_t0["pose"], f_tm1["pose"],
                                 (stamps[1] - stamps[0]) * 1e-9, with_instances=True)
    assert np.mean(ex["instance_id_t0"] == owner) >= 0.999
    assert (int(ex[pair_records.TIMESTAMP_KEY]), int(ex[pair_records.PARTNER_TIMESTAMP_KEY])) == (stamps[1], stamps[0])
    if os.path.exists(BENCH):  # the figure docs/datasets.md quotes
        with open(BENCH) as f:
            bench = json.load(f)["av2_sample_as_files"]["labels"]
        assert bench["same_label_share"] == pytest.approx(share) and bench["points"] == len(same)


@pytest.mark.slow
def test_nsfp_without_a_model_on_the_sample_pair_as_files(tmp_path):
    """`tools/predict.py --method nsfp` on the pair as two point files with their poses (t0: sweep 0, its partner
    sweep 1, as the challenge pairs them), no map: the three-way EPE by the challenge's arithmetic is the benchmark's
    (the fit is deterministic on one machine; other CPUs round differently) and well below zero flow's."""
    pair = av2_sequences.write_log_as_sequence(AV2_LOG, str(tmp_path / "pair"), with_boxes=False, pose_files=True)
    stamps = argoverse2.sweep_timestamps(AV2_LOG)
    gap_s = (stamps[1] - stamps[0]) * 1e-9
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "tools/predict.py", "--method", "nsfp",
                          "--points_tm1", os.path.join(pair, "000001.npy"), "--points_t0", os.path.join(pair, "000000.npy"),
                          "--pose_tm1", os.path.join(pair, "000001.pose.txt"),
                          "--pose_t0", os.path.join(pair, "000000.pose.txt"),
                          "--sweep_period_s", repr(gap_s), "--out_dir", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=3600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "nsfp pair 0:" in run.stdout and "ground by height" in run.stdout
    with np.load(out / "000000.npz") as z:
        flow, valid = z["flow_mps"], z["point_valid"]
    scores = av2_sequences.challenge_scores(AV2_LOG, 0, flow, valid, gap_s)
    three_way = scores["prediction"]["three_way/mean_epe_m"]
    with open(BENCH) as f:
        documented = json.load(f)["av2_sample_as_files"]["nsfp"]["three_way_epe_m"]
    assert abs(three_way - documented) <= 0.01, (documented, scores)
    assert three_way < 0.5 * scores["zero_flow"]["three_way/mean_epe_m"]
