"""Typed experiment configuration: frozen dataclasses, YAML overrides, validated before any work starts.

YAML files in `configs/` hold only overrides of the defaults below (which are the paper's values where the paper gives
one). `--set section.field=value` overrides on the command line; values are parsed with `yaml.safe_load`.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import types
import typing
from typing import Any

import numpy as np
import yaml

from ff3d_tf import schema


class ConfigError(ValueError):
    """A configuration that cannot work; raised before any data is read or any step runs."""


MAX_PILLARS_PER_AXIS = 16384  # 512 in the paper; larger grids cannot fit an accelerator's memory
MAX_WIDTH = 65536  # channels of any layer
MAX_BUCKET_BASE = 1 << 17  # point buckets reach 12288 x base and must stay within int32
MAX_GRU_ITERATIONS = 64  # model.gru_iterations


def _in_range(key: str, value, lo, hi) -> None:
    """ConfigError naming the key and the allowed closed range [lo, hi] (None: unbounded) unless value is in it."""
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        allowed = f">= {lo}" if hi is None else f"<= {hi}" if lo is None else f"in [{lo}, {hi}]"
        raise ConfigError(f"{key}={value!r}: must be {allowed}")


@dataclasses.dataclass(frozen=True)
class GridConfig:
    """Pillar grid in the vehicle frame at t0 (paper appendix: 512 x 512 pillars, 170 m x 170 m, z in [-3, 3] m)."""

    num_pillars_x: int = 512
    num_pillars_y: int = 512
    x_range_m: tuple[float, float] = (-85.0, 85.0)
    y_range_m: tuple[float, float] = (-85.0, 85.0)
    z_range_m: tuple[float, float] = (-3.0, 3.0)

    @property
    def pillar_size_x_m(self) -> float:
        return (self.x_range_m[1] - self.x_range_m[0]) / self.num_pillars_x

    @property
    def pillar_size_y_m(self) -> float:
        return (self.y_range_m[1] - self.y_range_m[0]) / self.num_pillars_y

    def validate(self) -> None:
        for name in ("num_pillars_x", "num_pillars_y"):
            n = getattr(self, name)
            if n <= 0 or n % 8:
                lo, hi = max(8, n // 8 * 8), n // 8 * 8 + 8
                raise ConfigError(
                    f"grid.{name}={n}: the U-Net halves the grid three times, so it must be a positive multiple of 8 "
                    f"(e.g. {lo} or {hi})")
            _in_range(f"grid.{name}", n, 8, MAX_PILLARS_PER_AXIS)
        for name in ("x_range_m", "y_range_m", "z_range_m"):
            lo, hi = getattr(self, name)
            if not lo < hi:
                raise ConfigError(f"grid.{name}={(lo, hi)}: need min < max")


ABLATED_CLASSES = {"pedestrian": (schema.CLASS_PEDESTRIAN,), "cyclist": (schema.CLASS_CYCLIST,),
                   "pedestrian_cyclist": (schema.CLASS_PEDESTRIAN, schema.CLASS_CYCLIST)}  # flow class ids
CLASS_ABLATIONS = ("none",) + tuple(f"{c}_{mode}" for c in ABLATED_CLASSES for mode in ("stationary", "ignored"))


DATA_SOURCES = ("wod", "pair_records")  # data.source
# data.labels: human (the boxes' flow labels), pseudo (NSFP pseudo-labels of pair records, `tools/pseudo_label.py`) or
# self (no flow labels: the self-supervised losses' per-point fields, `tools/prepare_self_supervision.py`).
TRAINING_LABELS = ("human", "pseudo", "self")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Reading WOD records and turning them into model input pairs."""

    # wod: WOD Frame TFRecords decoded on the fly; pair_records: decode-once model examples written by
    # `tools/write_pair_records.py` (from WOD segments or Argoverse 2 logs) or `tools/pseudo_label.py`.
    source: str = "wod"
    # The flow that trains the model: human (the boxes' labels) or pseudo (`flow_mps_pseudo_t0` of pair records).
    # Evaluation always scores against the human labels.
    labels: str = "human"
    laser_names: tuple[int, ...] = schema.ALL_LASERS  # TOP, FRONT, SIDE_LEFT, SIDE_RIGHT, REAR
    returns: tuple[int, ...] = (1,)  # 1 = first return, 2 = second return
    max_frame_gap_s: float = 0.15  # a sweep further after the one before is missing: an error (or skipped)
    # Sweeps per example: the current one and num_frames - 1 past ones, each moved into the current vehicle frame
    # (2: the paper's pair; more for model.temporal stack or delta; at most schema.MAX_NUM_FRAMES).
    num_frames: int = 2
    # Which sweep the t-1 slot holds (`schema.PARTNERS`): previous (WOD, own sequences) or next (Argoverse 2 challenge
    # records). None: from the data (the pair records' manifest; previous for WOD read on the fly). Training saves the
    # value it resolved with the model; a model that has none is of "previous".
    partner: str | None = None
    ego_motion_compensation: bool = True  # move the t-1 cloud into the t0 vehicle frame (paper appendix)
    crop_to_grid: bool = True  # drop points outside the pillar grid in the input pipeline (they get no prediction)
    skip_bad_records: bool = False  # False: a bad record stops the job with its file/record/field
    shuffle_buffer: int = 64
    cache_decoded: bool = False  # keep decoded pairs in memory (small datasets, e.g. the synthetic default)
    # Point counts are padded up to the next bucket so XLA compiles once per bucket, not once per point count.
    point_bucket_base: int = 16384
    # Paper Table 4: none | {pedestrian, cyclist, pedestrian_cyclist}_{stationary, ignored} (training labels only).
    class_ablation: str = "none"
    max_training_segments: int = 0  # 0 = all; the data-size study sets this
    point_keep_fraction: float = 1.0  # point-density study: random share of points kept per frame
    remove_ground_below_z_m: float | None = None  # ground-removal study: drop points below this z (vehicle frame)
    # DeltaFlow's input (its authors remove ground from every sweep): every sweep's ground points are left out of the
    # model's input by the records' masks (`schema.ground_keys`); they keep their place in the example and get flow 0.
    drop_ground: bool = False
    # Training augmentation (off in the paper config), drawn per pair from the training seed after the decode-once
    # records: with this probability both clouds move by one z offset drawn uniformly from the range (m) ...
    augment_height_offset_prob: float = 0.0
    augment_height_offset_m: tuple[float, float] = (-0.5, 0.5)
    # ... and with this probability each of x and y is mirrored (both clouds and the flow alike) ...
    augment_flip_prob: float = 0.0
    # ... and every point of every cloud moves by a normal draw of this standard deviation per axis (m; 0: none),
    # clipped to +-augment_jitter_clip_m.
    augment_jitter_sigma_m: float = 0.0
    augment_jitter_clip_m: float = 0.05

    def validate(self) -> None:
        if self.source not in DATA_SOURCES:
            raise ConfigError(f"data.source={self.source!r} unknown; one of {DATA_SOURCES}")
        if self.labels not in TRAINING_LABELS:
            raise ConfigError(f"data.labels={self.labels!r} unknown; one of {TRAINING_LABELS}")
        if self.labels != "human" and self.source != "pair_records":
            raise ConfigError(f"data.labels={self.labels}: its fields live in pair records (data.source=pair_records, "
                              "written by tools/pseudo_label.py or tools/prepare_self_supervision.py)")
        if not isinstance(self.drop_ground, bool):
            raise ConfigError(f"data.drop_ground={self.drop_ground!r}: true or false")
        if self.drop_ground and self.source != "pair_records":
            raise ConfigError("data.drop_ground=true: every sweep's ground masks live in pair records "
                              "(data.source=pair_records; Argoverse 2 records carry them, tools/add_ground_masks.py "
                              "adds them to others)")
        if self.source == "pair_records" and not self.ego_motion_compensation:
            raise ConfigError("data.ego_motion_compensation=false: pair records hold the t-1 cloud already moved "
                              "into the t0 frame; use data.source=wod for the ego-motion study")
        problem = schema.lidar_selection_problem(self.laser_names, self.returns)
        if problem is not None:
            raise ConfigError(f"data.{problem}")
        if self.max_frame_gap_s <= 0:
            raise ConfigError(f"data.max_frame_gap_s={self.max_frame_gap_s}: must be > 0")
        _in_range("data.point_bucket_base", self.point_bucket_base, 1, MAX_BUCKET_BASE)
        if isinstance(self.num_frames, bool) or not isinstance(self.num_frames, int):
            raise ConfigError(f"data.num_frames={self.num_frames!r}: an integer")
        _in_range("data.num_frames", self.num_frames, 2, schema.MAX_NUM_FRAMES)
        if self.partner is not None and self.partner not in schema.PARTNERS:
            raise ConfigError(f"data.partner={self.partner!r}: one of {', '.join(schema.PARTNERS)}, or null (from "
                              "the data)")
        _in_range("data.shuffle_buffer", self.shuffle_buffer, 1, None)
        _in_range("data.max_training_segments", self.max_training_segments, 0, None)
        if self.class_ablation not in CLASS_ABLATIONS:
            raise ConfigError(f"data.class_ablation={self.class_ablation!r} unknown; one of {CLASS_ABLATIONS}")
        if not 0.0 < self.point_keep_fraction <= 1.0:
            raise ConfigError(f"data.point_keep_fraction={self.point_keep_fraction}: must be in (0, 1]")
        for name in ("augment_height_offset_prob", "augment_flip_prob"):
            value = getattr(self, name)
            if not (_is_number(value) and 0.0 <= value <= 1.0):
                raise ConfigError(f"data.{name}={value!r}: a probability, must be in [0, 1]")
        for name in ("augment_jitter_sigma_m", "augment_jitter_clip_m"):
            value = getattr(self, name)
            if not (_is_number(value) and value >= 0.0):
                raise ConfigError(f"data.{name}={value!r}: a distance in m, must be >= 0")
        lo_hi = self.augment_height_offset_m
        if not (len(lo_hi) == 2 and all(_is_number(v) for v in lo_hi) and lo_hi[0] <= lo_hi[1]):
            raise ConfigError(f"data.augment_height_offset_m={list(lo_hi)}: must be [lo, hi] in m with lo <= hi")


