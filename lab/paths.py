"""Where the lab's files are: the checkout, its benchmarks/ folder (the figures the lab's tools write and its studies
read back) and the product's tools, which the lab runs as child processes."""
from __future__ import annotations

import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the checkout (under Bazel: the runfiles tree)
# realpath: under Bazel this module is a link into the checkout, and benchmarks/ is not among a target's runfiles.
BENCHMARKS_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.realpath(__file__))), "benchmarks")
TOOLS_DIR = os.path.join(ROOT, "tools")  # the product's tools (train.py, eval.py, ...)
LAB_TOOLS_DIR = os.path.join(ROOT, "lab", "tools")  # the lab's own (benchmark_*.py, run_planted.py, ...)


def benchmark_file(name: str) -> str:
    """benchmarks/`name` of the checkout."""
    return os.path.join(BENCHMARKS_DIR, name)
