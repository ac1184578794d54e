"""The model's forward as portable XLA programs: one `jax.export` artifact per point bucket and precision, weights
saved once (the directory's layout: `ff3d_tf.xla_export_dir`; the training step is added by
`ff3d_tf.training.xla_step_export`).

TensorFlow compiles the forward with XLA (`jit_compile=True`); this module takes that program before any
optimisation, with the weights as plain arguments, and serialises it so that a process without TensorFlow (JAX/XLA
only, e.g. on a GPU machine) compiles and runs it: `ff3d_tf.inference.xla_artifact` reads it back.

  1. `tf.function(jit_compile=True)` over `model.stateless_call` with flat arguments (weights, then the six inputs of
     one padded bucket): `experimental_get_compiler_ir(...)(stage="hlo_serialized")` is the pre-optimisation HLO,
     in which nothing depends on the device.
  2. jaxlib converts the HLO to StableHLO; a JAX primitive whose lowering inlines that module makes it a JAX
     function, and `jax.export` lowers it for the platforms asked (CPU and CUDA, on a machine without a GPU) and
     serialises it with StableHLO's versioned portable format (both steps: `ff3d_tf.xla_program`, which NSFP's export
     shares).

TF32: TensorFlow writes its TF32 setting into the program (convolution/matmul precision HIGHEST when disabled,
DEFAULT when enabled), so each precision is traced with the setting it names (see `xla_export_dir.PRECISIONS`).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
import tensorflow as tf

from ff3d_tf import xla_export_dir, xla_program
from ff3d_tf.config import ExperimentConfig
from ff3d_tf.data.pairs import bucket_size
from ff3d_tf.inference import xla_artifact
from ff3d_tf.schema import model_input_keys
from ff3d_tf.xla_export_dir import OUTPUT_KEYS, input_specs, model_weights, tracing_model

PLATFORMS = xla_program.PLATFORMS

# Other programs of the same model and weights that an export can add beside its artifacts (manifest "variants", by
# name; names join with "+"): lab/tools/profile_xla.py times and profiles them against the plain artifacts, on the same
# inputs, and checks that they compute the same flow.
VARIANTS = {"fold_bn": "the BatchNorm folded into each ConvBlock's convolution (the plan's fold_batch_norm)",
            "one_chunk": "the point encoder over the whole cloud in one chunk (ops.ONE_CHUNK)"}


def forward_hlo(model, batch_size: int, padded_points: int, tf32: bool = False) -> bytes:
    """Serialized pre-optimisation HLO of `model`'s inference forward for one bucket, weights as arguments.

    Arguments: `model_weights(model)` in order, then the inputs of `input_specs`; results: flow_mps [B,P,3],
    point_valid [B,P].
    """
    num_trainable = len(model.trainable_variables)
    num_weights = len(model_weights(model))
    keys = model_input_keys(model.num_frames)

    def forward(*flat):
        outputs, _ = model.stateless_call(list(flat[:num_trainable]), list(flat[num_trainable:num_weights]),
                                          dict(zip(keys, flat[num_weights:])), training=False,
                                          inline_stages=True)
        return tuple(outputs[k] for k in OUTPUT_KEYS)

    specs = [tf.TensorSpec(v.shape, v.dtype) for v in model_weights(model)] + input_specs(batch_size, padded_points,
                                                                                          model.num_frames)
    return xla_program.traced_hlo(forward, specs, tf32)


def check_variants(variants: Sequence[str]) -> None:
    for variant in variants:
        unknown = [part for part in variant.split("+") if part not in VARIANTS]
        if unknown or not variant:
            raise ValueError(f"forward variant {variant!r} unknown; one of {', '.join(VARIANTS)}, or several "
                             f"joined with '+'")


def variant_model(cfg: ExperimentConfig, precision: str, model, variant: str):
    """A model that traces `variant` (see VARIANTS) for `precision`, with `model`'s weights as its arguments."""
    from ff3d_tf.model import build_model, ops, plan
    check_variants([variant])
    parts = variant.split("+")
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, mixed_precision=precision == "bfloat16"))
    variant_plan = plan.resolve(cfg.model)[0].replace(fold_batch_norm="fold_bn" in parts)
    tracer = build_model(cfg, point_chunk_size=ops.ONE_CHUNK if "one_chunk" in parts else None, plan=variant_plan)
    if [(v.shape, v.dtype) for v in model_weights(tracer)] != [(v.shape, v.dtype) for v in model_weights(model)]:
        raise ValueError(f"variant {variant} changes the weights' shapes or dtypes")
    return tracer


