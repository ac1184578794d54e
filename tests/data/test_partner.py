"""Which sweep the t-1 slot holds (`data.partner`): resolved from the pair records' manifest, a config that asks for
the other side refused where the model would compute otherwise (`config.partner_matters`), the pair left free."""
import pytest

from ff3d_tf import schema
from ff3d_tf.config import ConfigError, partner_matters, replace_config
from ff3d_tf.data import pair_records, pairs


def _records(tmp_path, partner, num_frames):
    manifest = pair_records.Manifest(source="av2", laser_names=(1, 2), returns=(1,), max_frame_gap_s=0.15,
                                     partner=partner, num_frames=num_frames)
    pair_records.write_manifest(str(tmp_path), manifest)
    return [str(tmp_path / "part-0.tfrecord")]


def test_slots_newest_first():
    assert schema.slot_sweep_offsets(4, "previous") == (0, -1, -2, -3)  # t0, t-1, t-2, t-3
    assert schema.slot_sweep_offsets(4, "next") == (0, 1, -1, -2)  # t0, t+1, t-1, t-2
    assert schema.slots_newest_first(5, "previous") == (0, 1, 2, 3, 4)
    assert schema.slots_newest_first(5, "next") == (1, 0, 2, 3, 4)  # t+1, t0, t-1, t-2, t-3
    with pytest.raises(ValueError, match="sideways"):
        schema.slots_newest_first(3, "sideways")


@pytest.mark.parametrize("partner", schema.PARTNERS)
def test_the_records_partner_is_taken_when_the_config_leaves_it_unset(tiny_config, tmp_path, partner):
    cfg = replace_config(tiny_config, {"data.source": "pair_records", "data.num_frames": 3,
                                       "model.temporal": "delta"})
    assert cfg.data.partner is None
    assert pairs.with_data_partner(cfg, _records(tmp_path, partner, 3)).data.partner == partner


def test_a_config_of_the_other_side_is_refused_where_it_matters(tiny_config, tmp_path):
    files = _records(tmp_path, "next", 3)
    cfg = replace_config(tiny_config, {"data.source": "pair_records", "data.num_frames": 3,
                                       "model.temporal": "stack", "data.partner": "previous"})
    with pytest.raises(ConfigError, match="pair each sweep with the next one.*data.partner=previous"):
        pairs.with_data_partner(cfg, files)


def test_the_pair_reads_either_side(tiny_config, tmp_path):
    """The paper's pair computes the motion from its partner cloud to t0 whichever side the partner lies on."""
    cfg = replace_config(tiny_config, {"data.source": "pair_records", "data.partner": "previous"})
    assert not partner_matters(cfg)
    assert pairs.with_data_partner(cfg, _records(tmp_path, "next", 2)).data.partner == "next"
    assert partner_matters(replace_config(cfg, {"model.temporal": "delta"}))


def test_wod_frames_have_the_previous_sweep_as_partner(tiny_config):
    cfg = replace_config(tiny_config, {"data.num_frames": 3, "model.temporal": "delta"})
    assert pairs.with_data_partner(cfg, []).data.partner == "previous"
    with pytest.raises(ConfigError, match="data.partner=next with data.source=wod"):
        pairs.with_data_partner(replace_config(cfg, {"data.partner": "next"}), [])
