"""Latency of the ONNX export under onnxruntime (CPU) beside TensorFlow's serving forward, in one run. JSON out.

python lab/tools/benchmark_onnx.py --config configs/fastflow3d_waymo.yaml [--checkpoint M] --points 32000 --runs 3
    --threads 2 --variants loop,single_chunk --out benchmarks/onnx_cpu.json

One pair of benchmark clouds, random weights without --checkpoint. TensorFlow runs the SavedModel's serving function;
each ONNX variant runs in onnxruntime with --threads intra-op threads. After one warm-up round, every call takes its
turn in one round robin: compare the ratios. Also recorded: each variant's export time, its largest flow difference
from TensorFlow, whether validity is identical, and whether its outputs were bit-identical over all its calls. What
each figure is: `lab.inference.onnx_timing`.
"""
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)
from lab import tool_args  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    from lab.inference import onnx_timing
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", default=None, help="model_dir or checkpoint prefix (default: random weights)")
    p.add_argument("--points", type=int, default=32000)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    p.add_argument("--variants", default="loop,single_chunk")
    p.add_argument("--note", default="")
    p.add_argument("--out", default="onnx_cpu.json")
    args = p.parse_args()
    cfg = _common.load(args)
    results = {"note": args.note, "config": args.config, "overrides": args.set,
               **onnx_timing.run(cfg, args.checkpoint, args.points, args.runs, args.threads, args.variants.split(","),
                                 log=lambda line: print(line, flush=True))}
    tool_args.json_saver(args.out)(results)
    print(json.dumps(onnx_timing.headline(results), indent=1))


if __name__ == "__main__":
    _common.run(main)
