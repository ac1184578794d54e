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
