"""What DeFlow's GRU head (model.head=gru) costs beside the paper head on this CPU: forward latency and peak memory at
each point count, and the training step, every reading in its own process, the variants in one round robin. JSON out.

python lab/tools/benchmark_head_cost.py --out benchmarks/head_cost_cpu.json [--config configs/fastflow3d_waymo.yaml]
    [--gru_iterations 4,2] [--points 32000,255000,1000000] [--train_points 32000] [--runs 3] [--warmup 2]
    [--steps 3] [--rounds 1] [--cores N] [--timeout_s S]

Variants: "paper" (the reference) and "gru<K>" (--set model.head=gru model.gru_iterations=K) for each K of
--gru_iterations. What each figure is, the ratios and the generated `note`: `lab.training.head_cost`.
"""
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)
from lab import tool_args  # noqa: E402

from lab import paths  # noqa: E402
from lab.training import head_cost  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--out", default=paths.benchmark_file("head_cost_cpu.json"))
    p.add_argument("--gru_iterations", default="4,2", help="model.gru_iterations of the GRU variants")
    p.add_argument("--points", default="32000,255000,1000000", help="the forward's point counts")
    p.add_argument("--train_points", type=int, default=32000, help="the training step's point count (0: none)")
    p.add_argument("--runs", type=int, default=3, help="timed forward calls per child")
    p.add_argument("--warmup", type=int, default=2, help="unmeasured calls (or steps) first in each child")
    p.add_argument("--steps", type=int, default=3, help="timed training steps per child")
    p.add_argument("--rounds", type=int, default=1, help="every child once per round, in turn")
    p.add_argument("--cores", type=int, default=None, help="CPUs per child (default: all this process may use)")
    p.add_argument("--timeout_s", type=float, default=None, help="stop a child after this long (recorded)")
    args = p.parse_args()
    _common.load(args)  # the config and --set checked here, before any child starts
    save = tool_args.json_saver(args.out)
    try:
        result = head_cost.run(
            args.config or "", args.set, tool_args.int_list(p, args.points, "--points"), args.train_points,
            gru_iterations=tool_args.int_list(p, args.gru_iterations, "--gru_iterations"), runs=args.runs,
            warmup=args.warmup, steps=args.steps, rounds=args.rounds, cores=args.cores, timeout_s=args.timeout_s,
            command="python lab/tools/benchmark_head_cost.py " + " ".join(sys.argv[1:]),
            log=lambda line: print(line, flush=True), save=save)
    except ValueError as e:
        p.error(str(e))
    print(json.dumps(result["ratios"]))


if __name__ == "__main__":
    _common.run(main)
