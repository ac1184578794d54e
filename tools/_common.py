"""Shared flag handling of the tools: --config plus repeatable --set key=value, logging, error exit."""
from __future__ import annotations

import argparse
import logging
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")


def parser(description: str, config_default: str | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--config", default=config_default, help="YAML file of overrides (configs/*.yaml)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config value, e.g. --set train.learning_rate=1e-4 (repeatable)")
    return p


def load(args):
    from ff3d_tf.config import ConfigError, load_config
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        return load_config(args.config, args.set)
    except ConfigError as e:
        sys.exit(f"config error: {e}")


def run(main) -> None:
    """Calls a tool's `main`; a bad input the project names (a damaged checkpoint, a bad record, an unusable
    config) ends the tool with that message and exit status 1 instead of a traceback."""
    from ff3d_tf.config import ConfigError
    from ff3d_tf.data.wod_errors import FrameDecodeError
    from ff3d_tf.checkpoints import CheckpointError
    try:
        main()
    except (CheckpointError, FrameDecodeError, ConfigError) as e:
        sys.exit(f"error: {e}")


def int_list(p: argparse.ArgumentParser, value: str, flag: str) -> list[int]:
    """Comma-separated integers of a flag (empty: []); a bad one ends the tool through the parser, naming `flag`."""
    try:
        return [int(v) for v in value.split(",") if v]
    except ValueError:
        p.error(f"{flag} must be comma-separated integers, got {value!r}")


def json_saver(path: str | None):
    """A function that writes its argument as JSON to `path` (nothing when None), making its folder: the XLA runners
    call it after every measured entry, so that a run stopped from outside keeps what it measured."""
    def save(result) -> None:
        if path:
            import json
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            with open(path, "w") as f:
                json.dump(result, f, indent=1)
    return save
