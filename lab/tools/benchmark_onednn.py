"""TensorFlow's oneDNN operations on against off, per ISA cap: the Trainer's training step and the compiled forward,
each setting in its own child process (TensorFlow reads TF_ENABLE_ONEDNN_OPTS once, at start). JSON out.

python lab/tools/benchmark_onednn.py --out benchmarks/cpu_onednn_avx2.json [--config configs/synthetic_cpu.yaml]
    [--points 20000] [--caps avx2,none] [--steps 5] [--rounds 2]

--caps: `avx2` runs the children with oneDNN and XLA capped to AVX2 (the caps of `ff3d_tf.cpu.EMULATIONS["zen3"]`:
how an AVX2-only CPU such as AMD Zen 3 runs), `none` with this CPU's own ISA. Each round runs every (cap, oneDNN) child
once, in turn, so a change of load hits all alike; the summary is the median over rounds of each child's median step
(`lab.training.cpu_studies.onednn_study`).
"""
import argparse
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)
from lab import tool_args  # noqa: E402

from lab import paths  # noqa: E402
from lab.children import ChildError  # noqa: E402
from lab.training import cpu_studies  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=paths.benchmark_file("cpu_onednn_avx2.json"))
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--points", type=int, default=20000)
    p.add_argument("--caps", default="avx2,none", help=f"comma-separated, of: {', '.join(cpu_studies.ONEDNN_CAPS)}")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--rounds", type=int, default=2)
    args = p.parse_args()
    try:
        result = cpu_studies.onednn_study(args.config, args.points, args.caps.split(","), args.steps, args.rounds,
                                          log_fn=lambda line: print(line, flush=True))
    except (ValueError, ChildError) as e:
        sys.exit(f"error: {e}")
    tool_args.json_saver(args.out)(result)
    print(json.dumps(result["summary"], indent=1))


if __name__ == "__main__":
    main()
