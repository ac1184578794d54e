"""Forward latency of FastFlow3D vs point count, the dense-convolution floor of each backend and the training step,
for every compile mode side by side (paper Table 3). JSON out.

python lab/tools/benchmark_latency.py --config configs/fastflow3d_waymo.yaml --modes auto,xla,hybrid,none --out L.json
    [--precisions float32,bfloat16]
Variants: every compile mode (--modes) in every precision (--precisions: float32, bfloat16 or auto, the values of
`model.mixed_precision` false, true, auto; default: the config's), named "mode" with one precision, "mode/precision"
with several; all with the same weights. Batch 1, the benchmark cloud of `lab.bench`; every measured call (each
variant at each point count, the conv floors, each variant's training step at --train_points: the Trainer's own step)
takes its turn in one round robin: compare ratios within one run. What each figure is: `lab.inference.latency`.
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
    from lab.inference import latency
    from lab.training import bench_steps
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--points", default="32000,100000,255000,1000000")
    p.add_argument("--modes", default=None, help="comma-separated model.compile modes (default: the config's)")
    p.add_argument("--precisions", default=None,
                   help="comma-separated float32, bfloat16, auto (model.mixed_precision false, true, auto; default: "
                        "the config's)")
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--train_points", type=int, default=32000, help="0 = no training-step benchmark")
    p.add_argument("--skip_conv_floor", action="store_true",
                   help="no conv floor (its buffers stay resident and count in the later calls' memory)")
    p.add_argument("--out", default="latency.json")
    args = p.parse_args()
    points = tool_args.int_list(p, args.points, "--points")
    cfg = _common.load(args)
    try:
        precisions = latency.precision_settings(args.precisions, cfg.model.mixed_precision)
    except ValueError as e:
        p.error(f"--precisions: {e}")
    results = latency.run(cfg, (args.modes or cfg.model.compile).split(","), precisions, points, args.runs,
                          args.train_points, not args.skip_conv_floor, bench_steps.example, bench_steps.train_steps,
                          log=lambda line: print(line, flush=True))
    tool_args.json_saver(args.out)(results)
    print(json.dumps(results["ratios"]))


if __name__ == "__main__":
    main()
