"""What the lab's measuring tools share beyond `tools/_common.py`: integer-list flags and a JSON file kept up to date
after every measured entry."""
from __future__ import annotations

import argparse


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
            from ff3d_tf.json_io import write_json
            write_json(path, result)
    return save
