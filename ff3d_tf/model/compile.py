"""How FastFlow3D is compiled: `model.compile` = auto | xla | hybrid | none (`ff3d_tf.config.COMPILE_MODES`).

The model has two kinds of work. The point stages (pillarization, the point encoder and its scatter into the grid;
the ungrid head) are gathers, scatters and small matmuls over up to millions of points: XLA fuses them into a few
loops and keeps no per-op temporaries, less time and memory than TensorFlow's kernels. The dense stages (the
convolutional encoder and decoder on the 512 x 512 grids) are convolutions: on a CPU where TensorFlow runs oneDNN's
AVX-512 kernels, those are faster than XLA's (see benchmarks/latency_*.json, `lab/tools/benchmark_latency.py --modes`);
on an AVX2-only CPU, XLA's one program holds the training step's memory lowest (benchmarks/cpu_step_avx2.json); on
GPU both call cuDNN and XLA fuses the rest, so the whole program goes to XLA there.

  xla     one XLA program for the whole forward (and for the training step's forward + backward).
  hybrid  the point stages as their own XLA programs (forward and their gradients; each cloud's point encoding its
          own program, so that the two clouds' scatters run at once, `hybrid_encode`), the dense stages as graph
          kernels; the training step's loss, gradients and optimizer update run in the same graph.
  none    no XLA anywhere (reference and debugging).
  auto    xla where a GPU or TPU is visible; on a CPU, per job ("train": the training step, "inference": the
          forward) and per kind of CPU (`cpu_class`), the mode chosen from measurements there (`AUTO_CPU`).

`cpu_class` sorts a CPU process by the convolution kernels TensorFlow's graph has there: "onednn_avx512" (its oneDNN
operations on, with AVX-512 kernels: AMD Zen 4, Intel Skylake-SP and later), "onednn_avx2" (oneDNN on, AVX2 kernels
only: TF_ENABLE_ONEDNN_OPTS=1 on an AMD Zen 3 or an Intel Haswell to Comet Lake) and "eigen" (oneDNN off: Eigen's
kernels, TensorFlow's default on an AVX2-only CPU and the project's start-up choice there,
`ff3d_tf.cpu.startup_environment`). The rule of each entry and its measurement:
  onednn_avx512  hybrid for both jobs: the fastest training step there, and the fastest forward on large clouds
                 (on small ones xla's can be slightly faster) (benchmarks/latency_cpu.json);
  eigen          per job, in the start-up's environment for the job (`ff3d_tf.cpu.AVX2_STARTUP`): to train, the
                 mode with the lowest peak memory, xla (also the fastest step there); to serve, the fastest forward,
                 hybrid (xla holds a little less) (benchmarks/cpu_step_avx2.json, "after",
                 lab/tools/benchmark_cpu_step.py with both libraries capped to AVX2; docs/benchmarks.md, "The training
                 step on AVX2-only CPUs");
  onednn_avx2    xla for both jobs: for training the fastest step there, though `none` holds less memory
                 (benchmarks/cpu_step_avx2_onednn.json, `lab/tools/benchmark_cpu_step.py --settings after_onednn --jobs
                 train`); for the forward, not measured.

The mode lives on the model (`FastFlow3D.compile_mode`, set by `build_model`) and applies whenever the model is traced
into a `tf.function`, whatever that function's own `jit_compile`. A caller that compiles the whole call with XLA
(`tf.function(jit_compile=True)` around the call, at any depth: the forward of `ff3d_tf.model.forward`, the serving
module, the training step in mode xla, a portable export of `model.stateless_call`) passes `inline_stages=True`:
the model then traces its stages inline, as plain ops, one XLA program in every mode. Without it the stages' own XLA
functions nest inside the caller's program: the values are the same, and so is the optimized inference program, but a
training call (BatchNorm statistics assigned inside the nested functions) makes TensorFlow compile the caller's
program again at every call (seconds a gradient step instead of milliseconds, on the tiny test config).

Precision (`model.mixed_precision` = false | true | auto, `resolve_precision`): "bfloat16" runs the dense stages
(rows C-V: the convolutions, their BatchNorm and the upsampling blocks) in bfloat16 with float32 variables (Keras
"mixed_bfloat16"); the point stages (coordinates, pillar indices, the point encoder, the pillar sums, the head) and
the loss stay float32 in every precision. auto = bfloat16 where oneDNN's bfloat16 convolutions are expected to beat
its float32 ones (`bf16_convolutions_faster`: a CPU with amx_bf16, or an AMD CPU with avx512_bf16) and the
convolutions run as TensorFlow kernels (compile mode hybrid or none); float32 elsewhere: GPU, TPU, mode xla, CPUs
without those flags, and Intel CPUs with avx512_bf16 but no AMX, where oneDNN's avx512_core_bf16 convolution is
slower than its float32 one. The measurements behind each rule: benchmarks/bf16_cpu*.json (docs/benchmarks.md).
"""
from __future__ import annotations

