"""The framework internals this project relies on, behind one door.

Everything here uses an API that its framework does not promise to keep (a private module, a compatibility module
kept for TF1 code, or a public module whose behaviour is undocumented). Each function names what it needs and why no
public API serves; `CHECKED_ON` names the versions each was checked on, and `tests/test_internals.py` exercises each
one and fails, by name, on any other version. TensorFlow and JAX are imported inside the functions: importing this
module imports neither (the TensorFlow-free artifact runner, `ff3d_tf.inference.xla_artifact`, must stay so).

TensorFlow (checked on tensorflow 2.21.0, with keras 3.15.1):
  - `fused_batch_norm`: TensorFlow's fused batch normalisation kernel (FusedBatchNormV3 and its gradient), through
    the TF1 compatibility API `tf.compat.v1.nn.fused_batch_norm`: TensorFlow 2's `tf.nn` has only the elementwise
    `batch_normalization` (which Keras 3's BatchNormalization calls), and `tf.raw_ops.FusedBatchNormV3` is the bare
    op without the wrapper's argument handling.
  - `checkpoint_variable_keys`: the tensor key of each variable node of a checkpoint's object graph. The graph is a
    `TrackableObjectGraph` proto whose Python class lives in `tensorflow.core.protobuf` (not under `tf.*`);
    `tf.train.CheckpointView` parses it but exposes a node's children only, not its saved tensors.
  - `checkpoint_reader`: a checkpoint's reader through `tf.compat.v1.train.NewCheckpointReader`: the TensorFlow 2
    form, `tf.train.load_checkpoint`, takes a prefix on some filesystems (ram://) for a directory and looks for a
    `checkpoint` state file there.
  - `onednn_enabled`: whether TensorFlow's oneDNN operations (and with them its oneDNN CPU allocator, whose
    statistics `tf.config.experimental.get_memory_info` reports) are on in this process, through
    `tensorflow.python.util._pywrap_util_port.IsMklEnabled`: TensorFlow decides it at start from
    TF_ENABLE_ONEDNN_OPTS and the CPU's features and only logs it; no `tf.*` API returns it.
  - `profiler_xspace`: the profiler's trace files (`*.xplane.pb`) as `XSpace` protos; the proto's Python class lives
    in `tensorflow.tsl.profiler.protobuf` (TensorBoard's profile plugin reads the same files; no `tf.*` API does).

Keras (checked on keras 3.15.1):
  - `adam_slots`: a built Adam's first and second moments, one per weight in build order (`_momentums`,
    `_velocities`). Keras has no public accessor: `optimizer.variables` lists them with the iteration count and the
    learning rate, in an order it does not document. The training step (`ff3d_tf.model.step`) updates them.

JAX (checked on jax/jaxlib 0.10.2 and, for loading what this writes, 0.11.2):
  - `hlo_to_jax_exported`: a serialized XLA HLO module (TensorFlow's `experimental_get_compiler_ir(stage=
    "hlo_serialized")`) as a `jax.export.Exported`. jax.extend gives `hlo_to_stablehlo`, `Primitive` and the MLIR
    bindings; the lowering registration (`jax.interpreters.mlir.register_lowering`, `merge_mlir_modules`) and
    `jax.core.ShapedArray` are JAX internals: no public API calls a foreign StableHLO module.

tf2onnx (checked on tf2onnx 1.17.0, onnx 1.19.1):
  - `tf2onnx_custom_op_handlers`: the ONNX export's own lowering of two TensorFlow ops (UnsortedSegmentSum as
    ScatterElements with reduction add; Select/SelectV2 as Where). The handlers receive tf2onnx's internal `Graph` and
    `Node` (`make_node`, `make_const`, `remove_node`, `get_shape`, `get_dtype`, `replace_input`, `Node.input/output/
    type`) and use `tf2onnx.utils` (`make_name`, `make_sure`, `map_onnx_to_numpy_type`), through the dict form of
    `from_function(custom_op_handlers=...)` that tf2onnx's code calls temporary. Why: see
    `ff3d_tf.inference.onnx_export` (tf2onnx's own lowerings fail in onnxruntime, race, or leak NaN).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

# function -> {distribution: version it was checked on}; `tests/test_internals.py` fails on any other installed one.
CHECKED_ON = {
    "fused_batch_norm": {"tensorflow": "2.21.0", "keras": "3.15.1"},
    "checkpoint_variable_keys": {"tensorflow": "2.21.0", "keras": "3.15.1"},
    "adam_slots": {"keras": "3.15.1"},
    "checkpoint_reader": {"tensorflow": "2.21.0"},
    "profiler_xspace": {"tensorflow": "2.21.0"},
    "onednn_enabled": {"tensorflow": "2.21.0"},
    "hlo_to_jax_exported": {"jax": "0.10.2", "jaxlib": "0.10.2"},
    "tf2onnx_custom_op_handlers": {"tf2onnx": "1.17.0", "onnx": "1.19.1"},
}


def adam_slots(optimizer) -> tuple[list, list]:
    """(momentums, velocities) of a built `keras.optimizers.Adam`, one per weight in its build order."""
    return list(optimizer._momentums), list(optimizer._velocities)  # private: see the module docstring


# --- TensorFlow -------------------------------------------------------------------------------------------------

def fused_batch_norm(x, scale, offset, *, epsilon: float, training: bool, mean=None, variance=None):
    """Batch normalisation of NHWC `x` over its last axis as one fused kernel (FusedBatchNormV3), forward and backward.

    training: normalises by the batch statistics; returns (y, batch mean, batch variance), the variance with Bessel's
      correction n / (n - 1) (n = values per channel). Else by `mean` and `variance`; returns (y, mean, variance).
    scale, offset (and mean, variance) [C] float32; y has the dtype of x (float32 or bfloat16).
    """
    # No TensorFlow 2 API runs this kernel (see the module docstring): the TF1 compatibility wrapper does.
    import tensorflow as tf
    if training:
        return tf.compat.v1.nn.fused_batch_norm(x, scale, offset, epsilon=epsilon, data_format="NHWC",
                                                is_training=True)
    return tf.compat.v1.nn.fused_batch_norm(x, scale, offset, mean=mean, variance=variance, epsilon=epsilon,
                                            data_format="NHWC", is_training=False)


def checkpoint_reader(prefix: str):
    """A `CheckpointReader` of the checkpoint at `prefix` (index and data files), read as given."""
    import tensorflow as tf
    return tf.compat.v1.train.NewCheckpointReader(prefix)  # see the module docstring


def onednn_enabled() -> bool:
    """Whether TensorFlow's oneDNN operations are on in this process (`ff3d_tf.cpu` says when they are)."""
    from tensorflow.python.util import _pywrap_util_port  # private: see the module docstring
    return bool(_pywrap_util_port.IsMklEnabled())


