"""ff3d_tf.schema: the per-point keys of a pair, from which the record layout and the key tuples are derived."""
import numpy as np

from ff3d_tf import schema
from ff3d_tf.data import pair_records


def test_key_tuples_keep_the_order_existing_records_were_written_in():
    # Records store keys by name, but readers and writers iterate these tuples: the order is part of the format.
    assert schema.PAIR_T0_POINT_KEYS == ("points_xyz_t0", "point_features_t0", "flow_mps_t0", "class_id_t0")
    assert schema.PAIR_TM1_POINT_KEYS == ("points_xyz_tm1_in_t0", "point_features_tm1")
    assert set(schema.AV2_RECORD_EXTRAS) <= set(schema.PAIR_EXTRA_POINT_KEYS)


def test_every_stored_dtype_holds_its_values():
    for key, spec in schema.POINT_KEYS.items():
        assert spec.cloud in schema.sweep_clouds(schema.MAX_NUM_FRAMES), key
        assert key.endswith((f"_{spec.cloud}", f"_{spec.cloud}_in_t0")), key
        for stored in (spec.stored, spec.stored_compact or spec.stored):
            if spec.dtype == "bool":
                assert stored == "uint8", key
            elif spec.dtype == "int32":  # class ids -1..4, AV2 category indices -1..30
                assert np.iinfo(stored).min <= -1 and np.iinfo(stored).max >= 30, key
            else:
                assert np.dtype(stored).kind == "f", key
        field = pair_records.RECORD_FIELDS[key]
        assert (field.model_dtype, field.tail_shape, field.count_key) == (spec.dtype, spec.tail_shape,
                                                                          f"num_points_{spec.cloud}")


def test_sweep_keys_extend_the_pair():
    """The pair's model input is the 2-sweep case; older sweeps add their own keys in the same pattern."""
    assert schema.model_input_keys(2) == schema.MODEL_INPUT_KEYS
    assert schema.past_sweep_keys(2) == ()
    assert schema.model_input_keys(3)[len(schema.MODEL_INPUT_KEYS):] == (
        "points_xyz_tm2_in_t0", "point_features_tm2", "point_mask_tm2")
    assert schema.past_sweep_keys(3) == ("points_xyz_tm2_in_t0", "point_features_tm2", "num_points_tm2", "pose_tm2")
    for cloud in ("tm1", "tm2"):
        keys = schema.cloud_keys(cloud)
        assert schema.POINT_KEYS[keys["xyz"]].cloud == schema.POINT_KEYS[keys["features"]].cloud == cloud
