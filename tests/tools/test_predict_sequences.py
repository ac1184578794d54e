"""tools/predict.py on a user's sweeps directory with models of three sweeps (`model.temporal=delta`), as a user calls
it: every sweep with a partner gets the model's flow on the clouds of its slots, moved into its frame by NumPy (the
sweeps at the directory's start read its first sweep for those they lack, as evaluation reads a log); a sweep missing
from timestamps.txt stops the tool with one line naming it, as tools/write_pair_records.py does, unless
data.skip_bad_records; a model of Argoverse 2 challenge records (data.partner=next, saved with it) is fed each sweep
with the NEXT one, and its flow is written as the velocity."""
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, TINY_OVERRIDES
from ff3d_tf import geometry, schema

SETS = (*TINY_OVERRIDES, "data.num_frames=3", "model.temporal=delta")
TIMES_S = (0.0, 0.1, 0.2, 0.4, 0.5)  # a sweep is missing between the third and the fourth


def _sweeps(tmp_path):
    """Five sweeps (random clouds, rigid poses) and their times, with a gap of 0.2 s before sweep 3."""
    rng = np.random.default_rng(5)
    d = tmp_path / "log"
    d.mkdir()
    clouds = [rng.uniform([-35, -35, -2], [35, 35, 2], (n, 3)).astype(np.float32) for n in (120, 140, 130, 150, 110)]
    poses = [geometry.box_matrices_np((1.0 * k, 0.3 * k, 0.0), 0.04 * k)[0] for k in range(len(clouds))]
    for k, cloud in enumerate(clouds):
        np.save(d / f"{k:06d}.npy", cloud)
    (d / "poses.txt").write_text("".join(" ".join(repr(float(v)) for v in p[:3].reshape(-1)) + "\n" for p in poses))
    (d / "timestamps.txt").write_text("".join(f"{t:.1f}\n" for t in TIMES_S))
    return d, clouds, poses


def _model(tmp_path, sets):
    """A checkpoint of the tiny model of `sets`, its config saved beside it (as training leaves a model_dir)."""
    import tensorflow as tf
    from ff3d_tf.config import load_config
    from ff3d_tf.model import build_model
    cfg = load_config(None, sets)
    model = build_model(cfg, compile_mode="none")
    prefix = tf.train.Checkpoint(model=model).save(str(tmp_path / "model" / "ckpt"))
    cfg.save(str(tmp_path / "model" / "config.yaml"))
    return model, prefix


def _predict(prefix, d, out, *extra):
    return subprocess.run([sys.executable, "tools/predict.py", "--checkpoint", prefix, "--sweeps_dir", str(d),
                           "--out_dir", str(out), *extra], cwd=ROOT, capture_output=True, text=True, timeout=600)


def _expected_flow(model, clouds, poses, slots):
    """The model's flow for sweep slots[0] with the sweeps `slots` in its slots (t0, tm1, tm2), each past cloud moved
    into the t0 frame by its own pose (NumPy)."""
    inputs = {}
    for cloud, k in zip(schema.sweep_clouds(len(slots)), slots):
        keys, xyz = schema.cloud_keys(cloud), clouds[k].astype(np.float64)
        moved = geometry.transform_points_np(xyz, np.linalg.inv(poses[slots[0]]) @ poses[k])
        inputs.update({keys["xyz"]: moved[None].astype(np.float32),
                       keys["features"]: np.zeros((1, len(xyz), 2), np.float32),  # no intensity column: 0
                       keys["mask"]: np.ones((1, len(xyz)), bool)})
    return model(inputs)["flow_mps"][0].numpy()


def test_a_sweeps_directory_of_a_three_sweep_model(tmp_path):
    d, clouds, poses = _sweeps(tmp_path)
    model, prefix = _model(tmp_path, SETS)
    # The missing sweep: one line of the tool's own, naming the sweep file and its time, before any prediction.
    run = _predict(prefix, d, tmp_path / "refused")
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr[-3000:]
    assert run.stderr.strip().splitlines()[-1] == (
        f"error: {d / '000003.npy'}: timestamp: the sweep at 400000000 ns comes 0.200 s after 000002.npy "
        "(timestamps.txt), more than data.max_frame_gap_s = 0.15 s: a sweep is missing (data.skip_bad_records=true "
        "skips the examples across the gap)")
    assert not list((tmp_path / "refused").glob("*.npz"))
    # Skipping it: the sweeps each side are two sequences; every sweep with one before it in its sequence is
    # predicted, the second of each reading the sequence's first sweep in its oldest slot.
    run = _predict(prefix, d, tmp_path / "out", "--set", "data.skip_bad_records=true")
    assert run.returncode == 0, run.stderr[-3000:]
    assert "5 sweeps, 3 examples of 3 sweeps, poses given" in run.stdout
    assert "2 sweeps without a prediction of their own (no earlier sweep; 1 of them beside a missing sweep)" in \
        run.stdout
    for slots in ((1, 0, 0), (2, 1, 0), (4, 3, 3)):
        with np.load(tmp_path / "out" / f"{slots[0]:06d}.npz") as z:
            np.testing.assert_allclose(z["flow_mps"], _expected_flow(model, clouds, poses, slots), atol=1e-4)
            assert np.abs(z["flow_mps"]).max() > 0.1
    assert sorted(p.name for p in (tmp_path / "out").glob("*.npz")) == ["000001.npz", "000002.npz", "000004.npz"]


@pytest.mark.slow  # a second model and two runs of the tool: ~40 s
def test_a_model_of_the_next_sweep_reads_each_sweep_with_the_next_one(tmp_path):
    """Trained on Argoverse 2 challenge records (data.partner=next in its saved config): sweep i is read with sweep
    i+1 in the t-1 slot and i-1 in the t-2 slot, as the records hold them; the last sweep of each sequence has no
    partner; the flow written is minus the model's (the velocity). A pair of point files cannot be so read: one
    line says so."""
    d, clouds, poses = _sweeps(tmp_path)
    model, prefix = _model(tmp_path, (*SETS, "data.source=pair_records", "data.partner=next"))
    run = _predict(prefix, d, tmp_path / "out", "--set", "data.skip_bad_records=true")
    assert run.returncode == 0, run.stderr[-3000:]
    assert "2 sweeps without a prediction of their own (no next sweep" in run.stdout
    for slots in ((0, 1, 0), (1, 2, 0), (3, 4, 3)):
        with np.load(tmp_path / "out" / f"{slots[0]:06d}.npz") as z:
            np.testing.assert_allclose(z["flow_mps"], -_expected_flow(model, clouds, poses, slots), atol=1e-4)
    assert sorted(p.name for p in (tmp_path / "out").glob("*.npz")) == ["000000.npz", "000001.npz", "000003.npz"]
    run = subprocess.run([sys.executable, "tools/predict.py", "--checkpoint", prefix, "--points_tm1",
                          str(d / "000000.npy"), "--points_t0", str(d / "000001.npy"), "--out_dir",
                          str(tmp_path / "pair")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 1 and "Traceback" not in run.stderr, run.stderr[-3000:]
    assert "reads 3" in run.stderr.strip().splitlines()[-1] and "--sweeps_dir" in run.stderr
