"""Portable XLA programs, whatever they compute: a TensorFlow function traced to pre-optimisation HLO, written as a
serialised `jax.export` artifact (CPU and CUDA), and read back, checked and compiled with JAX alone.

The model's forward (`ff3d_tf.inference.xla_export` / `xla_artifact`), its training step
(`ff3d_tf.training.xla_step_export` / `xla_step_runner`) and NSFP's per-pair
optimiser (`ff3d_tf.labels.nsfp_export` / `nsfp_program`) are exported through this module. Importing it imports
neither TensorFlow nor JAX (each function imports what it needs): a TensorFlow-free runner (a GPU machine with JAX
only) loads programs through it. Trace with `traced_hlo` (TensorFlow), write with `write_program`, then on any
machine `load_program` and `compile_program`.
"""
from __future__ import annotations

import contextlib
import json
import os
import time
from typing import Callable, Sequence

from ff3d_tf import internals

PLATFORMS = ("cpu", "cuda")


class ExportFormatError(ValueError):
    """An export directory that does not hold what its manifest says (the message names the file and field)."""


@contextlib.contextmanager
def tensor_float_32(enabled: bool):
    """TensorFlow's TF32 setting for the duration: it is written into a traced program (matmul / convolution precision
    DEFAULT when enabled, HIGHEST when disabled)."""
    import tensorflow as tf
    previous = tf.config.experimental.tensor_float_32_execution_enabled()
    tf.config.experimental.enable_tensor_float_32_execution(enabled)
    try:
        yield
    finally:
        tf.config.experimental.enable_tensor_float_32_execution(previous)


def traced_hlo(fn: Callable, specs: Sequence, tf32: bool = False) -> bytes:
    """Serialized pre-optimisation HLO of `fn` (flat tensors in, a tuple of tensors out) compiled whole with XLA for
    the argument `specs` (`tf.TensorSpec`s), traced with TF32 as `tf32` says. Nothing in it depends on a device."""
    import tensorflow as tf
    with tensor_float_32(tf32):
        # A fresh tf.function per call: the TF32 setting is read when the function is converted to HLO.
        return tf.function(fn, jit_compile=True).experimental_get_compiler_ir(*specs)(stage="hlo_serialized")


def write_program(out_dir: str, name: str, hlo: bytes, platforms: Sequence[str] = PLATFORMS, log=print) -> int:
    """Writes `out_dir/name`: the HLO program as a serialised `jax.export` artifact lowered for `platforms` (no device
    of them needed). Returns its size in bytes."""
    blob = internals.hlo_to_jax_exported(hlo, platforms).serialize()
    with open(os.path.join(out_dir, name), "wb") as f:
        f.write(blob)
    log(f"{name}: {len(blob) / 1e3:.0f} kB")
    return len(blob)


def read_manifest(export_dir: str, name: str, expected_format: str, required: Sequence[str], made_by: str) -> dict:
    """`export_dir/name` as JSON, checked: its `format` field is `expected_format` and it has every `required` field.
    `made_by` names what writes such a directory (for the message when there is none)."""
    path = os.path.join(export_dir, name)
    try:
        with open(path) as f:
            manifest = json.load(f)
    except FileNotFoundError as e:
        raise ExportFormatError(f"{path}: no manifest (is {export_dir} a {made_by} output?)") from e
    except json.JSONDecodeError as e:
        raise ExportFormatError(f"{path}: not valid JSON: {e}") from e
    if manifest.get("format") != expected_format:
        raise ExportFormatError(f"{path}: field format is {manifest.get('format')!r}, expected {expected_format!r}")
    for key in required:
        if key not in manifest:
            raise ExportFormatError(f"{path}: field {key} missing")
    return manifest


def load_program(path: str, num_in: int, num_out: int, expected: str):
    """The `jax.export.Exported` stored at `path`, its argument and result counts checked (`expected` says what they
    should be, for the message)."""
    from jax import export
    with open(path, "rb") as f:
        exported = export.deserialize(bytearray(f.read()))
    if len(exported.in_avals) != num_in or len(exported.out_avals) != num_out:
        raise ExportFormatError(f"{path}: takes {len(exported.in_avals)} arguments and returns "
                                f"{len(exported.out_avals)}, expected {expected}")
    return exported


def compile_program(exported, donate_argnums: Sequence[int] = ()):
    """(compiled, compile_s): the program compiled for the default JAX device, arguments `donate_argnums` donated
    (their buffers may be reused for the results)."""
    import jax
    avals = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals]
    jitted = jax.jit(exported.call, donate_argnums=tuple(donate_argnums))
    start = time.perf_counter()
    compiled = jitted.lower(*avals).compile()
    return compiled, time.perf_counter() - start