COMPILE_MODES = ("auto", "xla", "hybrid", "none")  # model.compile
HEADS = ("paper", "gru", "mlp")  # model.head (`ff3d_tf.model.heads.HEADS`)
FORWARDS = ("fused", "table")  # model.forward
TEMPORALS = ("pair", "stack", "delta")  # model.temporal (`ff3d_tf.model.fusions.FUSIONS`)


@dataclasses.dataclass(frozen=True)
class LossSpec:
    """What a training loss (`train.loss`) reads, the one statement of it: the `data.labels` it trains on, the
    per-point fields of pair records (`schema.POINT_KEYS`) it cannot run without (`needs`), and those it reads where
    the records hold them (`may_use`). A name with "{cloud}" stands for that field of every sweep of an example
    (`schema.sweep_clouds(data.num_frames)`). Config validation, the training input
    (`ff3d_tf.training.input.loss_extras`) and the training step (`ff3d_tf.model.losses.LOSS_FUNCTIONS`, one
    function per name) read this table."""

    labels: tuple[str, ...]
    needs: tuple[str, ...] = ()
    may_use: tuple[str, ...] = ()
    writer: str = ""  # the tool that writes the fields it needs

    def fields(self, which: str, num_frames: int) -> tuple[str, ...]:
        """`which` ("needs" or "may_use") with every "{cloud}" name expanded over the sweeps of `num_frames`."""
        out = []
        for name in getattr(self, which):
            out += [name.format(cloud=c) for c in schema.sweep_clouds(num_frames)] if "{cloud}" in name else [name]
        return tuple(out)


