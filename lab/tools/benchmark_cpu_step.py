"""Where the training step's time and memory go on a CPU, stage by stage and per compile mode, before and after the
CPU choices of the project (`lab.training.cpu_step_study`), every variant in a fresh process. JSON out.

python lab/tools/benchmark_cpu_step.py --out benchmarks/cpu_step_avx2.json [--config configs/fastflow3d_waymo.yaml]
    [--cap zen3] [--modes auto,hybrid,xla,none] [--jobs train,forward] [--settings before,after]
    [--train_points 32000] [--forward_points 32000,1000000] [--steps 3] [--warmup 2] [--runs 3] [--no_stages]

--cap names the ISA caps of `ff3d_tf.cpu.EMULATIONS` every child runs under (zen3: oneDNN and XLA capped to AVX2, as
on an AMD Zen 3); "before" is the process as TensorFlow starts it there and the point stages as they were, "after" the
start-up environment of `ff3d_tf.cpu.startup_environment` for the job and the point stages' per-cloud programs,
"after_onednn" that with TensorFlow's oneDNN operations on, "after_remat" that with model.remat_encoder=true (the
encoder's activations recomputed in the backward). Each figure is this machine's under the caps;
`projection_zen3` scales the issue's Zen 3 figures by its ratios.
"""
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)
from lab import tool_args  # noqa: E402

from lab import paths  # noqa: E402
from lab.training import cpu_step_study  # noqa: E402


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--out", default=paths.benchmark_file("cpu_step_avx2.json"))
    p.add_argument("--cap", default="zen3", help="ISA caps: a name of ff3d_tf.cpu.EMULATIONS, or none (this CPU's own)")
    p.add_argument("--modes", default=",".join(cpu_step_study.MODES))
    p.add_argument("--jobs", default=",".join(cpu_step_study.JOBS))
    p.add_argument("--settings", default=",".join(cpu_step_study.SETTINGS),
                   help=f"of {', '.join(cpu_step_study.ALL_SETTINGS)}")
    p.add_argument("--train_points", type=int, default=32000)
    p.add_argument("--forward_points", default="32000,1000000")
    p.add_argument("--steps", type=int, default=3, help="measured training steps per child")
    p.add_argument("--warmup", type=int, default=2, help="unmeasured calls first (tracing, compilation)")
    p.add_argument("--runs", type=int, default=3, help="measured forward calls per point count")
    p.add_argument("--stage_runs", type=int, default=3, help="measured calls of each part of the step")
    p.add_argument("--no_stages", action="store_true", help="time the whole step only")
    p.add_argument("--cores", type=int, default=2)
    p.add_argument("--rounds", type=int, default=1, help="every variant once per round, in turn; medians over rounds")
    p.add_argument("--timeout_s", type=float, default=None, help="stop a child after this long (recorded)")
    p.add_argument("--resummarize", action="store_true",
                   help="measure nothing: compute --out's summary again from its variants")
    args = p.parse_args()
    if args.resummarize:
        with open(args.out) as f:
            tool_args.json_saver(args.out)(cpu_step_study.resummarize(json.load(f)))
        return
    _common.load(args)  # validates the config and --set here, before any child starts
    words = {name: [w for w in getattr(args, name).split(",") if w] for name in ("modes", "jobs", "settings")}
    save = tool_args.json_saver(args.out)
    cpu_step_study.study(
        args.config or "", args.set, args.train_points, tool_args.int_list(p, args.forward_points, "--forward_points"),
        words["modes"], words["jobs"], words["settings"], args.cap, args.steps, args.warmup, args.runs,
        not args.no_stages, args.stage_runs, args.cores, args.timeout_s,
        save=lambda result: save({**result, "command": "python lab/tools/benchmark_cpu_step.py " + " ".join(
            os.sys.argv[1:])}), rounds=args.rounds)


if __name__ == "__main__":
    _common.run(main)
