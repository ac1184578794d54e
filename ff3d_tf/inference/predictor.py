"""One way to run a trained model, whatever it was saved as.

`load_predictor(cfg, path)` is the one place where what a path holds chooses the runtime (`predictor_kind`); every
kind follows the contract of `ff3d_tf.predictor.Predictor`: `predict(batch, example) -> (flow_mps [N0,3],
point_valid [N0])` for one padded pair of `ff3d_tf.data.pairs.padded_singletons`, as NumPy arrays trimmed to the
pair's real t0 points.

  onnx         an .onnx file (tools/export_onnx.py): `onnx_export.OnnxFlowPredictor`, onnxruntime on the CPU
  saved_model  a directory with saved_model.pb (tools/export.py): `saved_model.SavedModelPredictor`
  xla          a directory with a portable export's manifest.json (tools/export_xla.py, batch 1):
               `xla_artifact.XlaPredictor`, JAX
  checkpoint   anything else, a model_dir or a checkpoint prefix: `ff3d_tf.model.forward.ModelPredictor` of the model
               restored with the config given

The order of the sweeps a model reads travels with it (`SweepOrder`, `sweep_order`): how many (`data.num_frames`),
which sweep its t-1 slot holds (`data.partner`: "previous", or "next" for a model of Argoverse 2 challenge records)
and how they meet (`model.temporal`). A checkpoint's is its config's; an export records its own (the SavedModel in its
module and its config.yaml, the ONNX file in its metadata, the XLA export in its manifest.json). `check_order` is the
check wherever examples of a known order are fed to a model.

`model_fingerprint(path)` names the model at a path by the hash of the files that hold it: what a resumable output
made by a model records (`tools/av2_submission.py`).
"""
from __future__ import annotations

import dataclasses
import hashlib
import os

import tensorflow as tf

from ff3d_tf import schema, xla_export_dir
from ff3d_tf.checkpoints import load_saved_config, resolve_checkpoint, restore_model, saved_config
from ff3d_tf.config import ConfigError, ExperimentConfig, load_config, partner_matters
from ff3d_tf.model.forward import ModelPredictor
from ff3d_tf.predictor import Predictor

KINDS = ("onnx", "saved_model", "xla", "checkpoint")


@dataclasses.dataclass(frozen=True)
class SweepOrder:
    """The examples a model reads: `num_frames` sweeps, its t-1 slot holding the `partner` sweep of t0
    (`schema.PARTNERS`), the sweeps meeting as `temporal` says (`config.TEMPORALS`)."""
    num_frames: int = 2
    partner: str = schema.DEFAULT_PARTNER
    temporal: str = "pair"

    def __post_init__(self):
        if self.partner not in schema.PARTNERS:
            raise ConfigError(f"partner {self.partner!r}: one of {', '.join(schema.PARTNERS)}")

    @property
    def partner_matters(self) -> bool:
        """Whether the model computes otherwise when its partner lies on the other side of t0
        (`config.partner_matters`)."""
        return partner_matters(load_config(None, [f"data.num_frames={self.num_frames}",
                                                  f"model.temporal={self.temporal}"]))

    def describe(self) -> str:
        if not self.partner_matters:
            return f"{self.num_frames} sweeps ({self.temporal})"
        slots = "t0, t+1, t-1, ..." if self.partner == "next" else "t0, t-1, t-2, ..."
        return f"{self.num_frames} sweeps ({self.temporal}), partner {self.partner}: slots {slots}"


def order_of_config(cfg: ExperimentConfig) -> SweepOrder:
    """The order of a model built from `cfg` (a config without `data.partner`: the default)."""
    return SweepOrder(cfg.data.num_frames, cfg.data.partner or schema.DEFAULT_PARTNER, cfg.model.temporal)


def order_of_saved_config(path: str, num_frames: int, recorded: dict) -> SweepOrder:
    """An export's order: what it recorded itself (`recorded`: "partner", "temporal"), else the config saved with it
    (config.yaml in its folder, written by the export tools), else the pair's defaults."""
    saved = saved_config(path)
    cfg = load_saved_config(saved) if saved else None
    partner = recorded.get("partner") or (cfg.data.partner if cfg is not None else None) or schema.DEFAULT_PARTNER
    temporal = recorded.get("temporal") or (cfg.model.temporal if cfg is not None else None) or \
        ("pair" if num_frames == 2 else "stack")
    return SweepOrder(num_frames, partner, temporal)


