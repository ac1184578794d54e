"""The framework internals this project relies on, behind one door.

Everything here uses an API that its framework does not promise to keep (a private module, or a public module whose
behaviour is undocumented). Each function names what it needs and why no public API serves; `tests/test_internals.py`
exercises each one and names the versions it was checked on, so an upgrade that breaks one fails there, by name.
TensorFlow and JAX are imported inside the functions: importing this module imports neither (the TensorFlow-free
artifact runner, `ff3d_tf.inference.xla_artifact`, must stay so).

JAX (checked on jax/jaxlib 0.10.2 and, for loading what this writes, 0.11.2):
  - `hlo_to_jax_exported`: a serialized XLA HLO module (TensorFlow's `experimental_get_compiler_ir(stage=
    "hlo_serialized")`) as a `jax.export.Exported`. jax.extend gives `hlo_to_stablehlo`, `Primitive` and the MLIR
    bindings; the lowering registration (`jax.interpreters.mlir.register_lowering`, `merge_mlir_modules`) and
    `jax.core.ShapedArray` are JAX internals: no public API calls a foreign StableHLO module.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np


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