import tensorflow as tf

from ff3d_tf import cpu
from ff3d_tf.config import COMPILE_MODES

RESOLVED_MODES = tuple(m for m in COMPILE_MODES if m != "auto")
AUTO_CHOICE = {"GPU": "xla", "TPU": "xla"}  # `model.compile=auto` off the CPU, for every job
JOBS = ("train", "inference")
CPU_CLASSES = ("onednn_avx512", "onednn_avx2", "eigen")
# `model.compile=auto` on a CPU: (cpu_class, job) -> mode (module docstring; measured in the files it names).
AUTO_CPU = {("onednn_avx512", "train"): "hybrid", ("onednn_avx512", "inference"): "hybrid",
            ("onednn_avx2", "train"): "xla", ("onednn_avx2", "inference"): "xla",
            ("eigen", "train"): "xla", ("eigen", "inference"): "hybrid"}
PRECISIONS = ("float32", "bfloat16")  # what `resolve_precision` returns: the compute dtype of rows C-V
# CPU flags (Linux /proc/cpuinfo) under which oneDNN has bfloat16 convolution kernels of its own: AVX-512 BF16
# (Intel Cooper Lake, Sapphire Rapids and later; AMD Zen 4 and later) and AMX-BF16 (Intel Sapphire Rapids and later,
# listed only where the OS enables the tiles; a VM may hide them).
BF16_CPU_FLAGS = ("avx512_bf16", "amx_bf16")


def accelerator_type() -> str:
    """"TPU", "GPU" or "CPU": the kind of device the model runs on by default."""
    for kind in ("TPU", "GPU"):
        if tf.config.list_logical_devices(kind):
            return kind
    return "CPU"


def cpu_class(onednn_enabled: bool | None = None, info: cpu.CpuInfo | None = None, environ=None) -> str:
    """This process's kind of CPU for `AUTO_CPU`: "onednn_avx512", "onednn_avx2" or "eigen" (module docstring).
    `onednn_enabled`: whether TensorFlow's oneDNN operations are on (default: in this process); `info`, `environ`:
    the CPU and the caps on it (default: this machine's, `ff3d_tf.cpu.usable_flags`)."""
    if onednn_enabled is None:
        from ff3d_tf import internals
        onednn_enabled = internals.onednn_enabled()
    if not onednn_enabled:
        return "eigen"
    info = info or cpu.read_cpuinfo()
    return "onednn_avx512" if info is not None and "avx512f" in cpu.usable_flags(info, environ) else "onednn_avx2"


