"""tools/predict.py on a user's sweeps directory with a model of three sweeps (`model.temporal=delta`), as a user
calls it: each sweep with two before it gets the model's flow on its cloud and the two past clouds moved into its
frame by NumPy; the first two sweeps get none."""
import subprocess
import sys

import numpy as np

from conftest import ROOT, TINY_OVERRIDES
from ff3d_tf import geometry, schema

SETS = (*TINY_OVERRIDES, "data.num_frames=3", "model.temporal=delta")


def test_sweeps_directory_with_a_three_sweep_model(tmp_path):
    import tensorflow as tf
    from ff3d_tf.config import load_config
    from ff3d_tf.model import build_model
    cfg = load_config(None, SETS)
    model = build_model(cfg, compile_mode="none")
    prefix = tf.train.Checkpoint(model=model).save(str(tmp_path / "ckpt" / "ckpt"))
    rng = np.random.default_rng(5)
    d = tmp_path / "log"
    d.mkdir()
    clouds = [rng.uniform([-35, -35, -2], [35, 35, 2], (n, 3)).astype(np.float32) for n in (120, 140, 130, 150)]
    poses = [geometry.box_matrices_np((1.0 * k, 0.3 * k, 0.0), 0.04 * k)[0] for k in range(4)]
    for k, cloud in enumerate(clouds):
        np.save(d / f"{k:06d}.npy", cloud)
    (d / "poses.txt").write_text("".join(" ".join(repr(float(v)) for v in p[:3].reshape(-1)) + "\n" for p in poses))
    run = subprocess.run([sys.executable, "tools/predict.py", "--config", "", *[a for s in SETS for a in ("--set", s)],
                          "--checkpoint", prefix, "--sweeps_dir", str(d), "--out_dir", str(tmp_path / "out")],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "4 sweeps, 2 examples of 3 sweeps, poses given" in run.stdout
    assert not (tmp_path / "out" / "000001.npz").exists()
    for k in (2, 3):
        inputs = {}
        for j, cloud in enumerate(schema.sweep_clouds(3)):
            keys, xyz = schema.cloud_keys(cloud), clouds[k - j].astype(np.float64)
            moved = geometry.transform_points_np(xyz, np.linalg.inv(poses[k]) @ poses[k - j])
            inputs.update({keys["xyz"]: moved[None].astype(np.float32),
                           keys["features"]: np.zeros((1, len(xyz), 2), np.float32),  # no intensity column: 0
                           keys["mask"]: np.ones((1, len(xyz)), bool)})
        want = model(inputs)["flow_mps"][0].numpy()
        with np.load(tmp_path / "out" / f"{k:06d}.npz") as z:
            np.testing.assert_allclose(z["flow_mps"], want, atol=1e-4)
            assert np.abs(z["flow_mps"]).max() > 0.1
