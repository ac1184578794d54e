"""Checkpoints that can be trusted: verified against the live objects before a restore, damaged ones moved aside.

A checkpoint is the prefix `DIR/ckpt-N` of `tf.train.CheckpointManager`: `ckpt-N.index` plus
`ckpt-N.data-0000k-of-0000K`.
`verify_checkpoint(root, prefix)` proves, before anything is restored, that

1. the index exists and parses, and every data shard it needs exists;
2. every variable reachable from `root` (a `tf.train.Checkpoint` of the model, optimizer, step...) is in the
   checkpoint's object graph, matched as a restore matches it (`tf.train.CheckpointView.match`), with the same shape
   and dtype (else the error names the first variable that differs);
3. each of those variables' bytes can be read back (a truncated data file or a flipped bit fails its checksum here).

`restore_newest_intact` is the resume policy of training: the newest intact checkpoint wins; newer damaged ones are
moved to `DIR/damaged/` (never deleted) with a REASON.txt; if checkpoints exist but none is intact it stops with
`CheckpointError` and moves nothing, so a rerun can never restart a long run from step 0 over its checkpoints.

A checkpoint knows its config: training writes the resolved config as `model_dir/config.yaml` (`CONFIG_NAME`) beside
`model_dir/checkpoints/`, and `saved_config` finds it from a model_dir, its checkpoints folder, a checkpoint prefix or
a SavedModel directory that holds one. The tools load it when given no `--config` (`tools/_common.load`); a mismatch
error names it.
"""
from __future__ import annotations

import collections
import os
import re
import tempfile

import keras
import tensorflow as tf

from ff3d_tf import internals, schema
from ff3d_tf.config import ConfigError, ExperimentConfig, load_config, replace_config
from ff3d_tf.model import build_model
from ff3d_tf.model.fastflow3d import model_definition

DAMAGED_DIR = "damaged"
CHECKPOINTS_DIR = "checkpoints"  # model_dir/checkpoints/ckpt-N
CONFIG_NAME = "config.yaml"  # the resolved config saved with a model (model_dir/config.yaml)
_OBJECT_GRAPH_KEY = "_CHECKPOINTABLE_OBJECT_GRAPH"
_FILE_RE = re.compile(r"^(?P<prefix>.+-(?P<number>\d+))\.(?:index|data-\d{5}-of-(?P<shards>\d{5}))$")


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be restored into the given objects; the message names it and says why."""

    def __init__(self, prefix: str, reason: str, mismatch: bool = False):
        super().__init__(f"checkpoint {prefix} is unusable: {reason}")
        # mismatch: intact but of another model or config (a variable missing, or of another shape or dtype)
        self.prefix, self.reason, self.mismatch = prefix, reason, mismatch


def list_checkpoints(checkpoint_dir: str) -> list[str]:
    """Checkpoint prefixes in `checkpoint_dir` (any file of one counts, so half-written ones too), newest first.

    Found from the files themselves, not from the `checkpoint` state file (which a killed save may leave behind the
    files, or ahead of them).
    """
    if not tf.io.gfile.isdir(checkpoint_dir):
        return []
    numbers = {}
    for name in tf.io.gfile.listdir(checkpoint_dir):
        match = _FILE_RE.match(name.rstrip("/"))
        if match:
            numbers[match["prefix"]] = int(match["number"])
    return [os.path.join(checkpoint_dir, p) for p in sorted(numbers, key=lambda p: (numbers[p], p), reverse=True)]


def _live_variables(root) -> list[tuple[str, object]]:
    """(path, variable) of every variable reachable from `root`, breadth first over `tf.train.TrackableView` children
    (the path is the first found: for a shared variable, e.g. an optimizer's `_variables` and `_momentums`, the one a
    checkpoint saves it under)."""
    view = tf.train.TrackableView(root)
    seen, found = {id(root)}, []
    queue = collections.deque([("", root)])
    while queue:
        path, obj = queue.popleft()
        for name, child in view.children(obj).items():
            if id(child) in seen:
                continue
            seen.add(id(child))
            child_path = f"{path}/{name}" if path else name
            if isinstance(child, (tf.Variable, keras.Variable)):
                found.append((child_path, child))
            else:
                queue.append((child_path, child))
    return found


def _saved_keys(reader, prefix: str) -> dict[int, str]:
    """The tensor key of each variable node of the checkpoint's object graph (`internals.checkpoint_variable_keys`)."""
    if not reader.has_tensor(_OBJECT_GRAPH_KEY):
        raise CheckpointError(prefix, "it holds no object graph (not written by tf.train.Checkpoint)")
    try:
        data = reader.get_tensor(_OBJECT_GRAPH_KEY)
    except Exception as e:  # truncated shard or checksum mismatch, whatever TF calls it
        raise CheckpointError(prefix, f"its object graph cannot be read ({type(e).__name__}: data file truncated "
                                      f"or corrupt)") from e
    try:
        return internals.checkpoint_variable_keys(data)
    except Exception as e:  # a decode error of any kind: the bytes are not an object graph
        raise CheckpointError(prefix, f"its object graph does not parse ({type(e).__name__})") from e


