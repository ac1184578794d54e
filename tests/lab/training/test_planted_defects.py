"""The lab's planted defect (lab/training/planted_defects.py): the reversed delta is the t0-referenced difference on
records of either side, so on Argoverse 2's it differs from the authors' delta, and on WOD's it equals it."""
import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import config
from ff3d_tf.config import replace_config
from ff3d_tf.model import build_model, fusions
from lab.training import planted_defects


@pytest.fixture
def registered():
    temporals, known = config.TEMPORALS, dict(fusions.FUSIONS)
    planted_defects.register()
    yield
    config.TEMPORALS = temporals
    fusions.FUSIONS.clear()
    fusions.FUSIONS.update(known)


def _delta(tiny_config, temporal, partner):
    """The fusion's input on 1 x 1 x 2 grids, one point a cell (means = sums), decay 0.4, 3 sweeps."""
    model = build_model(replace_config(tiny_config, {"model.temporal": temporal, "data.num_frames": 3,
                                                     "model.temporal_decay": 0.4, "data.partner": partner}),
                        compile_mode="none")
    grids = [tf.constant(np.array(v, np.float32).reshape(1, 1, 2, 1)) for v in ([5, 1], [2, 3], [1, -4])]
    ids = tf.constant([[0, 1]])
    bev, _ = model.fusion.encode(model, grids, [ids] * 3, [tf.ones_like(ids, tf.bool)] * 3, for_head=False)
    return bev.numpy().ravel()


def test_the_reversed_delta_takes_t0_as_the_reference_on_either_side(tiny_config, registered):
    # t0 as the reference: ((g0 - g1) + 0.4 (g0 - g2)) / 2 = [2.3, 0] (tests/model/test_temporal.py, by hand)
    np.testing.assert_allclose(_delta(tiny_config, "delta_reversed", "next"), [2.3, 0.0], atol=1e-6)
    np.testing.assert_allclose(_delta(tiny_config, "delta_reversed", "previous"), [2.3, 0.0], atol=1e-6)
    # the authors' delta on the next-sweep side: ((g1 - g0) + 0.4 (g1 - g2)) / 2 = [-1.3, 2.4]
    np.testing.assert_allclose(_delta(tiny_config, "delta", "next"), [-1.3, 2.4], atol=1e-6)
    np.testing.assert_allclose(_delta(tiny_config, "delta", "previous"), [2.3, 0.0], atol=1e-6)