def profiler_xspace(path: str):
    """The `XSpace` proto of one profiler trace file (`*.xplane.pb`): planes, lines, events and event metadata."""
    from tensorflow.tsl.profiler.protobuf import xplane_pb2  # private: see the module docstring
    space = xplane_pb2.XSpace()
    with open(path, "rb") as f:
        space.ParseFromString(f.read())
    return space


def checkpoint_variable_keys(object_graph: bytes) -> dict[int, str]:
    """{node id: tensor key of the variable's value} for the variable nodes of a checkpoint's serialized object graph
    (its `_CHECKPOINTABLE_OBJECT_GRAPH` tensor; node ids as `tf.train.CheckpointView` numbers them). Raises (a
    protobuf DecodeError) when the bytes are not an object graph."""
    # The proto's class is TensorFlow-private (see the module docstring); `tf.train.CheckpointView` parses the same
    # bytes but gives no node's tensor keys.
    from tensorflow.core.protobuf import trackable_object_graph_pb2
    graph = trackable_object_graph_pb2.TrackableObjectGraph.FromString(object_graph)
    return {i: a.checkpoint_key for i, node in enumerate(graph.nodes) for a in node.attributes
            if a.name == "VARIABLE_VALUE"}


# --- JAX --------------------------------------------------------------------------------------------------------


def _stablehlo_avals(stablehlo: bytes):
    import jax
    from jax.extend.mlir import ir
    from jax.interpreters import mlir
    dtypes = {"f32": np.float32, "bf16": jax.numpy.bfloat16, "i1": np.bool_, "i32": np.int32, "i64": np.int64}

    def aval(t):
        t = ir.RankedTensorType(t)
        name = str(t.element_type)
        if name not in dtypes:
            raise TypeError(f"forward program has a {name} tensor; supported: {sorted(dtypes)}")
        return jax.core.ShapedArray(tuple(t.shape), dtypes[name])
    with mlir.make_ir_context():
        main = ir.SymbolTable(ir.Module.parse(stablehlo).operation)["main"]
        return [aval(t) for t in main.type.inputs], [aval(t) for t in main.type.results]


def _program_primitive():
    """A JAX primitive `program_p.bind(*args, stablehlo=bytes, out_avals=...)` that calls a StableHLO module."""
    from jax.extend.core import Primitive
    from jax.extend.mlir import ir
    from jax.extend.mlir.dialects import func
    from jax.interpreters import mlir
    program_p = Primitive("ff3d_tf_xla_program")
    program_p.multiple_results = True
    program_p.def_abstract_eval(lambda *args, stablehlo, out_avals: list(out_avals))

    def lowering(ctx, *args, stablehlo, out_avals):
        del out_avals
        module = ir.Module.parse(stablehlo, context=ctx.module_context.context)
        result_types = ir.SymbolTable(module.operation)["main"].type.results
        name = mlir.merge_mlir_modules(ctx.module_context.module, "ff3d_tf_forward", module,
                                       dst_symtab=ctx.module_context.symbol_table)
        return func.CallOp(result_types, ir.FlatSymbolRefAttr.get(name), list(args)).results
    mlir.register_lowering(program_p, lowering)
    return program_p


