"""Run one of the project's tools with the lab's planted defects registered (lab/training/planted_defects.py), e.g.
the benchmark's reversed delta:

python lab/tools/run_planted.py tools/train.py --config C --set model.temporal=delta_reversed ...
python lab/tools/run_planted.py tools/eval.py --checkpoint M ...
"""
import os
import sys

# tools/ and the repository root on sys.path, also when run through runpy
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path; imports no TensorFlow)

from lab.training import planted_defects  # noqa: E402


def main():
    _common.start("train")  # before TensorFlow is imported; the lab measures the variants' accuracy, not their speed
    if len(sys.argv) < 2 or not sys.argv[1].endswith(".py"):
        sys.exit("usage: python lab/tools/run_planted.py TOOL.py [ARGS...]")
    planted_defects.run_tool(sys.argv[1], sys.argv[2:])


if __name__ == "__main__":
    main()
