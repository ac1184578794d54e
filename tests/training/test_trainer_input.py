"""A training input that holds no example it can train on ends with the project's message naming why, not with
TensorFlow's end-of-sequence traceback."""
import pytest

from ff3d_tf.config import ConfigError, replace_config
from ff3d_tf.training.trainer import Trainer


def test_training_without_a_full_history_example_names_why(tiny_config, tiny_segment, tmp_path):
    """The tiny segment has 4 frames: with 5 sweeps an example needs 4 past frames of its own, which no frame has."""
    cfg = replace_config(tiny_config, {"data.num_frames": 5, "model.temporal": "delta", "model.compile": "none"})
    lines = []
    trainer = Trainer(cfg, str(tmp_path / "m"), [tiny_segment], log_fn=lines.append)
    # said at start, before any step: which examples are left out and where they are counted
    assert any("a log's first 3 examples read its first sweep instead and are left out" in line and
               "pairs_without_full_history" in line for line in lines), lines
    with pytest.raises(ConfigError, match=r"no batch at step 0: the 1 training files hold no example it can train "
                                          r"on; with data.num_frames=5 only examples whose every past slot"):
        trainer.train(num_steps=2)
    assert not (tmp_path / "m" / "checkpoints").exists()
