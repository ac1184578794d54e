"""How FastFlow3D is compiled: `model.compile` = auto | xla | hybrid | none (`ff3d_tf.config.COMPILE_MODES`).

The model has two kinds of work. The point stages (pillarization, the point encoder and its scatter into the grid;
the ungrid head) are gathers, scatters and small matmuls over up to millions of points: XLA fuses them into a few
loops and keeps no per-op temporaries, about half the time and memory of TensorFlow's kernels. The dense stages (the
convolutional encoder and decoder on the 512 x 512 grids) are convolutions: on CPU, TensorFlow's oneDNN kernels are
faster than XLA's (see benchmarks/latency_*.json, `tools/benchmark_latency.py --modes`); on GPU both call cuDNN and
XLA fuses the rest, so the whole program goes to XLA there.

  xla     one XLA program for the whole forward (and for the training step's forward + backward).
  hybrid  the point stages as their own XLA programs (forward and their gradients), the dense stages as graph
          kernels; the training step's loss, gradients and optimizer update run in the same graph.
  none    no XLA anywhere (reference and debugging).
  auto    hybrid on CPU, xla where a GPU or TPU is visible.

The mode lives on the model (`FastFlow3D.compile_mode`, set by `build_model`) and applies whenever the model is traced
into a `tf.function`, whatever that function's own `jit_compile`. A caller that compiles the whole call with XLA
(`tf.function(jit_compile=True)` around the call, at any depth: the forward of `ff3d_tf.model.forward`, the serving
module, the training step in mode xla, a portable export of `model.stateless_call`) passes `inline_stages=True`:
the model then traces its stages inline, as plain ops, one XLA program in every mode. Without it the stages' own XLA
functions nest inside the caller's program: the values are the same, and so is the optimized inference program, but a
training call (BatchNorm statistics assigned inside the nested functions) makes TensorFlow compile the caller's
program again at every call (measured on CPU, tiny test config, 2 x 1,000 points: 6.7 s a gradient step in mode xla,
0.02 s with the flag).
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf.config import COMPILE_MODES

RESOLVED_MODES = tuple(m for m in COMPILE_MODES if m != "auto")
AUTO_CHOICE = {"CPU": "hybrid", "GPU": "xla", "TPU": "xla"}


def accelerator_type() -> str:
    """"TPU", "GPU" or "CPU": the kind of device the model runs on by default."""
    for kind in ("TPU", "GPU"):
        if tf.config.list_logical_devices(kind):
            return kind
    return "CPU"


def resolve_compile_mode(mode: str, device_type: str | None = None) -> str:
    """"auto" -> the mode for `device_type` (default: the visible accelerator); other modes unchanged."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"model.compile={mode!r}: one of {', '.join(COMPILE_MODES)}")
    if mode != "auto":
        return mode
    return AUTO_CHOICE[device_type or accelerator_type()]


def check_resolved(mode: str) -> str:
    if mode not in RESOLVED_MODES:
        raise ValueError(f"compile_mode={mode!r}: one of {', '.join(RESOLVED_MODES)} (resolve 'auto' with "
                         f"resolve_compile_mode first)")
    return mode


def describe(mode: str) -> str:
    """One line saying what runs where in a resolved mode (printed at start, recorded with benchmarks)."""
    return {"xla": "whole forward and training step in one XLA program",
            "hybrid": "point stages in XLA, convolutions as TensorFlow graph kernels",
            "none": "no XLA"}[check_resolved(mode)]


def xla_function(fn):
    """`fn` as a tf.function compiled by XLA (also its gradient). Traced once per call of the returned function's
    trace, so callers create it while tracing their own graph."""
    return tf.function(fn, jit_compile=True, autograph=False)
