"""Heads and fusions are units (`ff3d_tf.model.heads`, `ff3d_tf.model.fusions`): the config's names are the
registries' keys, every unit implements its interface, and DeltaFlow's point head counts its authors' parameters."""
import inspect

from ff3d_tf.config import HEADS, TEMPORALS, replace_config
from ff3d_tf.model import build_model, fusions, heads


def test_the_config_names_are_the_registries():
    assert HEADS == tuple(heads.HEADS)
    assert TEMPORALS == tuple(fusions.FUSIONS)
    assert all(name == unit.name for name, unit in heads.HEADS.items())
    assert all(name == unit.name for name, unit in fusions.FUSIONS.items())


def _overridden(unit, base):
    return {name for name, member in inspect.getmembers(type(unit), inspect.isfunction)
            if getattr(base, name, None) is not member}


def test_every_unit_implements_what_its_interface_leaves_open():
    abstract = {"make_layers", "build", "table", "encoded", "decode", "table_rows"}
    for head in heads.HEADS.values():
        assert abstract <= _overridden(head, heads.Head), head.name
    for fusion in fusions.FUSIONS.values():
        assert {"branches", "head_grid_count", "encode", "head_grids"} <= _overridden(fusion, fusions.Fusion)


def test_deltaflow_point_head_parameters(tiny_config):
    """Linear(C_V + C -> U) with bias, BatchNorm (4 values a channel, as the table counts them), Linear(U -> 3) with
    bias: in the tiny model C_V = 16, C = 16, U = 8: (32 x 8 + 8) + 4 x 8 + (8 x 3 + 3) = 264 + 32 + 27."""
    model = build_model(replace_config(tiny_config, {"model.head": "mlp"}), compile_mode="none")
    c_v, c, u = model.decoder_dims[-1][0], model.point_feature_dim, model.head_hidden_dim
    assert (c_v, c, u) == (16, 16, 8)
    assert model.table_rows()[-4:] == [("X", 0), ("MLP-1", 264), ("MLP-BN", 32), ("MLP-2", 27)]
    assert sum(n for _, n in model.table_rows()) == model.count_params()
