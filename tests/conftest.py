"""Test setup: two logical CPU devices (for MirroredStrategy tests), a tiny synthetic WOD segment per session."""
import os
import sys

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import pytest  # noqa: E402
import tensorflow as tf  # noqa: E402

_cpus = tf.config.list_physical_devices("CPU")
tf.config.set_logical_device_configuration(_cpus[0], [tf.config.LogicalDeviceConfiguration()] * 2)

AV2_LOG = os.path.join(ROOT, "data", "av2_sample_log")  # in-tree fixture (see data/README.md)
TINY_SCALE = 0.12  # range images ~8 x 318 (TOP) and 24 x 72 (short-range)


@pytest.fixture(scope="session")
def tiny_segment(tmp_path_factory):
    """Path of a 4-frame synthetic segment with small range images (all five lidars)."""
    from ff3d_tf.data.synthetic import wod as synthetic
    path = str(tmp_path_factory.mktemp("seg") / "segment-tiny.tfrecord")
    synthetic.write_segment(path, synthetic.SegmentSpec(seed=5, num_frames=4, lidar_scale=TINY_SCALE))
    return path


@pytest.fixture(scope="session")
def tiny_records(tiny_segment):
    from ff3d_tf.data.wod import waymo
    return [r for _, r in waymo.iterate_records(tiny_segment)]


# The tiny model of the tests (also passed to the tools as --set).
from ff3d_tf.config import TINY_OVERRIDES  # noqa: E402


@pytest.fixture(scope="session")
def tiny_config():
    from ff3d_tf.config import load_config
    return load_config(None, TINY_OVERRIDES)


@pytest.fixture(scope="session")
def av2_sample_records(tiny_config, tmp_path_factory):
    """Argoverse 2 challenge pair records of the real sample log (one pair: sweep 0 with sweep 1)."""
    from ff3d_tf.data import pair_records
    from ff3d_tf.labels import av2
    out = str(tmp_path_factory.mktemp("av2_records"))
    manifest = av2.records_manifest(tiny_config)
    pair_records.write_manifest(out, manifest)
    assert av2.write_log_records(AV2_LOG, out, tiny_config, manifest)["pairs"] == 1
    return out


def pytest_sessionstart(session):
    """Prints the CPU the suite runs on and the caps on its libraries (`ff3d_tf.cpu`), -q or not, once (not in
    pytest-xdist's workers): a failure that depends on the CPU can be read from the log."""
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is None or hasattr(session.config, "workerinput"):
        return
    from ff3d_tf import cpu, internals
    reporter.write_line(f"CPU: {cpu.one_line(cpu.describe())}; TensorFlow's oneDNN operations "
                        f"{'on' if internals.onednn_enabled() else 'off'}")


def tiny_model_off_initial_values(cfg, seed: int = 3):
    """A model of `cfg` whose kernels keep their Glorot initialisation and whose every other weight (biases, BatchNorm
    scales, offsets and statistics) is moved off its 0/1 initial value, so that a weight passed in the wrong place
    shows (the portable XLA exports' tests)."""
    import numpy as np
    from ff3d_tf.model import build_model
    from ff3d_tf.xla_export_dir import model_weights
    model = build_model(cfg)
    rng = np.random.default_rng(seed)
    for v in model_weights(model):
        if "kernel" not in v.path:
            centre = 1.0 if "variance" in v.path or "gamma" in v.path else 0.0
            v.assign(rng.uniform(centre - 0.2, centre + 0.2, v.shape).astype(np.float32))
    return model