def _check_files(prefix: str) -> None:
    gfile = tf.io.gfile
    if not gfile.exists(prefix + ".index"):
        raise CheckpointError(prefix, f"its index file {os.path.basename(prefix)}.index is missing")
    shards = [f for f in gfile.glob(prefix + ".data-*-of-*") if _FILE_RE.match(os.path.basename(f))]
    if not shards:
        raise CheckpointError(prefix, f"its data file {os.path.basename(prefix)}.data-00000-of-* is missing")
    total = int(_FILE_RE.match(os.path.basename(shards[0]))["shards"])
    for k in range(total):
        name = f"{prefix}.data-{k:05d}-of-{total:05d}"
        if not gfile.exists(name):
            raise CheckpointError(prefix, f"its data file {os.path.basename(name)} is missing")


def verify_checkpoint(root, prefix: str) -> int:
    """Raises `CheckpointError` unless every variable of `root` can be restored from `prefix`; returns their count.

    Reads each expected variable's bytes once (the whole model and optimizer for training: about one extra read of
    the checkpoint at start-up).
    """
    _check_files(prefix)
    try:
        reader = internals.checkpoint_reader(prefix)  # not tf.train.load_checkpoint: see internals
    except Exception as e:  # TF raises several types for an unreadable index; the reason is ours to state
        raise CheckpointError(prefix, f"its index {os.path.basename(prefix)}.index cannot be read "
                                      f"({type(e).__name__}: damaged or not a checkpoint index)") from e
    keys = _saved_keys(reader, prefix)
    # The saved node of each live object, as a restore pairs them (node id -> object).
    node_of = {id(obj): node for node, obj in tf.train.CheckpointView(prefix).match(root).items()}
    saved_shapes, saved_dtypes = reader.get_variable_to_shape_map(), reader.get_variable_to_dtype_map()
    variables = _live_variables(root)
    for path, variable in variables:
        key = keys.get(node_of.get(id(variable)))
        if key is None or key not in saved_shapes:
            raise CheckpointError(prefix, f"variable {path} is not in it (a checkpoint of another model or config?)",
                                  mismatch=True)
        want_shape, got_shape = tuple(variable.shape), tuple(saved_shapes[key])
        want_dtype, got_dtype = tf.as_dtype(variable.dtype), tf.as_dtype(saved_dtypes[key])
        if want_shape != got_shape or want_dtype != got_dtype:
            raise CheckpointError(prefix, f"variable {path} is {got_dtype.name}{list(got_shape)} in the checkpoint "
                                          f"but {want_dtype.name}{list(want_shape)} in this model (a checkpoint of "
                                          f"another config?)", mismatch=True)
        try:
            reader.get_tensor(key)
        except Exception as e:  # truncated shard or checksum mismatch, whatever TF calls it
            raise CheckpointError(prefix, f"the data of variable {path} cannot be read ({type(e).__name__}: data "
                                          f"file truncated or corrupt)") from e
    return len(variables)


