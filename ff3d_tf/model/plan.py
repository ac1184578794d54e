"""The execution plan: how FastFlow3D computes the paper's table in one process, for one job, on one device.

What the model computes is the table (`FastFlow3D.table_forward`: rows A to Z, one call per row). How the fused
forward (`FastFlow3D.call` with `forward="fused"`) computes it is this plan: the compile mode, the precision of rows
C-V, and the cheaper forms of the table's linear arithmetic, each equal to the table's rows up to float rounding
(`tests/model/test_plan.py` runs every field against the table forward, values and gradients). The plan is one frozen
value, resolved once from the config, the device and the job (`resolve`), passed to the model when it is built,
logged at start (`describe`) and recorded in the model's config (`FastFlow3D.get_config()["plan"]`, and
`execution_plan.json` beside a trained model or an export).

The fields, with the rows each rewrites (docs/architecture.md has the same table):

  compile_mode             all        xla | hybrid | none (`ff3d_tf.model.compile`)
  precision                C-V        float32 | bfloat16 (`ff3d_tf.model.compile.resolve_precision`)
  forward                  A-Z        fused (this plan's forms) | table (the rows as the table lists them; no form)
  matmul_1x1               S-U (U1, U3)  a 1x1 convolution as a matrix product over the last axis
  stride2_phase_gradients  C, G, M    the stride-2 convolutions' gradients as stride-1 convolutions on the input's
                                      phases (`ops.conv2d_stride2`)
  u6_into_next_u1          S, T       U6 composed with the next block's U1 into one 3x3 convolution to U1's channels
                                      (`layers.UpsampleSkip.into_next`)
  v_with_head              V, Y, Z    row V composed with the paper head's grid part: one 3x3 convolution to 3
                                      channels (`FastFlow3D.grid_stages`)
  decoder_chain            U (U5, U6), V  with `v_with_head`: row U's U5, U6 and that convolution as one composed
                                      7x7 convolution (`ops.conv_chain_same`)
  point_programs           A, B       compile mode hybrid: per_cloud (each cloud's encoding its own XLA program) | one
  remat_encoder            C-R        training recomputes the encoder stages' activations in the backward pass
  fold_batch_norm          C-R        inference convolves with the BatchNorm folded into the kernel and a bias

Row A's chunk loop also takes each t0 point's linear share of rows Y and Z (`FastFlow3D.encode_points`): that is what
the fused forward is, in every plan.
"""
from __future__ import annotations

import dataclasses
import json
import os

from ff3d_tf.config import FORWARDS, ModelConfig
from ff3d_tf.model import compile as compile_lib
from ff3d_tf.model import heads

POINT_PROGRAMS = ("per_cloud", "one")
# The fields that choose a cheaper form of the table's arithmetic (the table forward has every one of them off).
PLAN_NAME = "execution_plan.json"  # the plan that computed a model, beside its config (a model_dir, an export)
FORM_FIELDS = ("matmul_1x1", "stride2_phase_gradients", "u6_into_next_u1", "v_with_head", "decoder_chain",
               "remat_encoder", "fold_batch_norm")


@dataclasses.dataclass(frozen=True)
class ExecutionPlan:
    """How the model computes the table (module docstring). The defaults are the fused forward without XLA."""

    compile_mode: str = "none"
    precision: str = "float32"
    forward: str = "fused"
    matmul_1x1: bool = True
    stride2_phase_gradients: bool = False
    u6_into_next_u1: bool = True
    v_with_head: bool = True
    decoder_chain: bool = False
    point_programs: str = "per_cloud"
    remat_encoder: bool = False
    fold_batch_norm: bool = False

    def __post_init__(self):
        compile_lib.check_resolved(self.compile_mode)
        for name, value, choices in (("precision", self.precision, compile_lib.PRECISIONS),
                                     ("forward", self.forward, FORWARDS),
                                     ("point_programs", self.point_programs, POINT_PROGRAMS)):
            if value not in choices:
                raise ValueError(f"execution plan: {name}={value!r}: one of {', '.join(choices)}")
        for name in FORM_FIELDS:
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"execution plan: {name}={getattr(self, name)!r}: true or false")
        if self.forward == "table" and any(getattr(self, name) for name in FORM_FIELDS):
            raise ValueError(f"execution plan: forward=table computes the rows as the table lists them; "
                             f"{', '.join(n for n in FORM_FIELDS if getattr(self, n))} apply to forward=fused only")
        if self.decoder_chain and not self.v_with_head:
            raise ValueError("execution plan: decoder_chain composes U5 and U6 with row V's convolution composed "
                             "with the head (v_with_head=true)")
        if self.decoder_chain and self.precision != "float32":
            raise ValueError("execution plan: decoder_chain computes in float32; with precision=bfloat16 it would "
                             "replace the bfloat16 convolutions")

    @classmethod
    def table(cls, compile_mode: str = "none", precision: str = "float32") -> "ExecutionPlan":
        """The table forward: every row as the paper lists it, no form."""
        return cls(compile_mode=compile_mode, precision=precision, forward="table",
                   **{name: False for name in FORM_FIELDS})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "ExecutionPlan":
        unknown = set(values) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"execution plan: unknown field(s) {', '.join(sorted(unknown))}")
        return cls(**values)

    def replace(self, **changes) -> "ExecutionPlan":
        return dataclasses.replace(self, **changes)

    def describe(self) -> str:
        """One line for the log at start: the mode, precision and forward, then the forms in use."""
        forms = [name for name in FORM_FIELDS if getattr(self, name)]
        programs = f", point programs {self.point_programs}" if self.compile_mode == "hybrid" else ""
        return (f"compile {self.compile_mode} ({compile_lib.describe(self.compile_mode)}), {self.precision}, "
                f"forward {self.forward}{programs}; forms: {', '.join(forms) or 'none'}")