_PROGRAM_P = None


def hlo_to_jax_exported(hlo: bytes, platforms: Sequence[str]):
    """A `jax.export.Exported` that runs the HLO program (lowered for `platforms`; no device of them needed)."""
    global _PROGRAM_P
    import jax
    from jax import export
    from jax.extend.mlir import hlo_to_stablehlo
    if _PROGRAM_P is None:
        _PROGRAM_P = _program_primitive()
    stablehlo = hlo_to_stablehlo(hlo)
    in_avals, out_avals = _stablehlo_avals(stablehlo)

    def program(*args):
        return _PROGRAM_P.bind(*args, stablehlo=stablehlo, out_avals=tuple(out_avals))
    specs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in in_avals]
    return export.export(jax.jit(program), platforms=tuple(platforms))(*specs)


# --- tf2onnx -----------------------------------------------------------------------------------------------------

def _segment_sum_to_scatter_elements(ctx, node, name, args):
    """UnsortedSegmentSum(data [P, C...], ids [P], num_segments S) -> ScatterElements(add) of data into zeros
    [S, C...]; the values of ids outside [0, S) (TensorFlow drops them) are added to row 0 as zeros."""
    del name, args
    from onnx import TensorProto, numpy_helper
    from tf2onnx import utils
    data, ids, num_segments = node.input
    data_static = ctx.get_shape(data)
    utils.make_sure(data_static is not None and len(data_static) >= 1 and len(ctx.get_shape(ids) or []) == 1,
                    "UnsortedSegmentSum %s: only 1-D segment ids of data with a known rank are handled", node.name)
    rank = len(data_static)
    dtype, out_shape = ctx.get_dtype(node.output[0]), ctx.get_shape(node.output[0])

    def op(op_type, inputs, **attr):
        return ctx.make_node(op_type, inputs, attr=attr, op_name_scope=node.name).output[0]

    def const(value, np_type=np.int64):
        return ctx.make_const(utils.make_name(f"{node.name}_const"), np.asarray(value, np_type)).output[0]

    segments = op("Reshape", [op("Cast", [num_segments], to=TensorProto.INT64), const([1])])  # [1]: S
    data_shape = op("Shape", [data])
    grid_shape = op("Concat", [segments, op("Slice", [data_shape, const([1]), const([rank]), const([0])])], axis=0)
    np_dtype = utils.map_onnx_to_numpy_type(dtype)
    ids64 = op("Cast", [ids], to=TensorProto.INT64)
    inside = op("And", [op("GreaterOrEqual", [ids64, const(0)]), op("Less", [ids64, segments])])  # [P]
    rows = op("Where", [inside, ids64, const(0)])
    if rank > 1:
        trailing = const(list(range(1, rank)))
        rows, inside = op("Unsqueeze", [rows, trailing]), op("Unsqueeze", [inside, trailing])
    updates = op("Where", [inside, data, const([0], np_dtype)])
    indices = op("Expand", [rows, data_shape])  # [P, C...]: ScatterElements takes one index per value
    grid = op("ConstantOfShape", [grid_shape], value=numpy_helper.from_array(np.zeros([1], np_dtype), "value"))
    ctx.remove_node(node.name)
    ctx.make_node("ScatterElements", [grid, indices, updates], attr={"axis": 0, "reduction": "add"},
                  outputs=node.output, name=node.name, shapes=[out_shape], dtypes=[dtype])


def _select_to_where(ctx, node, name, args):
    """Select/SelectV2 -> ONNX Where, whatever the dtype (NaN-safe). SelectV2 broadcasts as Where does; Select (v1)
    with a 1-D condition picks rows, so its condition is reshaped to [P, 1, ...]."""
    del name, args
    from tf2onnx import utils
    cond_shape, x_shape = ctx.get_shape(node.input[0]), ctx.get_shape(node.input[1]) or ctx.get_shape(node.input[2])
    if node.type == "Select" and cond_shape is not None and len(cond_shape) == 1 and (x_shape is None or
                                                                                      len(x_shape) != 1):
        utils.make_sure(x_shape is not None, "Select %s: a 1-D condition on an input of unknown rank", node.name)
        shape = ctx.make_const(utils.make_name(f"{node.name}_shape"),
                               np.array([-1] + [1] * (len(x_shape) - 1), np.int64)).output[0]
        reshaped = ctx.make_node("Reshape", [node.input[0], shape], op_name_scope=node.name).output[0]
        ctx.replace_input(node, node.input[0], reshaped, 0)
    node.type = "Where"


def tf2onnx_custom_op_handlers() -> dict:
    """`custom_op_handlers` for `tf2onnx.convert.from_function`: UnsortedSegmentSum -> ScatterElements(add),
    Select/SelectV2 -> Where."""
    return {"UnsortedSegmentSum": (_segment_sum_to_scatter_elements, []),
            "SelectV2": (_select_to_where, []), "Select": (_select_to_where, [])}
