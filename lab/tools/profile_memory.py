"""What holds the resident memory between training steps and between inference calls, per allocator setting. JSON out.

python lab/tools/profile_memory.py --config configs/fastflow3d_waymo.yaml --out benchmarks/memory_cpu.json
    [--variants tf_bfc_pool,system_allocator,...] [--points 32000] [--steps 5] [--calls 5]
    [--repeat 3 --repeat_variants tf_bfc_pool,system_allocator]

Every variant (`lab.training.cpu_studies.MEMORY_VARIANTS`) runs in fresh child processes (one training, one
inference) with its own environment, set before Python starts, so allocator settings never leak from one variant into
the next: the environment keys any variant sets are removed from the others', and every variant states
TF_ONEDNN_USE_SYSTEM_ALLOCATOR explicitly. Training: the Trainer's own step (forward, backward, Adam) on one batch of
--points points held in memory, batch 1, one warm-up step then --steps timed steps. Inference: the predictor's
compiled forward at --points, two warm-up calls then --calls timed calls.

Per call: wall ms, CPU ms of the whole process (user + system, all threads: less moved by other load than wall time),
system-CPU ms and minor page faults, resident set right after the call (what the process holds between calls, no
trim) and the peak during the call. At the end of the calls: glibc's accounting (mallinfo2), TensorFlow's allocator
statistics, /proc/self/smaps summed by kind, smaps_rollup; then the same after gc.collect() + glibc malloc_trim(0)
(`lab.training.cpu_studies.memory_study`).
"""
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)
from lab import tool_args  # noqa: E402

from lab import paths  # noqa: E402
from lab.training import cpu_studies  # noqa: E402


def main(argv=None):
    _common.start("inference")  # before TensorFlow is imported
    variants = cpu_studies.MEMORY_VARIANTS
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--variants", default=",".join(variants), help=f"comma-separated, of: {', '.join(variants)}")
    p.add_argument("--points", type=int, default=32000)
    p.add_argument("--steps", type=int, default=5, help="timed training steps (after one warm-up step)")
    p.add_argument("--calls", type=int, default=5, help="timed inference calls (after two warm-up calls)")
    p.add_argument("--kinds", default="train,infer", help="train, infer or both")
    p.add_argument("--repeat", type=int, default=1,
                   help="rounds over the variants, in turn (fresh processes each): the summary's times are the "
                        "median over the rounds, so a change of load hits all variants alike")
    p.add_argument("--repeat_variants", default=None, help="the variants of the rounds after the first (default: all)")
    p.add_argument("--child_timeout_s", type=int, default=1800)
    p.add_argument("--note", default="", help="findings, appended to the JSON's note")
    p.add_argument("--out", default=paths.benchmark_file("memory_cpu.json"))
    args = p.parse_args(argv)
    _common.load(args)  # a bad config or override ends the tool here, before any child starts
    try:
        result = cpu_studies.memory_study(
            args.config, args.set, args.variants.split(","), args.points, args.steps, args.calls,
            args.kinds.split(","), args.repeat, args.repeat_variants.split(",") if args.repeat_variants else None,
            args.child_timeout_s, args.note, log_fn=lambda line: print(line, flush=True))
    except ValueError as e:
        sys.exit(f"error: {e}")
    tool_args.json_saver(args.out)(result)


if __name__ == "__main__":
    main()
