import pytest

from ff3d_tf.config import ConfigError, load_config


def test_paper_config_and_overrides(tmp_path):
    cfg = load_config("configs/fastflow3d_waymo.yaml", ["train.learning_rate=1e-4", "grid.num_pillars_x=256"])
    assert cfg.train.learning_rate == 1e-4 and cfg.grid.num_pillars_x == 256
    assert cfg.train.global_batch_size == 64 and cfg.grid.x_range_m == (-85.0, 85.0)
    cfg.save(str(tmp_path / "c.yaml"))
    again = load_config(str(tmp_path / "c.yaml"))
    assert again == cfg


@pytest.mark.parametrize("override,message", [
    ("grid.num_pillars_x=100", "multiple of 8"),
    ("train.learnin_rate=1", "unknown config key train.learnin_rate"),
    ("train.global_batch_size=two", "expected an integer"),
    ("data.laser_names=[1, 9]", "laser_names"),
    ("model.decoder_dims=[[1, 1], [1, 1], [8, 8]]", "point_feature_dim"),
])
def test_bad_config_fails_before_work(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_yaml_is_data_only(tmp_path):
    p = tmp_path / "evil.yaml"
    p.write_text("train: !!python/object/apply:os.system ['echo hi']\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(str(p))