_SELF_FIELD = schema.DYNAMIC_CLUSTER_KEY_FORMAT  # per cloud: ground, static, dynamic, cluster (schema)
LOSS_SPECS = {  # train.loss -> its spec
    "l2": LossSpec(("human", "pseudo")),  # the paper's; ZeroFlow's on pseudo-labels
    "deflow": LossSpec(("human", "pseudo")),
    "deltaflow": LossSpec(("human",), may_use=("category_t0", "instance_id_t0")),
    # SeFlow (Zhang et al., ECCV 2024): the pair's two clouds; TeFlow (arXiv 2602.19053): every sweep of the example.
    "seflow": LossSpec(("self",), needs=tuple(_SELF_FIELD.format(cloud=c) for c in schema.sweep_clouds(2)),
                       writer="tools/prepare_self_supervision.py"),
    "teflow": LossSpec(("self",), needs=(_SELF_FIELD,), writer="tools/prepare_self_supervision.py"),
}
LOSSES = tuple(LOSS_SPECS)  # train.loss


def loss_labels_problem(loss: str, labels: str) -> str:
    """Why `train.loss` cannot train on `data.labels` (`LOSS_SPECS`), naming the losses that can; "" if it can."""
    if labels in LOSS_SPECS[loss].labels:
        return ""
    fitting = [name for name, spec in LOSS_SPECS.items() if labels in spec.labels]
    return (f"train.loss={loss} trains on data.labels {' or '.join(LOSS_SPECS[loss].labels)}, not {labels}: with "
            f"data.labels={labels} use train.loss={' or '.join(fitting)}")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """FastFlow3D widths (paper architecture table). The defaults give exactly 5,233,571 parameters."""

    point_feature_dim: int = 64  # row A
    encoder_widths: tuple[int, int, int] = (64, 128, 256)  # rows C-F, G-L, M-R
    encoder_depths: tuple[int, int, int] = (4, 6, 6)
    # Upsample-Skip (d, d_b) for rows S, T, U; row V keeps U's depth.
    decoder_dims: tuple[tuple[int, int], ...] = ((128, 128), (128, 64), (64, 64))
    head_hidden_dim: int = 32  # row Y
    # The per-point head: paper = rows W-Z (the paper's table); gru = DeFlow's GRU point decoder (Zhang et al., ICRA
    # 2024), `gru_iterations` refinement steps (0: an MLP on the point's encoding and its pillar's features); mlp =
    # DeltaFlow's point head (Linear-BN-ReLU-Linear on the cell embedding and the point feature, head_hidden_dim wide).
    head: str = "paper"
    gru_iterations: int = 4
    # Training recomputes the encoder stages' activations (rows C-R) in the backward pass from each stage's input
    # instead of holding them: less memory at the step's peak (docs/training.md, benchmarks/cpu_step_avx2_memory.json).
    remat_encoder: bool = False
    # fused = the forward in the cheaper forms the execution plan chooses for the job and device
    # (`ff3d_tf.model.plan`); table = every row as the paper's table lists it, one call per row (reading, debugging).
    # Both compute the same values up to float rounding.
    forward: str = "fused"
    # How the sweeps of an example (data.num_frames) meet in the U-Net (`ff3d_tf.model.fusions`): pair = the
    # paper's two clouds (num_frames 2); stack = every sweep through the shared encoder, the decoder's skips
    # concatenating all of them (the pair's concatenation extended, as DeFlow++ does); delta = DeltaFlow's decayed
    # differences of the sweeps' pillar means, from the newest sweep to the others ranked by recency, weighted by
    # temporal_decay^rank and divided by num_frames - 1, the only input of the U-Net (Zhang et al., arXiv 2508.17054).
    temporal: str = "pair"
    temporal_decay: float = 0.4
    # Zeros for row Z's kernel (the model starts at the zero-flow prediction) instead of the paper's Glorot init:
    # sum-pooled dense pillars through the linear decoder otherwise start at outputs of tens of m/s.
    zero_init_output: bool = False
    # How the forward and the training step are compiled (one of COMPILE_MODES): xla = the whole program in XLA;
    # hybrid = the point stages (pillarize, encode, scatter; ungrid head) in XLA, the convolutions as TensorFlow
    # graph kernels (oneDNN on CPU, faster there than XLA's); none = no XLA; auto = hybrid on CPU, xla on GPU/TPU.
    compile: str = "auto"
    # Precision of the convolutions (rows C-V; `ff3d_tf.model.compile.resolve_precision`): false = float32; true =
    # bfloat16 with float32 variables (Keras "mixed_bfloat16"); auto = bfloat16 on a CPU where oneDNN's bfloat16
    # convolutions beat float32 (amx_bf16, or AMD with avx512_bf16) in compile mode hybrid or none, float32 elsewhere
    # (GPU, TPU, xla, Intel avx512_bf16 without AMX: slower, benchmarks/bf16_cpu.json). Points, pillar indices and
    # sums, the head and the loss are float32 in every setting.
    mixed_precision: bool | str = False

    @property
    def jit_compile(self) -> bool:
        """Whether callers wrap the whole forward in one XLA program (`model.compile: xla`); the model applies every
        other mode itself (see `ff3d_tf.model.compile`), so False never turns its XLA stages off."""
        return self.compile == "xla"

    def validate(self) -> None:
        for name in ("encoder_widths", "encoder_depths", "decoder_dims"):
            if len(getattr(self, name)) != 3:
                raise ConfigError(f"model.{name}: must have 3 entries (three encoder stages and three Upsample-Skip "
                                  f"blocks, paper table), got {len(getattr(self, name))}")
        if any(d < 1 for d in self.encoder_depths):
            raise ConfigError("model.encoder_depths: each stage needs at least its stride-2 convolution (>= 1)")
        _in_range("model.point_feature_dim", self.point_feature_dim, 1, MAX_WIDTH)
        _in_range("model.head_hidden_dim", self.head_hidden_dim, 1, MAX_WIDTH)
        for name in ("encoder_widths", "decoder_dims"):
            for i, width in enumerate(np.ravel(getattr(self, name)).tolist()):
                _in_range(f"model.{name} (value {i})", width, 1, MAX_WIDTH)
        if self.decoder_dims[2][0] != self.point_feature_dim:
            raise ConfigError("model.decoder_dims[2][0] must equal point_feature_dim (row X concatenates them)")
        if self.compile not in COMPILE_MODES:
            raise ConfigError(f"model.compile={self.compile!r}: one of {', '.join(COMPILE_MODES)}")
        if self.head not in HEADS:
            raise ConfigError(f"model.head={self.head!r}: one of {', '.join(HEADS)}")
        if self.forward not in FORWARDS:
            raise ConfigError(f"model.forward={self.forward!r}: one of {', '.join(FORWARDS)}")
        if self.temporal not in TEMPORALS:
            raise ConfigError(f"model.temporal={self.temporal!r}: one of {', '.join(TEMPORALS)}")
        if not (_is_number(self.temporal_decay) and 0.0 < self.temporal_decay <= 1.0):
            raise ConfigError(f"model.temporal_decay={self.temporal_decay!r}: must be in (0, 1]")
        if not (isinstance(self.gru_iterations, int) and not isinstance(self.gru_iterations, bool)
                and 0 <= self.gru_iterations <= MAX_GRU_ITERATIONS):
            raise ConfigError(f"model.gru_iterations={self.gru_iterations!r}: an integer in [0, {MAX_GRU_ITERATIONS}]")
        if not (isinstance(self.mixed_precision, bool) or self.mixed_precision == "auto"):
            raise ConfigError(f"model.mixed_precision={self.mixed_precision!r}: must be one of true, false, auto")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Training loop (paper appendix: Adam, lr 1e-6, betas 0.9/0.999, batch 64, L2 loss, background weight 0.1)."""

    global_batch_size: int = 64
    learning_rate: float = 1e-6
    lr_schedule: str = "constant"  # constant | cosine (decay to lr_final_fraction * learning_rate at num_steps)
    lr_final_fraction: float = 0.05
    warmup_steps: int = 0
    beta_1: float = 0.9
    beta_2: float = 0.999
    num_steps: int = 100000
    background_weight: float = 0.1
    # l2: the paper's (mean per-point L2 error, background points weighted by background_weight); deflow: DeFlow's
    # speed-bucketed mean; deltaflow: that plus class- and instance-balanced terms (DeltaFlow, arXiv 2508.17054).
    loss: str = "l2"
    grad_clip_norm: float | None = None
    max_nonfinite_steps_in_row: int = 10
    checkpoint_every_steps: int = 500
    keep_checkpoints: int = 3
    log_every_steps: int = 10
    eval_every_steps: int = 1000
    eval_num_batches: int = 4
    seed: int = 0
    # Multi-worker: a lost worker (dead, stopped or not answering) ends every other worker within this many seconds,
    # with a message naming it (the collective timeout and the step watchdog of `ff3d_tf.training.trainer`). Keep it
    # above the longest stretch one worker spends without the others (the chief's periodic evaluation).
    peer_timeout_s: float = 120.0
    # Multi-worker: how long a worker waits at start for every other worker to join before it exits naming the
    # missing ones (workers of one job may start minutes apart).
    peer_join_timeout_s: float = 600.0

    def validate(self) -> None:
        if self.global_batch_size < 1:
            raise ConfigError("train.global_batch_size must be >= 1")
        if not self.learning_rate > 0:
            raise ConfigError("train.learning_rate must be > 0")
        if self.loss not in LOSSES:
            raise ConfigError(f"train.loss={self.loss!r}: one of {', '.join(LOSSES)}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ConfigError(f"train.lr_schedule={self.lr_schedule!r}: must be constant or cosine")
        if self.warmup_steps < 0 or not 0 <= self.lr_final_fraction <= 1:
            raise ConfigError("train.warmup_steps must be >= 0 and train.lr_final_fraction in [0, 1]")
        if self.num_steps < 0:
            raise ConfigError("train.num_steps must be >= 0")
        if not 0 <= self.background_weight:
            raise ConfigError("train.background_weight must be >= 0")
        if self.grad_clip_norm is not None and self.grad_clip_norm <= 0:
            raise ConfigError("train.grad_clip_norm must be > 0 or null")
        if self.max_nonfinite_steps_in_row < 1:
            raise ConfigError("train.max_nonfinite_steps_in_row must be >= 1")
        for name in ("beta_1", "beta_2"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ConfigError(f"train.{name}={getattr(self, name)}: must be in [0, 1)")
        for name in ("checkpoint_every_steps", "keep_checkpoints", "log_every_steps", "eval_num_batches"):
            _in_range(f"train.{name}", getattr(self, name), 1, None)
        _in_range("train.eval_every_steps", self.eval_every_steps, 0, None)  # 0: never
        _in_range("train.seed", self.seed, 0, 2 ** 32 - 1)
        for name in ("peer_timeout_s", "peer_join_timeout_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"train.{name}={getattr(self, name)}: must be > 0 (seconds)")


NSFP_GROUND_RULES = ("auto", "records", "height", "none")  # nsfp.ground
NSFP_BAD_FIT_ACTIONS = ("skip", "stop")  # nsfp.on_bad_fit
_INT32_MAX = 2 ** 31 - 1  # counts and seeds of the fit are int32 in its compiled program


@dataclasses.dataclass(frozen=True)
class NsfpConfig:
    """The NSFP pseudo-label job (`tools/pseudo_label.py`, `ff3d_tf.labels.pseudo_records`): the fit of each pair
    (the fields of `ff3d_tf.labels.nsfp.NsfpOptions`, which documents them; `nsfp.options_from_config`), then what
    the job does around the fit (`pseudo_records.JobOptions`; `pseudo_records.job_from_config`). One rule table
    (`nsfp_option_problem`) checks this section and both option classes.

    The defaults are the job's fit (`nsfp.MEASURED_FIT_OPTIONS`), chosen on the Argoverse 2 sample pair (its scores:
    benchmarks/nsfp_cpu.json): NSFP's two-sided Chamfer (reverse correspondences found every 5 steps), a learning rate
    of 0.002 (NSFP: 0.008), no weight decay (NSFP: 1e-4), early stopping at 1e-5 m^2 (NSFP: 1e-4; a dense pair's mean
    squared distances are small), fitted to every 4th point; the fitted region bounded whatever the sweep's range:
    the Argoverse 2 challenge's box in x and y (`metrics_av2.MAX_DISTANCE_M`) and ZeroFlow's z range. NSFP's
    published fit: learning_rate=0.008, weight_decay=1e-4, reverse_every=1, min_delta=1e-4, fit_every=1,
    crop_xy_half_extent_m=null, crop_z_range_m=null."""

    # --- the fit (NsfpOptions)
    hidden_layers: int = 8  # coordinate MLP: hidden layers of hidden_units, ReLU
    hidden_units: int = 128
    learning_rate: float = 2e-3  # Adam
    warmup_iterations: int = 0  # learning rate ramped linearly over the first this many steps
    weight_decay: float = 0.0  # L2 added to the gradients of both MLPs
    max_iterations: int = 5000
    patience: int = 100  # early stopping: steps without the loss improving by more than min_delta
    min_delta: float = 1e-5  # m^2 (m with squared_chamfer=false)
    backward_cycle: bool = True  # NSFP's backward-flow (cycle) term
    reverse_every: int = 5  # two-sided Chamfer, correspondences found every this many steps; 0: one-sided
    fit_every: int = 4  # fit on every k-th kept point, then evaluate the fitted MLP at every kept point
    exact_chamfer: bool = False  # exact nearest neighbours (slow; for checking) instead of the distance transform
    squared_chamfer: bool = True  # mean squared distances (NSFP's Chamfer), else mean distances
    truncate_m: float | None = None  # points this far or farther from the target count 0; null: no truncation
    grid_cell_m: float = 0.1  # finest cell of the distance transform (coarsened to fit max_grid_cells)
    grid_margin_m: float = 0.5  # grid bounds: the kept clouds' bounding box (or crop box) grown by this much
    band_cells: int = 4  # finest level exact wherever the nearest point is within this many cells
    coarse_band_cells: int = 3  # the same on the coarser levels
    max_grid_cells: int = 1 << 26  # largest grid (4 bytes a node, two grids a pair)
    remove_ground_below_z_m: float | None = None  # also drop points below this z (vehicle frame, both clouds)
    crop_xy_half_extent_m: float | None = 35.0  # fit points with |x|, |y| <= this (metrics_av2.MAX_DISTANCE_M); null:
    # no crop (the grid coarsens to fit the clouds)
    crop_z_range_m: tuple[float, float] | None = (-3.0, 3.0)  # fit points with z in [lo, hi]; null: no crop
    point_bucket_base: int = 1024  # point counts padded to buckets: one compiled fit per bucket
    segment_iterations: int = 100  # Adam steps per compiled call (progress is reported between calls)
    seed: int = 0  # the MLPs' initialisation; a retry of a bad fit uses the next seed
    # --- the job around the fit (JobOptions)
    ground: str = "auto"  # ground removed from both clouds by one rule: records (the records' masks of both
    # clouds, e.g. Argoverse 2's map), height (ff3d_tf.labels.ground), auto (records where they carry both masks,
    # else height), none
    max_speed_mps: float = 50.0  # a fitted point faster than this is implausible (no pseudo-label)
    max_implausible_fraction: float = 0.01  # a fit with a larger share of implausible fitted points is bad
    retries: int = 1  # fits of a bad pair with the next seeds before it is given up
    on_bad_fit: str = "skip"  # skip: the pair is written without pseudo-labels and named; stop: the job stops

    def validate(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            problem = nsfp_option_problem(field.name, value)
            if problem:
                raise ConfigError(f"nsfp.{field.name}={value!r}: {problem}")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _integer(lo: int):
    return lambda v: "" if isinstance(v, int) and not isinstance(v, bool) and lo <= v <= _INT32_MAX else \
        f"must be an integer in [{lo}, {_INT32_MAX}]"


def _number(lo: float, strict: bool):
    return lambda v: "" if _is_number(v) and (v > lo if strict else v >= lo) else \
        f"must be a finite number {'>' if strict else '>='} {lo:g}"


def _or_null(rule):
    return lambda v: "" if v is None else (rule(v) and f"{rule(v)} or null")


def _one_of(choices: tuple[str, ...]):
    return lambda v: "" if v in choices else f"must be one of {', '.join(choices)}"


def _flag(v) -> str:
    return "" if isinstance(v, bool) else "must be true or false"


def _range(v) -> str:
    ok = isinstance(v, (tuple, list)) and len(v) == 2 and all(_is_number(z) for z in v) and v[0] < v[1]
    return "" if ok else "must be [lo, hi] with lo < hi, or null"


_NSFP_RULES = {  # NsfpConfig field -> its check (message of what is allowed, "" if the value is)
    **{name: _integer(1) for name in ("hidden_layers", "hidden_units", "max_iterations", "patience", "fit_every",
                                      "band_cells", "coarse_band_cells", "max_grid_cells", "point_bucket_base",
                                      "segment_iterations")},
    **{name: _integer(0) for name in ("warmup_iterations", "reverse_every", "seed", "retries")},
    **{name: _number(0.0, strict=True) for name in ("learning_rate", "grid_cell_m", "max_speed_mps",
                                                     "max_implausible_fraction")},
    **{name: _number(0.0, strict=False) for name in ("weight_decay", "min_delta", "grid_margin_m")},
    **{name: _flag for name in ("backward_cycle", "exact_chamfer", "squared_chamfer")},
    "truncate_m": _or_null(_number(0.0, strict=True)),
    "crop_xy_half_extent_m": _or_null(_number(0.0, strict=True)),
    "remove_ground_below_z_m": _or_null(lambda v: "" if _is_number(v) else "must be a finite number"),
    "crop_z_range_m": lambda v: "" if v is None else _range(v),
    "ground": _one_of(NSFP_GROUND_RULES),
    "on_bad_fit": _one_of(NSFP_BAD_FIT_ACTIONS),
}


def nsfp_option_problem(name: str, value) -> str:
    """What is allowed for the `nsfp` option `name` (a field of NsfpConfig, NsfpOptions or JobOptions) when `value`
    is not, else "": the one statement of these rules, for the config section and the option classes alike."""
    if name not in _NSFP_RULES:
        raise KeyError(f"{name}: not an nsfp option; known: {sorted(_NSFP_RULES)}")
    return _NSFP_RULES[name](value)


SELFSUP_GROUND_RULES = ("auto", "records", "height")  # selfsup.ground


@dataclasses.dataclass(frozen=True)
class SelfSupConfig:
    """Self-supervision without flow labels (SeFlow, Zhang et al., ECCV 2024; TeFlow, arXiv 2602.19053): the
    preparation job's parameters (`tools/prepare_self_supervision.py`, `ff3d_tf.labels.self_supervision`: DUFOMap
    over each log, HDBSCAN clusters of each sweep's dynamic points) and the weights of the losses `train.loss=seflow`
    and `teflow`. The defaults are the authors' (KTH-RPL/OpenSceneFlow; docs/label_free.md cites file and line)."""

    # --- the losses: each term's weight (the authors' "add_seloss"), and the time between two sweeps
    chamfer_weight: float = 1.0
    dynamic_chamfer_weight: float = 1.0
    static_flow_weight: float = 1.0
    cluster_weight: float = 1.0
    sweep_period_s: float = 0.1  # the authors' DELTA_T: flow in m/s times this is a sweep's displacement
    # --- the preparation
    # The lidar's position in the vehicle frame (m): each sweep's rays start at pose @ this point. The authors cast
    # Argoverse 2's rays from the ego pose itself (0, 0, 0); a fleet sets its lidar's mounting position.
    sensor_origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dufomap_resolution_m: float = 0.15  # voxel size
    dufomap_hit_inflation_m: float = 0.2  # DUFOMap's d_s
    dufomap_unknown_inflation: int = 1  # DUFOMap's d_p (voxels)
    min_range_m: float = 2.0  # points nearer the vehicle origin than this (the ego vehicle) are not integrated
    max_range_m: float = 50.0  # ... nor those farther than this
    cluster_min_points: int = 20  # HDBSCAN's min_cluster_size
    cluster_epsilon_m: float = 0.7  # HDBSCAN's cluster_selection_epsilon
    # Ground flags of each sweep: records (the records' own masks, Argoverse 2's map), height
    # (`ff3d_tf.labels.ground.height_ground_mask`), auto (records where the records carry them, else height).
    ground: str = "auto"
    num_threads: int = 0  # DUFOMap's threads; 0: every core

    def validate(self) -> None:
        rules = {**{name: _number(0.0, strict=False) for name in ("chamfer_weight", "dynamic_chamfer_weight",
                                                                  "static_flow_weight", "cluster_weight")},
                 **{name: _number(0.0, strict=True) for name in ("sweep_period_s", "dufomap_resolution_m",
                                                                  "max_range_m", "cluster_epsilon_m")},
                 **{name: _number(0.0, strict=False) for name in ("dufomap_hit_inflation_m", "min_range_m")},
                 **{name: _integer(0) for name in ("dufomap_unknown_inflation", "num_threads")},
                 "cluster_min_points": _integer(2), "ground": _one_of(SELFSUP_GROUND_RULES),
                 "sensor_origin_m": lambda v: "" if len(v) == 3 and all(_is_number(x) for x in v) else
                 "must be [x, y, z] in m"}
        for name, rule in rules.items():
            problem = rule(getattr(self, name))
            if problem:
                raise ConfigError(f"selfsup.{name}={getattr(self, name)!r}: {problem}")
        if not self.min_range_m < self.max_range_m:
            raise ConfigError(f"selfsup.min_range_m={self.min_range_m} must be below selfsup.max_range_m="
                              f"{self.max_range_m}")


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    grid: GridConfig = GridConfig()
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    train: TrainConfig = TrainConfig()
    nsfp: NsfpConfig = NsfpConfig()
    selfsup: SelfSupConfig = SelfSupConfig()

    def validate(self) -> "ExperimentConfig":
        self.grid.validate()
        self.data.validate()
        self.model.validate()
        self.train.validate()
        self.nsfp.validate()
        self.selfsup.validate()
        if self.model.temporal == "pair" and self.data.num_frames != 2:
            raise ConfigError(f"data.num_frames={self.data.num_frames} with model.temporal=pair: the pair reads 2 "
                              "sweeps; model.temporal=stack or delta reads more")
        # data.labels=human with a loss that trains on other labels is the config of evaluating such a model (its
        # evaluation scores human labels); training refuses it (`ff3d_tf.training.input.loss_extras`).
        problem = loss_labels_problem(self.train.loss, self.data.labels)
        if problem and self.data.labels != "human":
            raise ConfigError(problem)
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def save(self, path: str) -> None:
        """Writes the resolved config (YAML) next to checkpoints and results (local or any tf.io.gfile path)."""
        import tensorflow as tf  # only here: loading and validating configs stays free of TensorFlow
        tf.io.gfile.makedirs(os.path.dirname(path) or ".")
        with tf.io.gfile.GFile(path, "w") as f:
            yaml.safe_dump(json.loads(json.dumps(self.to_dict())), f, sort_keys=False)