def resolve_compile_mode(mode: str, device_type: str | None = None, job: str = "inference",
                         cpu_kind: str | None = None) -> str:
    """"auto" -> the mode for `job` ("train" or "inference") on `device_type` (default: the visible accelerator),
    on a CPU of `cpu_kind` (default: `cpu_class()` of this process); other modes unchanged."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"model.compile={mode!r}: one of {', '.join(COMPILE_MODES)}")
    if job not in JOBS:
        raise ValueError(f"job={job!r}: one of {', '.join(JOBS)}")
    if mode != "auto":
        return mode
    device_type = device_type or accelerator_type()
    if device_type != "CPU":
        return AUTO_CHOICE[device_type]
    kind = cpu_kind or cpu_class()
    if kind not in CPU_CLASSES:
        raise ValueError(f"cpu_kind={kind!r}: one of {', '.join(CPU_CLASSES)}")
    return AUTO_CPU[(kind, job)]


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


def hybrid_encode(encode_points, inputs, training, point_programs: str = "per_cloud"):
    """The point encoding of compile mode hybrid: `encode_points(inputs, training, stage=...)` (a model's
    `FastFlow3D.encode_points`) with its parts as XLA programs of their own.

    XLA's CPU backend runs a scatter on one thread and the instructions of one program one after another, so the two
    clouds' pillar scatters in one program take one core each in turn. As separate programs (`point_programs`
    "per_cloud": the pillar cells of each cloud, the statistics of training, each cloud's encoding and scatter,
    `PointEncoder.call`'s `stage`), the clouds depend on nothing of each other and TensorFlow's executor runs them at
    the same time on its inter-op threads; so do their gradient programs. The values are those of one program
    (`point_programs` "one", the execution plan's field)."""
    if point_programs == "one":
        return xla_function(lambda x: encode_points(x, training))(inputs)
    return encode_points(inputs, training, stage=xla_function)


def cpu_bf16_support(cpuinfo: str | None = None) -> tuple[str, tuple[str, ...]]:
    """(vendor, flags): the "vendor_id" of `cpuinfo` (the text of /proc/cpuinfo; default: this machine's,
    `ff3d_tf.cpu.read_cpuinfo`), e.g. "GenuineIntel" or "AuthenticAMD" ("" if none), and the flags of
    `BF16_CPU_FLAGS` that every processor in it lists and that oneDNN may use under ONEDNN_MAX_CPU_ISA
    (`ff3d_tf.cpu.usable_flags`). ("", ()) where the file cannot be read; () where it has no flags line (not x86)."""
    info = cpu.parse_cpuinfo(cpuinfo) if cpuinfo is not None else cpu.read_cpuinfo()
    if info is None:
        return "", ()
    usable = cpu.usable_flags(info)
    return info.vendor, tuple(f for f in BF16_CPU_FLAGS if f in usable)


def bf16_convolutions_faster(vendor: str, flags: tuple[str, ...]) -> tuple[bool, str]:
    """(whether oneDNN's bfloat16 convolutions are expected to beat float32 on this CPU, why).

    amx_bf16: AMX tiles (TDPBF16PS), oneDNN's avx10_1_512_amx kernels: the dense stages, the forward and the
    training step faster in bfloat16 (benchmarks/bf16_cpu_amx.json).
    AMD with avx512_bf16 (Zen 4 and later): the forward faster in bfloat16 (benchmarks/bf16_cpu_amd.json).
    Intel with avx512_bf16 and no AMX (a VM that hides AMX): every oneDNN bfloat16 convolution kernel
    (brg_conv_fwd:avx512_core_bf16) slower than its float32 one (brg_conv_fwd:avx512_core), and so the forward and the
    training step (benchmarks/bf16_cpu.json)."""
    if "amx_bf16" in flags:
        return True, "CPU has amx_bf16"
    if "avx512_bf16" in flags and vendor == "AuthenticAMD":
        return True, "AMD CPU has avx512_bf16"
    if "avx512_bf16" in flags:
        return False, (f"{vendor or 'this'} CPU has avx512_bf16 but no amx_bf16: oneDNN's bfloat16 convolutions are "
                       f"slower than float32 there")
    return False, f"CPU has none of {', '.join(BF16_CPU_FLAGS)}"


def resolve_precision(mixed_precision, compile_mode: str, device_type: str | None = None,
                      cpu: tuple[str, tuple[str, ...]] | None = None,
                      onednn_enabled: bool | None = None) -> tuple[str, str]:
    """(precision, reason): `model.mixed_precision` (false, true or "auto") -> "float32" or "bfloat16" for a resolved
    `compile_mode` on `device_type` (default: the visible accelerator) with `cpu` = (vendor, flags) (default:
    `cpu_bf16_support()`). `reason` says why, for the log line at start.

    bfloat16 never meets TensorFlow's oneDNN operations on a CPU whose oneDNN has no bfloat16 convolutions (none of
    `BF16_CPU_FLAGS` usable, e.g. an AVX2-only CPU): `true` there, in compile mode hybrid or none with oneDNN on
    (`onednn_enabled`, default: this process), raises ValueError saying how to run it (oneDNN's own error, "could not
    create a primitive descriptor", would come at the first convolution). The tools' start-up leaves oneDNN off on
    such CPUs (`ff3d_tf.cpu.startup_environment`), so only a TF_ENABLE_ONEDNN_OPTS=1 set by hand gets here."""
    check_resolved(compile_mode)
    if mixed_precision is True or mixed_precision is False:
        if mixed_precision and compile_mode != "xla" and (device_type or accelerator_type()) == "CPU":
            vendor, flags = cpu_bf16_support() if cpu is None else cpu
            if onednn_enabled is None:
                from ff3d_tf import internals
                onednn_enabled = internals.onednn_enabled()
            if onednn_enabled and not flags:
                raise ValueError(
                    f"model.mixed_precision=true with TensorFlow's oneDNN operations on, on a CPU with none of "
                    f"{', '.join(BF16_CPU_FLAGS)} (usable): oneDNN has no bfloat16 convolutions there. Start Python "
                    f"with TF_ENABLE_ONEDNN_OPTS=0 (Eigen's bfloat16 kernels), or train in float32 "
                    f"(model.mixed_precision=false)")
        return ("bfloat16" if mixed_precision else "float32"), "as set"
    if mixed_precision != "auto":
        raise ValueError(f"model.mixed_precision={mixed_precision!r}: true, false or auto")
    device_type = device_type or accelerator_type()
    if device_type != "CPU":
        return "float32", f"{device_type}: auto keeps float32 off the CPU"
    if compile_mode == "xla":
        return "float32", "model.compile=xla: XLA's CPU convolutions are not oneDNN's bfloat16 kernels"
    faster, reason = bf16_convolutions_faster(*(cpu_bf16_support() if cpu is None else cpu))
    return ("bfloat16" if faster else "float32"), reason


def describe_precision(precision: str) -> str:
    """One line saying what runs in which dtype (printed at start, recorded with benchmarks)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision={precision!r}: one of {', '.join(PRECISIONS)}")
    if precision == "float32":
        return "everything in float32"
    return ("convolutions (rows C-V) in bfloat16 with float32 variables; points, pillar sums, head and loss in "
            "float32")