def move_aside(prefix: str, reason: str) -> str:
    """Moves the files of `prefix` into `DIR/damaged/<name>[_k]/` with a REASON.txt; returns that folder."""
    gfile = tf.io.gfile
    base = os.path.join(os.path.dirname(prefix), DAMAGED_DIR, os.path.basename(prefix))
    target, k = base, 1
    while gfile.exists(target):
        k += 1
        target = f"{base}_{k}"
    gfile.makedirs(target)
    with gfile.GFile(os.path.join(target, "REASON.txt"), "w") as f:
        f.write(reason + "\n")
    for name in gfile.glob(prefix + ".*"):
        match = _FILE_RE.match(os.path.basename(name))
        if match and match["prefix"] == os.path.basename(prefix):  # its index and data files only
            gfile.rename(name, os.path.join(target, os.path.basename(name)))
    return target


def newest_intact(root, checkpoint_dir: str, log_fn=print, move_damaged: bool = True) -> str | None:
    """The newest checkpoint of `checkpoint_dir` that verifies against `root`; None when there is none at all.

    Damaged checkpoints newer than it are moved aside (logged), unless `move_damaged` is False (multi-worker
    training: only the chief moves files, the other workers only skip them). When checkpoints exist and none
    verifies, raises `CheckpointError` naming each with its reason and moves nothing.
    """
    candidates = list_checkpoints(checkpoint_dir)
    damaged = []
    for prefix in candidates:
        try:
            verify_checkpoint(root, prefix)
        except CheckpointError as e:
            damaged.append(e)
            continue
        for e in damaged:
            where = f"moved to {move_aside(e.prefix, e.reason)}" if move_damaged else "left for the chief to move"
            log_fn(f"{e}; {where}, resuming from the older {prefix}")
        return prefix
    if damaged:
        listing = "; ".join(f"{os.path.basename(e.prefix)}: {e.reason}" for e in damaged)
        own = _own_config(checkpoint_dir) if any(e.mismatch for e in damaged) else ""
        raise CheckpointError(checkpoint_dir, f"none of its {len(damaged)} checkpoints is intact and fits this "
                                              f"model ({listing}{own}). "
                                              f"Nothing was moved or overwritten. To start from step 0 anyway, move "
                                              f"them out of {checkpoint_dir} or pass a new model_dir")
    return None


def restore_newest_intact(checkpoint: tf.train.Checkpoint, checkpoint_dir: str, log_fn=print,
                          move_damaged: bool = True) -> str | None:
    """Restores `checkpoint` from `newest_intact`; returns the prefix used, or None (nothing to resume)."""
    prefix = newest_intact(checkpoint, checkpoint_dir, log_fn, move_damaged)
    if prefix is not None:
        checkpoint.restore(prefix).assert_existing_objects_matched()
    return prefix


def saved_config(path: str) -> str | None:
    """The config saved with a checkpoint: `CONFIG_NAME` in the folder `path` (a model_dir, a SavedModel directory) or
    in the folder of the checkpoint prefix `path`, or, when that folder is a model_dir's `CHECKPOINTS_DIR`, in the
    model_dir; None when there is none (or `path` does not exist)."""
    gfile = tf.io.gfile
    if gfile.exists(path + ".index"):  # a prefix (checked first: ram:// calls any prefix of a file a directory)
        folder = os.path.dirname(path)
    elif gfile.isdir(path):
        folder = path.rstrip("/")
    else:
        return None
    folders = [folder] + ([os.path.dirname(folder)] if os.path.basename(folder) == CHECKPOINTS_DIR else [])
    for candidate in (os.path.join(f, CONFIG_NAME) for f in folders):
        if gfile.exists(candidate) and not gfile.isdir(candidate):
            return candidate
    return None


def load_saved_config(path: str, overrides=()) -> ExperimentConfig:
    """The config file at `path` (local, gs:// or any `tf.io.gfile` filesystem) with `key=value` `overrides`,
    validated."""
    if "://" not in path:
        return load_config(path, overrides)
    with tempfile.TemporaryDirectory() as folder:
        local = os.path.join(folder, os.path.basename(path))
        try:
            tf.io.gfile.copy(path, local)
        except (tf.errors.OpError, OSError) as e:
            raise ConfigError(f"cannot read config {path}: {e}") from e
        try:
            return load_config(local, overrides)
        except ConfigError as e:
            raise ConfigError(str(e).replace(local, path)) from None