def variant_file(padded_points: int, precision: str, variant: str) -> str:
    return xla_artifact.artifact_name(padded_points, precision).replace(".jaxexport",
                                                                        f".{variant.replace('+', '_')}.jaxexport")


def _reference(model, manifest: dict, rng: np.random.Generator) -> dict:
    """Inputs and TensorFlow's results (CPU, XLA) for the first float32 forward artifact, for the runner to compare
    against what the exported program computes on its device (`xla_export_dir.REFERENCE_NAME`)."""
    forward = next((e for e in manifest["artifacts"] if e["precision"] == "float32"), None)
    if forward is None:
        return {}
    inputs = xla_export_dir.random_inputs(manifest, forward, rng)
    keys = manifest["input_keys"]
    out = tf.function(lambda x: model(x, training=False, inline_stages=True), jit_compile=True)(
        dict(zip(keys, inputs)))
    return {**{f"forward/{k}": a for k, a in zip(keys, inputs)},
            **{f"forward/out/{k}": out[k].numpy() for k in OUTPUT_KEYS},
            "forward/padded_points": np.int64(forward["padded_points"])}


def export_forward(cfg: ExperimentConfig, model, points: Sequence[int], out_dir: str,
                   precisions: Sequence[str] = ("float32",), platforms: Sequence[str] = PLATFORMS,
                   batch_size: int = 1, weights_source: str = "random initialisation", log=print,
                   reference: bool = False, variants: Sequence[str] = (),
                   variant_points: Sequence[int] = (), variant_precisions: Sequence[str] = ()) -> dict:
    """Writes `out_dir` (layout in `ff3d_tf.xla_export_dir`): the weights of `model` and one forward artifact per
    (bucket, precision).

    `points` are cloud sizes; each is padded to its bucket (`data.point_bucket_base`), as the input pipeline does.
    `reference`: also write TensorFlow's results for the first float32 artifact (`xla_export_dir.REFERENCE_NAME`).
    `variants` (names of VARIANTS): the same for each, at `variant_points` and `variant_precisions` (default `points`,
    `precisions`), listed under the manifest's "variants" and not among its artifacts (no predictor picks them).
    The manifest also records the order of the sweeps the model reads ("partner", "temporal").
    Returns the manifest (also written as manifest.json).
    """
    xla_export_dir.check_precisions([*precisions, *variant_precisions])
    check_variants(variants)
    if not points or min(points) < 1:
        raise ValueError(f"points must be positive cloud sizes, got {list(points)}")
    manifest = xla_export_dir.new_export(cfg, model, out_dir, platforms, weights_source)
    # The order of the sweeps the model reads (`ff3d_tf.inference.predictor.SweepOrder`; its count: "input_keys").
    manifest.update(partner=getattr(model, "partner", "previous"), temporal=model.temporal)
    written: dict[str, int] = {}

    def write(tracer, precision: str, sizes: Sequence[int], file_name, entries: list, **extra) -> None:
        """One artifact per bucket of `sizes` (a bucket written once), an entry per size."""
        for n in sizes:
            padded = bucket_size(n, cfg.data.point_bucket_base)
            name = file_name(padded, precision)
            if name not in written:
                written[name] = xla_program.write_program(out_dir, name, forward_hlo(tracer, batch_size, padded,
                                                                           tf32=precision == "tf32"), platforms, log)
            entries.append({"points": int(n), "padded_points": padded, "batch_size": batch_size,
                            "precision": precision, "file": name, "bytes": written[name], **extra})

    for precision in precisions:
        write(tracing_model(cfg, precision, model), precision, points, xla_artifact.artifact_name,
              manifest["artifacts"])
    for variant in variants:
        entries = manifest.setdefault("variants", {}).setdefault(variant, [])
        for precision in variant_precisions or precisions:
            write(variant_model(cfg, precision, model, variant), precision, variant_points or points,
                  lambda padded, p, v=variant: variant_file(padded, p, v), entries, variant=variant)
    if reference:
        xla_export_dir.add_reference(out_dir, _reference(model, manifest, np.random.default_rng(0)))
    xla_export_dir.write_manifest(out_dir, manifest)
    return manifest
