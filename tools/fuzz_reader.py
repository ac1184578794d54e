"""Fuzz the readers: damaged WOD records and files, damaged Argoverse 2 feather logs, damaged YAML configs, damaged
sequences of your own sweeps (point files of every format, poses, timestamps, box tables).

python tools/fuzz_reader.py [--mutants 2000] [--files 40] [--pair_files 4] [--av2_mutants 270] \
    [--config_mutants 700] [--sequence_mutants 320] [--seed 0] [--work_dir /tmp/fuzz] [--out fuzz_report.json]

Every mutant must end as a finite decode or the reader's own error naming file, record and field (configs: the key
and what is allowed); never a crash, a raw library error, a hang (the process aborts with a traceback after
--hang_s per input) or a huge allocation. Prints mutants by kind x outcome, the slowest input and the peak memory;
exits 1 if any defect was found. The inputs are a tiny synthetic segment and `data/av2_sample_log` (copied, never
written) and a small sequence of every point format written here. See `ff3d_tf.fuzz` for the mutation kinds;
a read of a damaged sequence that allocates far more than its files hold is a defect too (`huge_allocation`).
"""
import argparse
import json
import os
import sys
import tempfile
import time

import _common  # noqa: F401

from ff3d_tf.config import load_config
from ff3d_tf.fuzz.report import peak_rss_mib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.data.synthetic import wod as synthetic
    from ff3d_tf.data.wod import waymo
    from ff3d_tf.fuzz import av2 as av2_fuzz, config as config_fuzz, files as files_fuzz, wod as wod_fuzz
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mutants", type=int, default=2000, help="damaged WOD records decoded one by one")
    p.add_argument("--files", type=int, default=40, help="damaged WOD files read whole (mixed or cut)")
    p.add_argument("--pair_files", type=int, default=4, help="of those, read through the tf.data pair pipeline too")
    p.add_argument("--av2_mutants", type=int, default=270)
    p.add_argument("--config_mutants", type=int, default=700)
    p.add_argument("--sequence_mutants", type=int, default=320, help="damaged sequences of your own sweeps")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--lidar_scale", type=float, default=0.12, help="range image scale of the synthetic segment")
    p.add_argument("--hang_s", type=float, default=60.0,
                   help=f"abort with a traceback if one input takes longer (a whole file: {wod_fuzz.FILE_FACTOR}x)")
    p.add_argument("--av2_log", default=os.path.join(ROOT, "data", "av2_sample_log"))
    p.add_argument("--work_dir", default=None)
    p.add_argument("--out", default=None, help="JSON report")
    args = p.parse_args()
    work = args.work_dir or tempfile.mkdtemp(prefix="fuzz_reader_")
    os.makedirs(work, exist_ok=True)
    segment = os.path.join(work, "segment.tfrecord")
    synthetic.write_segment(segment, synthetic.SegmentSpec(seed=5, num_frames=4, lidar_scale=args.lidar_scale))
    records = [r for _, r in waymo.iterate_records(segment)]
    reports, t0 = {}, time.time()
    reports["wod_records"] = wod_fuzz.fuzz_records(records, args.mutants, args.seed, hang_s=args.hang_s)
    print(reports["wod_records"].format("WOD records"), flush=True)
    if args.files:
        cfg = load_config(None, ["grid.num_pillars_x=32", "grid.num_pillars_y=32", "grid.x_range_m=[-40, 40]",
                                 "grid.y_range_m=[-40, 40]"])
        reports["wod_files"] = wod_fuzz.fuzz_files(records, os.path.join(work, "files"), args.files, args.seed,
                                                   cfg, num_pair_files=args.pair_files, hang_s=args.hang_s)
        print(reports["wod_files"].format("WOD files"), flush=True)
    if args.av2_mutants:
        reports["av2"] = av2_fuzz.fuzz_log(args.av2_log, os.path.join(work, "av2"), args.av2_mutants, args.seed,
                                           hang_s=args.hang_s)
        print(reports["av2"].format("Argoverse 2 logs"), flush=True)
    if args.config_mutants:
        reports["configs"] = config_fuzz.fuzz_configs(os.path.join(work, "configs"), args.config_mutants,
                                                     args.seed, hang_s=args.hang_s)
        print(reports["configs"].format("YAML configs"), flush=True)
    if args.sequence_mutants:
        reports["sequences"] = files_fuzz.fuzz_sequence(os.path.join(work, "sequences"), args.sequence_mutants,
                                                        args.seed, hang_s=args.hang_s)
        print(reports["sequences"].format("sequences of your own sweeps"), flush=True)
    defects = sum(len(r.defects) for r in reports.values())
    total = sum(len(r.results) for r in reports.values())
    print(f"{total} inputs in {time.time() - t0:.0f} s, {defects} defects, peak memory {peak_rss_mib():.0f} MiB")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({name: {"table": {k: dict(v) for k, v in r.table().items()},
                              "slowest_s": r.slowest().seconds if r.results else None,
                              "defects": [vars(d) for d in r.defects]} for name, r in reports.items()}
                      | {"peak_rss_mib": peak_rss_mib(), "defects": defects}, f, indent=1)
    sys.exit(1 if defects else 0)


if __name__ == "__main__":
    main()
