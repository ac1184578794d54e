"""JSON written whole or not at all: what every job's record (stages, summaries, the runners' results) is saved with.
Standard library only (rank 0)."""
from __future__ import annotations

import json
import os


def write_json(path: str, value, sort_keys: bool = False) -> None:
    """`value` as indented JSON at `path`, its folder made, written whole or not at all (a reader never sees half a
    file: a run stopped from outside keeps the last complete write)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    partial = path + ".partial"
    with open(partial, "w") as f:
        json.dump(value, f, indent=1, sort_keys=sort_keys)
    os.replace(partial, path)
