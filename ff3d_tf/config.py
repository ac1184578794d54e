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
TRAINING_LABELS = ("human", "pseudo")  # data.labels


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
    max_frame_gap_s: float = 0.15  # pairs further apart are skipped (WOD frames are ~0.1 s apart)
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

    def validate(self) -> None:
        if self.source not in DATA_SOURCES:
            raise ConfigError(f"data.source={self.source!r} unknown; one of {DATA_SOURCES}")
        if self.labels not in TRAINING_LABELS:
            raise ConfigError(f"data.labels={self.labels!r} unknown; one of {TRAINING_LABELS}")
        if self.labels == "pseudo" and self.source != "pair_records":
            raise ConfigError("data.labels=pseudo: pseudo-labels live in pair records (data.source=pair_records, "
                              "written by tools/pseudo_label.py)")
        if self.source == "pair_records" and not self.ego_motion_compensation:
            raise ConfigError("data.ego_motion_compensation=false: pair records hold the t-1 cloud already moved "
                              "into the t0 frame; use data.source=wod for the ego-motion study")
        problem = schema.lidar_selection_problem(self.laser_names, self.returns)
        if problem is not None:
            raise ConfigError(f"data.{problem}")
        if self.max_frame_gap_s <= 0:
            raise ConfigError(f"data.max_frame_gap_s={self.max_frame_gap_s}: must be > 0")
        _in_range("data.point_bucket_base", self.point_bucket_base, 1, MAX_BUCKET_BASE)
        _in_range("data.shuffle_buffer", self.shuffle_buffer, 1, None)
        _in_range("data.max_training_segments", self.max_training_segments, 0, None)
        if self.class_ablation not in CLASS_ABLATIONS:
            raise ConfigError(f"data.class_ablation={self.class_ablation!r} unknown; one of {CLASS_ABLATIONS}")
        if not 0.0 < self.point_keep_fraction <= 1.0:
            raise ConfigError(f"data.point_keep_fraction={self.point_keep_fraction}: must be in (0, 1]")


COMPILE_MODES = ("auto", "xla", "hybrid", "none")  # model.compile


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """FastFlow3D widths (paper architecture table). The defaults give exactly 5,233,571 parameters."""

    point_feature_dim: int = 64  # row A
    encoder_widths: tuple[int, int, int] = (64, 128, 256)  # rows C-F, G-L, M-R
    encoder_depths: tuple[int, int, int] = (4, 6, 6)
    # Upsample-Skip (d, d_b) for rows S, T, U; row V keeps U's depth.
    decoder_dims: tuple[tuple[int, int], ...] = ((128, 128), (128, 64), (64, 64))
    head_hidden_dim: int = 32  # row Y
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
        if self.lr_schedule not in ("constant", "cosine"):
            raise ConfigError(f"train.lr_schedule={self.lr_schedule!r}: constant or cosine")
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


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    grid: GridConfig = GridConfig()
    data: DataConfig = DataConfig()
    model: ModelConfig = ModelConfig()
    train: TrainConfig = TrainConfig()

    def validate(self) -> "ExperimentConfig":
        self.grid.validate()
        self.data.validate()
        self.model.validate()
        self.train.validate()
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


def replace_config(cfg: ExperimentConfig, changes: dict[str, Any]) -> ExperimentConfig:
    """`cfg` with dotted-key changes (e.g. {"data.point_keep_fraction": 0.5}), type-checked and validated."""
    tree: dict[str, Any] = {}
    for key, value in changes.items():
        _set_dotted(tree, key, value)
    return _apply(cfg, tree, "").validate()
