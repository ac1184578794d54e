"""tools/pseudo_label.py on Argoverse 2 records of 3 sweeps: it fits every pair, writes the records and scores them
against Argoverse's labels, reading the sweeps per example from the records' manifest, not from the config (whose
`data.num_frames` is the default 2 here)."""
import json
import os
import subprocess
import sys

from ff3d_tf.config import TINY_OVERRIDES, load_config
from ff3d_tf.data import pair_records
from ff3d_tf.labels import av2, pseudo_records

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")
# a small fit on the points within 8 m: the job's bookkeeping, not the fit's quality
SMALL_FIT = ("nsfp.max_iterations=8", "nsfp.patience=8", "nsfp.segment_iterations=4", "nsfp.grid_cell_m=0.5",
             "nsfp.crop_xy_half_extent_m=8", "nsfp.hidden_layers=2", "nsfp.hidden_units=32", "nsfp.retries=0",
             "nsfp.fit_every=16")


def test_records_of_three_sweeps_are_labelled_and_scored(tmp_path):
    cfg = load_config(None, list(TINY_OVERRIDES) + ["data.num_frames=3", "model.temporal=stack"])
    records = str(tmp_path / "records")
    manifest = av2.records_manifest(cfg)
    pair_records.write_manifest(records, manifest)
    counts = av2.write_log_records(AV2_LOG, records, cfg, manifest)
    assert counts["pairs"] == counts["pairs_without_full_history"] == 1  # 2 sweeps: sweep 0's history is its own
    out = tmp_path / "pseudo"
    run = subprocess.run([sys.executable, "tools/pseudo_label.py", "--input", records, "--out_dir", str(out),
                          *[a for s in SMALL_FIT for a in ("--set", s)]], cwd=ROOT, capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert pair_records.read_manifest(str(out)).num_frames == 3
    scores = json.loads((out / pseudo_records.SCORES_NAME).read_text())
    assert scores["pairs"] == 1 and scores["evaluated_points"] > 0
    assert "three_way/mean_epe_m" in scores["nsfp"] and "three_way/mean_epe_m" in scores["zero_flow"]
