"""bfloat16 convolutions (`model.mixed_precision=true`) against float32 on this CPU: speed and accuracy. JSON out.

python lab/tools/benchmark_bf16.py --out benchmarks/bf16_cpu.json [--runs 5] [--train_steps 300] [--skip_demo]

Sections (`lab.training.bf16_study`, whose docstring says what each measures): cpu (bfloat16 flags, what
model.mixed_precision=auto picks here), convolution (one convolution and the dense stages, oneDNN's own times, in a
child process), latency (lab/tools/benchmark_latency.py, float32 and bfloat16), demo (the demo trained and evaluated in
both precisions), summary (the speed-ups and differences).
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
from lab.training import bf16_study  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=paths.benchmark_file("bf16_cpu.json"))
    p.add_argument("--runs", type=int, default=5, help="round-robin rounds of the latency section")
    p.add_argument("--points", default="32000,1000000",
                   help="point counts of the latency section; the training step runs at the first")
    p.add_argument("--conv_runs", type=int, default=5)
    p.add_argument("--train_steps", type=int, default=300, help="demo training steps per precision")
    p.add_argument("--skip_demo", action="store_true")
    p.add_argument("--note", default="", help="context recorded in the JSON (machine load, commit)")
    p.add_argument("--work_dir", default=None, help="demo data and models (default: a temporary directory; "
                                                    "given, existing data and finished runs are reused)")
    args = p.parse_args()
    points = tool_args.int_list(p, args.points, "--points")
    if not points:
        p.error("--points: at least one point count")
    try:
        results = bf16_study.bf16_study(points, args.runs, args.conv_runs, args.train_steps, not args.skip_demo,
                                        args.work_dir, " ".join(["lab/tools/benchmark_bf16.py"] + sys.argv[1:]),
                                        args.note, log_fn=lambda line: print(line, flush=True))
    except ChildError as e:
        sys.exit(str(e))
    print(json.dumps(results["summary"], indent=1))
    tool_args.json_saver(args.out)(results)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