def sweep_order(predictor) -> SweepOrder:
    """The order of the examples `predictor` reads: an export's (`recorded_order` and the config saved with it at its
    `path`: `order_of_saved_config`), that of the Keras model it runs, or the pair's (a predictor of any pair, e.g.
    NSFP's fit)."""
    if hasattr(predictor, "recorded_order"):
        return order_of_saved_config(predictor.path, predictor.num_frames, predictor.recorded_order)
    model = getattr(predictor, "model", None)
    if model is not None and hasattr(model, "num_frames"):
        return SweepOrder(model.num_frames, getattr(model, "partner", schema.DEFAULT_PARTNER), model.temporal)
    return SweepOrder()


PARTNER_WORDS = {"previous": "the previous sweep (WOD, your own sequences)",
                 "next": "the next sweep (Argoverse 2 challenge records)"}


def check_order(order: SweepOrder, data_partner: str, where: str) -> None:
    """ConfigError naming `where` unless examples whose t-1 slot holds the `data_partner` sweep are what a model of
    `order` reads: checked where it matters (`SweepOrder.partner_matters`)."""
    if order.partner_matters and data_partner != order.partner:
        raise ConfigError(f"{where}: the model was trained with {PARTNER_WORDS[order.partner]} in its t-1 slot "
                          f"(data.partner={order.partner}, {order.describe()}); these examples hold "
                          f"{PARTNER_WORDS[data_partner]}: give it data of its own order")


def is_saved_model(path: str) -> bool:
    return tf.io.gfile.exists(os.path.join(path, "saved_model.pb"))


def predictor_kind(path: str) -> str:
    """Which of `KINDS` `path` holds (see the module docstring)."""
    if path.endswith(".onnx"):
        return "onnx"
    if is_saved_model(path):
        return "saved_model"
    if os.path.isfile(os.path.join(path, xla_export_dir.MANIFEST_NAME)):
        return "xla"
    return "checkpoint"


def load_predictor(cfg: ExperimentConfig, path: str) -> Predictor:
    """The model at `path` (an ONNX file, a SavedModel or portable XLA export directory, a model_dir or a checkpoint
    prefix) as a `Predictor`; `cfg` builds the model of a checkpoint (the exports carry their own). The examples the
    caller will make are `cfg.data.num_frames` sweeps of the `cfg.data.partner` order (None: any): a model of
    another order is a ConfigError (a checkpoint's own config: `checkpoints.restore_model`'s CheckpointError)."""
    kind = predictor_kind(path)
    if kind == "onnx":
        from ff3d_tf.inference.onnx_export import OnnxFlowPredictor
        predictor = OnnxFlowPredictor(path)
    elif kind == "saved_model":
        from ff3d_tf.inference.saved_model import SavedModelPredictor
        predictor = SavedModelPredictor(path)
    elif kind == "xla":
        from ff3d_tf.inference.xla_artifact import XlaPredictor
        predictor = XlaPredictor(path)
    else:
        predictor = ModelPredictor(restore_model(cfg, path), cfg.model.jit_compile)
    order = sweep_order(predictor)
    if order.num_frames != cfg.data.num_frames:
        raise ConfigError(f"{path}: the model reads {order.num_frames} sweeps per example; the config has "
                          f"data.num_frames={cfg.data.num_frames}: set data.num_frames={order.num_frames} (and "
                          "the model.temporal it was trained with)")
    check_order(order, cfg.data.partner or order.partner, path)
    return predictor


def model_files(path: str) -> list[str]:
    """The files that hold the model at `path` (its weights and program): an ONNX file; a SavedModel's graph and
    variable index; an XLA export's manifest and weights; a checkpoint's index (which holds every tensor's CRC32C)."""
    kind = predictor_kind(path)
    if kind == "onnx":
        return [path]
    if kind == "saved_model":
        return [os.path.join(path, "saved_model.pb"), os.path.join(path, "variables", "variables.index")]
    if kind == "xla":
        return [os.path.join(path, xla_export_dir.MANIFEST_NAME), os.path.join(path, xla_export_dir.WEIGHTS_NAME)]
    return [resolve_checkpoint(path) + ".index"]


def model_fingerprint(path: str) -> dict:
    """{"kind", "sha256"}: the model at `path` by the SHA-256 of `model_files` (the same weights and program under
    another path have the same hash)."""
    digest = hashlib.sha256()
    for name in model_files(path):
        with tf.io.gfile.GFile(name, "rb") as f:
            while True:
                block = f.read(1 << 22)
                if not block:
                    break
                digest.update(block)
    return {"kind": predictor_kind(path), "sha256": digest.hexdigest()}
