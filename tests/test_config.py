import re

import pytest

from ff3d_tf.config import ConfigError, NsfpConfig, load_config, replace_config


def test_paper_config_and_overrides(tmp_path):
    cfg = load_config("configs/fastflow3d_waymo.yaml", ["train.learning_rate=1e-4", "grid.num_pillars_x=256",
                                                         "nsfp.fit_every=8", "nsfp.crop_z_range_m=[-2, 4]",
                                                         "nsfp.crop_xy_half_extent_m=null", "nsfp.on_bad_fit=stop"])
    assert cfg.train.learning_rate == 1e-4 and cfg.grid.num_pillars_x == 256
    assert cfg.train.global_batch_size == 64 and cfg.grid.x_range_m == (-85.0, 85.0)
    assert cfg.nsfp.fit_every == 8 and cfg.nsfp.crop_z_range_m == (-2.0, 4.0) and cfg.nsfp.on_bad_fit == "stop"
    assert cfg.nsfp.crop_xy_half_extent_m is None and cfg.nsfp.learning_rate == NsfpConfig().learning_rate
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


@pytest.mark.parametrize("override,message", [
    ("train.learnin_rate=1", r"unknown config key train.learnin_rate; known: \[.*'learning_rate'"),
    ("gridd.num_pillars_x=8",
     r"unknown config key gridd; known: \['data', 'grid', 'model', 'nsfp', 'selfsup', 'train'\]"),
    ("grid.x_range_m=[1, 2, 3]", r"grid.x_range_m: expected a list of 2 values, got 3"),
    ("grid.z_range_m=[-3]", r"grid.z_range_m: expected a list of 2 values, got 1"),
    ("train.background_weight=null", r"train.background_weight: expected a finite number, got None"),
    ("train.learning_rate=.inf", r"train.learning_rate: expected a finite number, got inf"),
    ("train.grad_clip_norm=.nan", r"train.grad_clip_norm \(or null\): expected a finite number"),
    ("data.remove_ground_below_z_m=low", r"data.remove_ground_below_z_m \(or null\): expected a finite number"),
    ("data.drop_ground=true", r"data.drop_ground=true: every sweep's ground masks live in pair records"),
    ("train.beta_1=1.5", r"train.beta_1=1.5: must be in \[0, 1\)"),
    ("train.checkpoint_every_steps=0", r"train.checkpoint_every_steps=0: must be >= 1"),
    ("train.seed=-1", r"train.seed=-1: must be in \[0, 4294967295\]"),
    ("data.shuffle_buffer=0", r"data.shuffle_buffer=0: must be >= 1"),
    ("data.point_bucket_base=4611686018427387904", r"data.point_bucket_base=4611686018427387904: must be in \[1, "),
    ("grid.num_pillars_x=1048576", r"grid.num_pillars_x=1048576: must be in \[8, 16384\]"),
    ("model.head_hidden_dim=0", r"model.head_hidden_dim=0: must be in \[1, 65536\]"),
    ("model.encoder_widths=[0, 8, 8]", r"model.encoder_widths \(value 0\)=0: must be in \[1, 65536\]"),
    ("model.decoder_dims=[[8, 8], [8, 8]]", r"model.decoder_dims: must have 3 entries"),
    ("data=[1, 2]", r"data: expected a mapping of \[.*'laser_names'"),
    # the nsfp section: the pseudo-label job's options (tools/pseudo_label.py)
    ("nsfp.learning_rate=0", r"nsfp.learning_rate=0.0: must be a finite number > 0"),
    ("nsfp.reverse_every=-1", r"nsfp.reverse_every=-1: must be an integer in \[0, 2147483647\]"),
    ("nsfp.fit_every=0", r"nsfp.fit_every=0: must be an integer in \[1, 2147483647\]"),
    ("nsfp.max_iterations=1.5", r"nsfp.max_iterations: expected an integer, got 1.5"),
    ("nsfp.crop_z_range_m=[3, -3]", r"nsfp.crop_z_range_m=\(3.0, -3.0\): must be \[lo, hi\] with lo < hi, or null"),
    ("nsfp.truncate_m=0", r"nsfp.truncate_m=0.0: must be a finite number > 0 or null"),
    ("nsfp.ground=map", r"nsfp.ground='map': must be one of auto, records, height, none"),
    ("nsfp.on_bad_fit=ignore", r"nsfp.on_bad_fit='ignore': must be one of skip, stop"),
    ("nsfp.retries=-1", r"nsfp.retries=-1: must be an integer in \[0, "),
    ("nsfp.fit_evry=2", r"unknown config key nsfp.fit_evry; known: \[.*'fit_every'"),
])
def test_bad_values_name_the_key_and_what_is_allowed(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_values_within_range_are_kept():
    cfg = load_config(None, ["train.eval_every_steps=0", "data.remove_ground_below_z_m=-1", "train.beta_1=0",
                             "train.grad_clip_norm=null", "data.remove_ground_below_z_m='0.25'"])
    assert cfg.train.eval_every_steps == 0 and cfg.train.beta_1 == 0.0 and cfg.train.grad_clip_norm is None
    assert cfg.data.remove_ground_below_z_m == 0.25  # numbers given as text are read as numbers


def test_replace_config_keeps_the_fields_it_does_not_name():
    base = load_config(None, ["model.point_feature_dim=16", "model.decoder_dims=[[24, 24], [24, 16], [16, 16]]",
                              "train.learning_rate=0.001"])
    changed = replace_config(base, {"model.zero_init_output": True})
    assert changed.model.zero_init_output and changed.model.point_feature_dim == 16
    assert changed.model.decoder_dims == ((24, 24), (24, 16), (16, 16)) and changed.train.learning_rate == 1e-3


@pytest.mark.parametrize("laser_names,returns", [((1, 9), (1,)), ((1, 2), ())])
def test_lidar_selection_rule_is_the_readers(laser_names, returns):
    from ff3d_tf.data.wod.wod_decode import DecodeOptions
    with pytest.raises(ConfigError) as config_error:
        load_config(None, [f"data.laser_names={list(laser_names)}", f"data.returns={list(returns)}"])
    with pytest.raises(ValueError) as reader_error:
        DecodeOptions(laser_names, returns)
    assert str(config_error.value) == f"data.{reader_error.value}"


@pytest.mark.parametrize("override, key", [
    ("model.head=transformer", "model.head"),
    ("data.partner=sideways", "data.partner"),
    ("data.augment_jitter_sigma_m=-0.01", "data.augment_jitter_sigma_m"),
    ("model.gru_iterations=-1", "model.gru_iterations"),
    ("train.loss=huber", "train.loss"),
    ("data.augment_flip_prob=1.5", "data.augment_flip_prob"),
    ("data.augment_height_offset_prob=-0.1", "data.augment_height_offset_prob"),
    ("data.augment_height_offset_m=[0.5,-0.5]", "data.augment_height_offset_m"),
])
def test_head_loss_and_augmentation_keys_are_checked(override, key):
    with pytest.raises(ConfigError, match=re.escape(key)):
        load_config(None, [override])


def test_deltaflow_refuses_pseudo_labels():
    with pytest.raises(ConfigError, match="train.loss=deltaflow"):
        load_config(None, ["train.loss=deltaflow", "data.source=pair_records", "data.labels=pseudo"])
    cfg = load_config(None, ["model.head=gru", "train.loss=deflow", "data.source=pair_records", "data.labels=pseudo"])
    assert (cfg.model.head, cfg.model.gru_iterations, cfg.train.loss) == ("gru", 4, "deflow")
