"""NSFP as a predictor (`ff3d_tf.labels.nsfp_predictor`): the fit of the pseudo-label job on one pair, its gap from the
pair's times or the default, ground predicted static, points outside the fitted region without a prediction; and
`tools/predict.py --method nsfp` on a sweeps directory, no model."""
import subprocess
import sys

import numpy as np

from conftest import ROOT
from ff3d_tf.data import pair_records
from ff3d_tf.labels import nsfp_predictor, pseudo_records
from ff3d_tf.labels.nsfp import NsfpOptions

RNG = np.random.default_rng(4)


def _scene(shift_m):
    """Ground (z = -1.6 m, 20 m around), a 4 x 2 x 1.5 m box of points at x = 8 + shift, and 3 far points."""
    ground = np.concatenate([RNG.uniform(-20, 20, (1500, 2)), np.full((1500, 1), -1.6)], 1)
    box = RNG.uniform([-2, -1, -1.4], [2, 1, 0.1], (600, 3)) + [8.0 + shift_m, 3.0, 0.0]
    far = np.array([[60.0, 0, 0], [0, -50.0, 0], [3, 3, 8.0]])
    return np.concatenate([ground, box, far]).astype(np.float32)


JOB = pseudo_records.JobOptions(NsfpOptions(max_iterations=60, patience=100, fit_every=1, segment_iterations=30,
                                            crop_xy_half_extent_m=35.0, crop_z_range_m=(-3.0, 3.0),
                                            learning_rate=5e-3, point_bucket_base=256))


def test_the_fit_of_a_pair(tmp_path):
    t0, tm1 = _scene(0.5), _scene(0.0)  # the box moved 0.5 m along +x
    lines = []
    predictor = nsfp_predictor.NsfpPredictor(JOB, default_gap_s=0.1, log=lines.append)
    example = {"points_xyz_t0": t0, "points_xyz_tm1_in_t0": tm1, "num_points_t0": len(t0),
               "num_points_tm1": len(tm1)}
    flow, valid = predictor.predict({}, example)
    assert flow.shape == t0.shape and flow.dtype == np.float32 and valid.shape == (len(t0),)
    assert not valid[-3:].any() and not flow[-3:].any()  # outside the fitted region: no prediction
    ground = slice(0, 1500)
    assert valid[ground].mean() > 0.95 and not flow[ground][valid[ground]].any()  # ground: predicted static
    assert valid[1500:2100].all()
    box_x = flow[1500:2100, 0]
    assert np.median(box_x) > 0.5  # moving along +x (5 m/s at the end of a full fit; 60 steps here)
    assert any(line.startswith("nsfp pair 0:") and "ground by height" in line for line in lines)
    # The gap: the pair's times where the example carries them; the flow is the same motion over the gap.
    example[pair_records.TIMESTAMP_KEY], example[pair_records.PARTNER_TIMESTAMP_KEY] = 1_200_000_000, 1_000_000_000
    assert predictor.gap_s(example) == 0.2
    flow_02, valid_02 = predictor.predict({}, example)
    np.testing.assert_array_equal(valid_02, valid)
    np.testing.assert_allclose(flow_02 * 0.2, flow * 0.1, atol=1e-4)


def test_predict_tool_with_nsfp_and_no_model(tmp_path):
    d = tmp_path / "scans"
    d.mkdir()
    for k, shift in enumerate((0.0, 0.5)):
        np.save(d / f"{k:06d}.npy", _scene(shift))
    (d / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
    out = tmp_path / "out"
    sets = ["--set", "nsfp.max_iterations=30", "--set", "nsfp.segment_iterations=30", "--set",
            "nsfp.point_bucket_base=256", "--set", "nsfp.fit_every=1"]
    run = subprocess.run([sys.executable, "tools/predict.py", "--method", "nsfp", "--sweeps_dir", str(d),
                          "--out_dir", str(out), "--sweep_period_s", "0.05", *sets],
                         cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "sweep times from a sweep every 0.05 s" in run.stdout and "gap 0.0500 s" in run.stdout
    with np.load(out / "000001.npz") as z:
        assert z["flow_mps"].shape == (2103, 3) and z["point_valid"][:2100].mean() > 0.9
    assert (out / "000001.feather").exists() and (out / "000001_bev.png").exists()
    bad = subprocess.run([sys.executable, "tools/predict.py", "--sweeps_dir", str(d), "--out_dir", str(out)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "--method model needs --checkpoint" in bad.stderr