def resolve(model: ModelConfig, job: str = "inference", compile_mode: str | None = None,
            device_type: str | None = None, cpu_kind: str | None = None) -> tuple[ExecutionPlan, dict]:
    """(plan, why): the plan of `model` (the config's model section) for `job` ("train" or "inference") on
    `device_type` (default: the visible accelerator) and a CPU of `cpu_kind` (default: this process's,
    `compile_lib.cpu_class`). `compile_mode` overrides `model.compile`. `why` holds the log lines that say how
    "auto" was resolved ("compile", "precision"), and "hint" where float32 is set and `auto` would take bfloat16.

    The rules, each measured where `ff3d_tf.model.compile` says: XLA's CPU backend takes the stride-2 gradients on
    phases (mode xla on a CPU); the decoder chain where the dense stages are float32 and XLA compiles them for training
    or they run for inference (TensorFlow's own kernels in training, op by op, pay more for the chain's shifted sums'
    gradients than the convolutions it replaces, and so would bfloat16's oneDNN convolutions); the other forms always.
    """
    requested = model.compile if compile_mode is None else compile_mode
    mode = compile_lib.resolve_compile_mode(requested, device_type, job=job, cpu_kind=cpu_kind)
    precision, precision_reason = compile_lib.resolve_precision(model.mixed_precision, mode, device_type)
    why = {"compile": f"model.compile={requested} -> {mode} for {job} ({compile_lib.describe(mode)})",
           "precision": f"model.mixed_precision={str(model.mixed_precision).lower()} -> {precision} "
                        f"({precision_reason}; {compile_lib.describe_precision(precision)})"}
    if model.mixed_precision is False:
        auto, auto_reason = compile_lib.resolve_precision("auto", mode, device_type)
        if auto == "bfloat16":
            why["hint"] = (f"model.mixed_precision=auto would run bfloat16 here ({auto_reason}): faster, and less "
                           "memory to train (docs/benchmarks.md, bfloat16 on a CPU)")
    if model.forward == "table":
        return ExecutionPlan.table(mode, precision), why
    composes = heads.HEADS[model.head].composes_with_v  # the head's first layer is linear in row V's output
    on_cpu = (device_type or compile_lib.accelerator_type()) == "CPU"
    plan = ExecutionPlan(
        compile_mode=mode, precision=precision, forward="fused", matmul_1x1=True,
        stride2_phase_gradients=mode == "xla" and on_cpu, u6_into_next_u1=True, v_with_head=composes,
        decoder_chain=composes and precision == "float32" and (job == "inference" or mode == "xla"),
        point_programs="per_cloud", remat_encoder=bool(model.remat_encoder), fold_batch_norm=False)
    return plan, why


def save(plan: ExecutionPlan, directory: str) -> str:
    """Writes `plan` as `directory/execution_plan.json` (local or gs://) and returns the path: a trained model and an
    export say which forms, precision and compile mode computed them."""
    import tensorflow as tf
    path = os.path.join(directory, PLAN_NAME)
    with tf.io.gfile.GFile(path, "w") as f:
        f.write(json.dumps(plan.to_dict(), indent=1) + "\n")
    return path
