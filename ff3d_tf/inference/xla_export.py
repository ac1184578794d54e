"""The model's forward as a portable XLA program: one `jax.export` artifact per point bucket, weights saved once.

TensorFlow compiles the forward with XLA (`jit_compile=True`); this module takes that program before any
optimisation, with the weights as plain arguments, and serialises it so that a process without TensorFlow (JAX/XLA
only, e.g. on a GPU machine) compiles and runs it: `ff3d_tf.inference.xla_artifact` reads it back.

  1. `tf.function(jit_compile=True)` over `model.stateless_call` with flat arguments (weights, then the six inputs of
     one padded bucket): `experimental_get_compiler_ir(...)(stage="hlo_serialized")` is the pre-optimisation HLO,
     in which nothing depends on the device.
  2. jaxlib converts the HLO to StableHLO; a JAX primitive whose lowering inlines that module makes it a JAX
     function, and `jax.export` lowers it for the platforms asked (CPU and CUDA, on a machine without a GPU) and
     serialises it with StableHLO's versioned portable format.

TF32: TensorFlow writes its TF32 setting into the program (convolution/matmul precision HIGHEST when disabled,
DEFAULT when enabled), so each precision is traced with the setting it names (see `xla_artifact.PRECISIONS`).
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from typing import Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.inference import xla_artifact
from ff3d_tf.model import build_model
from ff3d_tf.model.fastflow3d import INPUT_KEYS

OUTPUT_KEYS = ("flow_mps", "point_valid")
PLATFORMS = ("cpu", "cuda")


def input_specs(batch_size: int, padded_points: int) -> list[tf.TensorSpec]:
    """The six model inputs of one bucket, in `INPUT_KEYS` order (see `ff3d_tf.model.fastflow3d`)."""
    b, p = batch_size, padded_points
    shapes = {"points_xyz_t0": ([b, p, 3], tf.float32), "point_features_t0": ([b, p, 2], tf.float32),
              "point_mask_t0": ([b, p], tf.bool), "points_xyz_tm1_in_t0": ([b, p, 3], tf.float32),
              "point_features_tm1": ([b, p, 2], tf.float32), "point_mask_tm1": ([b, p], tf.bool)}
    return [tf.TensorSpec(*shapes[k], name=k) for k in INPUT_KEYS]


def model_weights(model) -> list:
    """The forward's weight arguments: trainable, then non-trainable variables (BatchNorm statistics)."""
    return list(model.trainable_variables) + list(model.non_trainable_variables)


@contextlib.contextmanager
def _tensor_float_32(enabled: bool):
    previous = tf.config.experimental.tensor_float_32_execution_enabled()
    tf.config.experimental.enable_tensor_float_32_execution(enabled)
    try:
        yield
    finally:
        tf.config.experimental.enable_tensor_float_32_execution(previous)


def forward_hlo(model, batch_size: int, padded_points: int, tf32: bool = False) -> bytes:
    """Serialized pre-optimisation HLO of `model`'s inference forward for one bucket, weights as arguments.

    Arguments: `model_weights(model)` in order, then the inputs of `input_specs`; results: flow_mps [B,P,3],
    point_valid [B,P].
    """
    num_trainable = len(model.trainable_variables)
    num_weights = len(model_weights(model))

    def forward(*flat):
        outputs, _ = model.stateless_call(list(flat[:num_trainable]), list(flat[num_trainable:num_weights]),
                                          dict(zip(INPUT_KEYS, flat[num_weights:])), training=False)
        return tuple(outputs[k] for k in OUTPUT_KEYS)

    specs = [tf.TensorSpec(v.shape, v.dtype) for v in model_weights(model)] + input_specs(batch_size, padded_points)
    with _tensor_float_32(tf32):
        # A fresh tf.function per call: the TF32 setting is read when the function is converted to HLO.
        return tf.function(forward, jit_compile=True).experimental_get_compiler_ir(*specs)(stage="hlo_serialized")


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


def hlo_to_exported(hlo: bytes, platforms: Sequence[str] = PLATFORMS):
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


def _tracing_model(cfg: ExperimentConfig, precision: str, model):
    """The model whose forward is traced for `precision` (weights are arguments, so a fresh one is fine)."""
    mixed = precision == "bfloat16"
    if mixed == cfg.model.mixed_precision:
        return model
    other = build_model(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, mixed_precision=mixed)))
    same = [(v.shape, v.dtype) for v in model_weights(other)] == [(v.shape, v.dtype) for v in model_weights(model)]
    if not same:
        raise ValueError(f"model.mixed_precision={mixed} changes the weights' shapes or dtypes; cannot export "
                         f"precision {precision} with the same weights")
    return other


def export_forward(cfg: ExperimentConfig, model, points: Sequence[int], out_dir: str,
                   precisions: Sequence[str] = ("float32",), platforms: Sequence[str] = PLATFORMS,
                   batch_size: int = 1, weights_source: str = "random initialisation", log=print) -> dict:
    """Writes `out_dir` (layout in `xla_artifact`): the weights of `model`, one artifact per (bucket, precision).

    `points` are cloud sizes; each is padded to its bucket (`data.point_bucket_base`), as the input pipeline does.
    Returns the manifest (also written as manifest.json).
    """
    for p in precisions:
        if p not in xla_artifact.PRECISIONS:
            raise ValueError(f"precision {p!r} unknown; one of {xla_artifact.PRECISIONS}")
    if not points or min(points) < 1:
        raise ValueError(f"points must be positive cloud sizes, got {list(points)}")
    os.makedirs(out_dir, exist_ok=True)
    import jax
    weights = model_weights(model)
    np.savez(os.path.join(out_dir, xla_artifact.WEIGHTS_NAME),
             **{f"w{i:03d}": np.asarray(v.numpy()) for i, v in enumerate(weights)})
    g = cfg.grid
    manifest = {
        "format": xla_artifact.FORMAT,
        "exported_with": {"tensorflow": tf.__version__, "jax": jax.__version__, "platforms": list(platforms)},
        "weights_source": weights_source,
        "grid": {"num_pillars_x": g.num_pillars_x, "num_pillars_y": g.num_pillars_y, "x_range_m": list(g.x_range_m),
                 "y_range_m": list(g.y_range_m), "z_range_m": list(g.z_range_m)},
        "params": int(model.count_params()),
        "input_keys": list(INPUT_KEYS), "output_keys": list(OUTPUT_KEYS),
        "weights": [{"path": v.path, "shape": list(v.shape), "dtype": str(v.dtype)} for v in weights],
        "artifacts": [],
    }
    written: dict[str, int] = {}
    for precision in precisions:
        tracer = _tracing_model(cfg, precision, model)
        for n in points:
            padded = bucket_size(n, cfg.data.point_bucket_base)
            name = xla_artifact.artifact_name(padded, precision)
            if name not in written:
                hlo = forward_hlo(tracer, batch_size, padded, tf32=precision == "tf32")
                blob = hlo_to_exported(hlo, platforms).serialize()
                with open(os.path.join(out_dir, name), "wb") as f:
                    f.write(blob)
                written[name] = len(blob)
                log(f"{name}: {len(blob) / 1e3:.0f} kB")
            manifest["artifacts"].append({"points": int(n), "padded_points": padded, "batch_size": batch_size,
                                          "precision": precision, "file": name, "bytes": written[name]})
    with open(os.path.join(out_dir, xla_artifact.MANIFEST_NAME), "w") as f:
        json.dump(manifest, f, indent=1)
    return manifest
