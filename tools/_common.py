"""Shared flag handling of the tools: --config (else the config saved with the model a tool is given) plus repeatable
--set key=value, logging, error exit."""
from __future__ import annotations

import argparse
import logging
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from ff3d_tf import cpu as _cpu  # noqa: E402  (the standard library only: TensorFlow is not imported yet)

JOBS = _cpu.STARTUP_JOBS  # "train": FastFlow3D trains in this process; "inference": it runs forward, or no model


class StartupError(RuntimeError):
    """`start` came after TensorFlow was imported: the start-up's settings would not take effect."""


def start(job: str) -> dict:
    """A tool's start-up, the first call of its `main()`, before anything imports TensorFlow: the environment of
    `ff3d_tf.cpu.startup_environment` for `job` (one of `JOBS`) on this machine's CPU (docs/deployment.md, "Serving on
    a CPU"; the user's own settings are kept), glibc's arena limit, and TensorFlow's C++ log level (warnings and
    errors). Returns what it added to os.environ. A tool imports the ff3d_tf modules that import
    TensorFlow inside `main()`, after this call (`tests/tools/test_startup.py` checks every tool)."""
    if job not in JOBS:
        raise ValueError(f"start-up job {job!r}: one of {', '.join(JOBS)}")
    if sys.modules.get("tensorflow") is not None:  # (None: a process that blocks TensorFlow's import)
        raise StartupError(f"start({job!r}) after TensorFlow was imported: its settings would not take effect; a tool "
                           f"imports ff3d_tf's TensorFlow modules inside main(), after the start-up")
    added = _cpu.startup_environment(job)
    os.environ.update(added)
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    _cpu.limit_malloc_arenas()  # glibc read MALLOC_ARENA_MAX at start, before the line above could set it
    return added


# The flags by which a tool names a model_dir, a checkpoint prefix or a SavedModel directory: a tool given one of them
# and no --config loads the config saved with it (`load`).
CHECKPOINT_FLAGS = ("checkpoint", "model_dir")


class _ConfigFlag(argparse.Action):
    """--config, remembering that the command line gave it (`config_given`): a default does not count."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.config_given = True


def parser(description: str, config_default: str | None = None) -> argparse.ArgumentParser:
    """--config and --set. `config_default` is the config of a tool run without --config, unless the tool is given a
    model (see `load`)."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--config", default=config_default, action=_ConfigFlag,
                   help="YAML file of overrides (configs/*.yaml); default: the config saved with the model the tool "
                        "is given (--checkpoint, --model_dir), if any, else "
                        f"{config_default or 'the built-in defaults'}")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set train.learning_rate=1e-4 (repeatable)")
    p.set_defaults(config_given=False)
    return p


def _onnx_config(path: str) -> str | None:
    """The config in the metadata of the ONNX file `path` (tools/export_onnx.py writes it), as a file that lasts as
    long as this process; None when it has none."""
    import atexit
    import shutil
    import tempfile
    from ff3d_tf.inference.onnx_export import saved_config_yaml
    text = saved_config_yaml(path)
    if text is None:
        return None
    folder = tempfile.mkdtemp(prefix="onnx_config_")
    atexit.register(shutil.rmtree, folder, True)
    local = os.path.join(folder, "config.yaml")
    with open(local, "w", encoding="utf-8") as f:
        f.write(text)
    return local


def saved_config(args) -> tuple[str, str] | None:
    """(the config file saved with the model, the flag's value) of the first of `CHECKPOINT_FLAGS` that `args` holds
    and whose model has one (`ff3d_tf.checkpoints.saved_config`; an ONNX file's metadata); None when there is
    none."""
    for flag in CHECKPOINT_FLAGS:
        path = getattr(args, flag, None)
        if path:
            if path.endswith(".onnx") and os.path.isfile(path):
                found = _onnx_config(path)
            else:
                from ff3d_tf.checkpoints import saved_config as find
                found = find(path)
            if found:
                return found, path
    return None


def load(args, runs_model: bool = True):
    """The config of a tool: --config (when the command line gives it, even "": the built-in defaults) else the config
    saved with the model named by --checkpoint or --model_dir (one line says which file) else the parser's default;
    then every --set. `args.config` is set to the file used (a tool that hands it on hands on the same).

    `runs_model=False`: the tool runs no model (it writes or reads data only), so the config's model section does not
    have to read the data's sweeps: `data.num_frames` > 2 needs no `--set model.temporal` (the model section is left
    at a temporal that reads them, `NO_MODEL_TEMPORAL`, and not used)."""
    from ff3d_tf.config import ConfigError
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if not getattr(args, "config_given", True):  # a namespace not made by `parser`: its config is as given
        found = saved_config(args)
        if found:
            args.config, model = found
            shown = args.config if not model.endswith(".onnx") else f"the metadata of {model}"
            print(f"config: {shown}, the one saved with {model} (--config chooses another)", flush=True)
    try:
        return _load_config(args.config, args.set)
    except ConfigError as e:
        if not runs_model:  # the same config, its model left able to read the sweeps: the only fault a job that
            try:            # runs no model may ignore
                return _load_config(args.config, [*args.set, f"model.temporal={NO_MODEL_TEMPORAL}"])
            except ConfigError:
                pass
        sys.exit(f"config error: {e}")


# The model.temporal of a job that runs no model (`load(runs_model=False)`): one that reads any data.num_frames.
NO_MODEL_TEMPORAL = "stack"


def _load_config(path: str | None, overrides):
    """`load_config` of a local file, or of a remote one (gs://, ram://: a model_dir may be either)."""
    if not path or "://" not in path:
        from ff3d_tf.config import load_config
        return load_config(path, overrides)
    from ff3d_tf.checkpoints import load_saved_config  # imports TensorFlow: after the start-up
    return load_saved_config(path, overrides)


def project_errors() -> tuple[type, ...]:
    """The errors of the project's own checks, each naming what is wrong (file, record, field): a damaged checkpoint,
    a bad record, point file, Argoverse 2 log, submission or export file, an unusable config, and a missing input
    file or directory. (Imported when called: some import TensorFlow.)"""
    from ff3d_tf.checkpoints import CheckpointError
    from ff3d_tf.config import ConfigError
    from ff3d_tf.data.av2.argoverse2 import Argoverse2FormatError
    from ff3d_tf.data.av2.av2_submission import SubmissionFormatError
    from ff3d_tf.data.files.point_file_errors import PointFileError
    from ff3d_tf.data.wod.wod_format import WireFormatError
    from ff3d_tf.data.wod_errors import FrameDecodeError
    from ff3d_tf.xla_program import ExportFormatError
    return (CheckpointError, FrameDecodeError, ConfigError, PointFileError, Argoverse2FormatError,
            SubmissionFormatError, ExportFormatError, WireFormatError, FileNotFoundError)


def run(main) -> None:
    """Calls a tool's `main`; a bad input the project names (`project_errors`) ends the tool with that message and
    exit status 1 instead of a traceback, and so does a data job whose inputs failed so (`DataJobError`: one line per
    input). (The error classes are imported after `main` raised: before it, no TensorFlow module may be imported,
    `start`.)"""
    try:
        main()
    except Exception as e:
        from ff3d_tf.data.beam_job import DataJobError
        if isinstance(e, DataJobError):
            for failure in e.failures:
                print(f"error: {failure}", file=sys.stderr)
            sys.exit(f"error: {e}")
        if isinstance(e, project_errors()):
            sys.exit(f"error: {e}")
        raise