def _coerce(value: Any, annotation: Any, where: str, current: Any = None) -> Any:
    """Checks/coerces an override against the declared type of the field it replaces; errors name the key and the
    type that is allowed. A section (`current`, a dataclass) keeps every field the override does not name."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if dataclasses.is_dataclass(annotation):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping of {sorted(f.name for f in dataclasses.fields(annotation))}"
                              f", got {value!r}")
        return _apply(current if current is not None else annotation(), value, where)
    if origin in (typing.Union, types.UnionType):  # `X | None`
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], where + " (or null)") if len(inner) == 1 else value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if args and args[-1] is Ellipsis:
            item_types = [args[0]] * len(value)
        else:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected a list of {len(args)} values, got {len(value)}: {value!r}")
            item_types = list(args)
        return tuple(_coerce(v, t, f"{where}[{i}]") for i, (v, t) in enumerate(zip(value, item_types)))
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true/false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        number = value
        if isinstance(value, str):
            try:
                number = float(value)
            except ValueError:
                number = None
        if isinstance(number, bool) or not isinstance(number, (int, float)) or not math.isfinite(number):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return float(number)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _apply(obj: Any, overrides: dict[str, Any], where: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(obj)}
    hints = typing.get_type_hints(type(obj))
    changes = {}
    for key, value in overrides.items():
        if key not in fields:
            raise ConfigError(f"unknown config key {where + '.' if where else ''}{key}; known: {sorted(fields)}")
        changes[key] = _coerce(value, hints[key], f"{where + '.' if where else ''}{key}", getattr(obj, key))
    return dataclasses.replace(obj, **changes)


def _set_dotted(tree: dict[str, Any], dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = tree
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise ConfigError(f"--set {dotted}: {p} is not a section")
    node[parts[-1]] = value


# The smallest model of the paper's structure on a small grid: the tests' and the soak job's model (`load_config(None,
# TINY_OVERRIDES)`), quick to build, train and export on one CPU core.
TINY_OVERRIDES = ("grid.num_pillars_x=32", "grid.num_pillars_y=32", "grid.x_range_m=[-40, 40]",
                  "grid.y_range_m=[-40, 40]", "model.point_feature_dim=16", "model.encoder_widths=[16, 24, 32]",
                  "model.encoder_depths=[2, 2, 2]", "model.decoder_dims=[[24, 24], [24, 16], [16, 16]]",
                  "model.head_hidden_dim=8", "data.point_bucket_base=1024", "train.global_batch_size=2",
                  "train.learning_rate=1e-3", "data.shuffle_buffer=4")


def load_config(path: str | None = None, overrides: list[str] | tuple[str, ...] = ()) -> ExperimentConfig:
    """Defaults <- YAML file (overrides only) <- `key=value` overrides; validated before it is returned."""
    tree: dict[str, Any] = {}
    if path:
        try:
            with open(path) as f:
                loaded = yaml.safe_load(f) or {}
        except OSError as e:
            raise ConfigError(f"cannot read config {path}: {e}") from e
        except yaml.YAMLError as e:
            raise ConfigError(f"config {path} is not valid YAML: {e}") from e
        if not isinstance(loaded, dict):
            raise ConfigError(f"config {path}: top level must be a mapping of sections")
        tree = loaded
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key=value, e.g. train.learning_rate=1e-4")
        key, raw = item.split("=", 1)
        _set_dotted(tree, key.strip(), yaml.safe_load(raw))
    try:
        cfg = _apply(ExperimentConfig(), tree, "")
    except ConfigError as e:
        raise ConfigError(f"{path or '<defaults>'}: {e}") from None
    return cfg.validate()


def partner_matters(cfg: ExperimentConfig) -> bool:
    """Whether a model of `cfg` computes otherwise when its partner sweep lies on the other side of t0
    (`data.partner`): delta's difference is taken from the newest sweep, and the older slots of more than 2 sweeps
    hold other sweeps; the pair (2 sweeps, pair or stack) reads its two clouds the same either way (its flow is the
    motion from the partner cloud to the t0 cloud over their gap)."""
    return cfg.model.temporal == "delta" or cfg.data.num_frames > 2


def replace_config(cfg: ExperimentConfig, changes: dict[str, Any]) -> ExperimentConfig:
    """`cfg` with dotted-key changes (e.g. {"data.point_keep_fraction": 0.5}), type-checked and validated."""
    tree: dict[str, Any] = {}
    for key, value in changes.items():
        _set_dotted(tree, key, value)
    return _apply(cfg, tree, "").validate()
