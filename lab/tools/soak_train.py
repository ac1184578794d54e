"""Soak test of fault-tolerant training: a two-worker job on 127.0.0.1 under random faults. JSON into benchmarks/.

python lab/tools/soak_train.py --faults 20 --service --out benchmarks/soak_train.json   # with a tf.data service
python lab/tools/soak_train.py --faults 6 --out benchmarks/soak_train.json              # the trainers alone

Two `tools/train.py` workers (the tests' tiny model on small synthetic segments made in --work_dir), with --service a
fault-tolerant dispatcher and --input_workers input workers; after each random wait (--gap_s) a SIGKILL or SIGTERM
(--sigterm_share) to a random target, then a restart of what died. At the end the job is preempted at step S and
compared with an uninterrupted run of S steps. What each fault's record measures (detect_s, resume_s, stall_s,
steps_lost), what counts as a hang and as a lost checkpoint: `lab/training/soak.py`. Exit status 0: no hang, no
lost checkpoint, and the end equal to the uninterrupted run's (weights; with --service the loss's range).
"""
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402

def main():
    _common.start("inference")  # before TensorFlow is imported
    from lab.training import soak
    defaults = soak.SoakSettings()
    p = _common.parser(__doc__, None)
    p.add_argument("--faults", type=int, default=defaults.faults, help="faults to inject")
    p.add_argument("--service", action="store_true", help="feed the trainers from a tf.data service")
    p.add_argument("--input_workers", type=int, default=defaults.input_workers,
                   help="tf.data service workers (with --service)")
    p.add_argument("--seed", type=int, default=defaults.seed, help="seed of the fault schedule")
    p.add_argument("--gap_s", type=float, nargs=2, default=defaults.gap_s, metavar=("MIN", "MAX"),
                   help="seconds of running training before each fault (uniform)")
    p.add_argument("--targets", default=",".join(defaults.target_kinds),
                   help="kinds of target to choose from (comma-separated; dispatcher and input need --service)")
    p.add_argument("--sigterm_share", type=float, default=defaults.sigterm_share,
                   help="share of faults that are SIGTERM (else SIGKILL)")
    p.add_argument("--max_minutes", type=float, default=defaults.max_minutes,
                   help="no new fault after this; the job is then stopped")
    p.add_argument("--hang_slack_s", type=float, default=defaults.hang_slack_s)
    p.add_argument("--resume_timeout_s", type=float, default=defaults.resume_timeout_s,
                   help="restart -> first step (start-up included)")
    p.add_argument("--work_dir", default=defaults.work_dir, help="data, model dirs and every process's log")
    p.add_argument("--out", default=paths.benchmark_file("soak_train.json"), help="report (merged: one entry per mode)")
    args = p.parse_args()
    settings = soak.SoakSettings(
        faults=args.faults, service=args.service, input_workers=args.input_workers, seed=args.seed,
        gap_s=tuple(args.gap_s), target_kinds=tuple(args.targets.split(",")), sigterm_share=args.sigterm_share,
        max_minutes=args.max_minutes, hang_slack_s=args.hang_slack_s, resume_timeout_s=args.resume_timeout_s,
        work_dir=args.work_dir, config=args.config or "", overrides=tuple(args.set))
    try:
        report = soak.run_soak(settings, args.out)
    except soak.SoakError as e:
        sys.exit(f"error: {e}")
    sys.exit(0 if soak.passed(report) else 1)


if __name__ == "__main__":
    _common.run(main)