def with_model_partner(cfg: ExperimentConfig, model) -> ExperimentConfig:
    """`cfg` with `data.partner` the model's own (resolved from its checkpoint's config when `cfg` left it unset): the
    config an export saves with it."""
    partner = getattr(model, "partner", schema.DEFAULT_PARTNER)
    return cfg if cfg.data.partner == partner else replace_config(cfg, {"data.partner": partner})


def with_model_definition(cfg: ExperimentConfig, path: str) -> ExperimentConfig:
    """`cfg` checked against the config saved with the model at `path` (`saved_config`; nothing to check without
    one): `CheckpointError` naming that file and each key of `model_definition` whose value differs (such a model
    restores into the other config's variables, and computes something else). A `data.partner` that `cfg` leaves
    unset is the saved one's."""
    saved_path = saved_config(path)
    if saved_path is None:
        return cfg
    saved = load_saved_config(saved_path)
    if cfg.data.partner is None and saved.data.partner is not None:
        cfg = replace_config(cfg, {"data.partner": saved.data.partner})
    ours, theirs = model_definition(cfg), model_definition(saved)
    differ = [f"{k}={theirs.get(k)} there, {ours.get(k)} here" for k in sorted(set(ours) | set(theirs))
              if ours.get(k) != theirs.get(k)]
    if differ:
        raise CheckpointError(saved_path, "the model saved here is of another definition: " + "; ".join(differ) +
                              " (the tools load this config when given no --config; check --config and --set, or "
                              "use another model_dir)", mismatch=True)
    return cfg


def _own_config(path: str) -> str:
    """"; its own config is X (...)" for the error of a checkpoint that does not fit the model; "" without one."""
    saved = saved_config(path)
    return (f"; its own config is {saved} (the tools load it when given no --config; check --config and --set)"
            if saved else "")


def resolve_checkpoint(path: str) -> str:
    """A checkpoint prefix from a checkpoint prefix or a model_dir (its newest checkpoint, found from the files)."""
    if tf.io.gfile.exists(path + ".index"):
        return path  # a prefix (checked first: ram:// calls any prefix of a file a directory)
    if tf.io.gfile.isdir(path):
        found = list_checkpoints(os.path.join(path, CHECKPOINTS_DIR)) or list_checkpoints(path)
        if not found:
            raise FileNotFoundError(f"no checkpoint under {path} (expected {path}/checkpoints/ckpt-N.index)")
        return found[0]
    return path


def restore_model(cfg: ExperimentConfig, checkpoint_path: str):
    """The model of `cfg` with the weights of a checkpoint prefix or a model_dir's newest checkpoint.

    The checkpoint is verified first (`ff3d_tf.checkpoints.verify_checkpoint`): a damaged one, or one of
    another config, raises `CheckpointError` naming it, the reason, the config saved with it when it is of another
    config (`saved_config`) and, for a model_dir, the newest intact one.
    Nothing is moved: choosing another checkpoint is the caller's decision.
    """
    model = build_model(with_model_definition(cfg, checkpoint_path))
    root = tf.train.Checkpoint(model=model)
    prefix = resolve_checkpoint(checkpoint_path)
    try:
        verify_checkpoint(root, prefix)
    except CheckpointError as e:
        reason = e.reason + (_own_config(checkpoint_path) if e.mismatch else "")
        if prefix != checkpoint_path:  # a model_dir was given: say which of its checkpoints would work
            try:
                intact = newest_intact(root, os.path.dirname(prefix), log_fn=lambda _: None, move_damaged=False)
            except CheckpointError:
                intact = None
            if intact is not None:
                raise CheckpointError(prefix, f"{reason}; the newest intact checkpoint is {intact} (pass it as "
                                              f"the checkpoint, or rerun training to resume from it)") from e
        if reason != e.reason:
            raise CheckpointError(prefix, reason, mismatch=True) from e
        raise
    root.restore(prefix).expect_partial()
    return model
