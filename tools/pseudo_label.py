"""NSFP pseudo-labels for pair records (ZeroFlow's label job), as an Apache Beam job.

python tools/pseudo_label.py --input RECORDS --out_dir PSEUDO [--crop_m 35 --z_range_m -3 3] [--ground auto]
    [--max_iterations 5000 --fit_every 4 ...] [--max_speed_mps 50 --retries 1 --on_bad_fit skip]
    [--skip_bad_records] [beam options]
Defaults: the job's fit (`nsfp.MEASURED_FIT_OPTIONS`): NSFP's two-sided Chamfer on every 4th point, the region the
Argoverse 2 challenge scores (|x|, |y| <= 35 m) and z in [-3, 3] m, ground removed from both clouds (the records' map
masks for Argoverse 2 records, else a local height rule). Points outside the fitted region get no pseudo-label
(`pseudo_valid_t0` False). NSFP's published fit: --learning_rate 0.008 --weight_decay 1e-4 --reverse_every 1
--min_delta 1e-4 --fit_every 1.
RECORDS: `tools/write_pair_records.py` output (WOD or Argoverse 2; raw LiDAR with --no_labels works too). PSEUDO then
trains with `--set data.source=pair_records --set data.labels=pseudo`. Resumable per pair; a bad record stops the job
naming file, record and field, or with --skip_bad_records is skipped and counted; a fit that stays implausible is
named in the report and its pair written without pseudo-labels (--on_bad_fit stop: the job stops). On Argoverse 2
records the pseudo-labels are scored against Argoverse's labels (PSEUDO/pseudo_label_scores.json).
"""
import argparse
import dataclasses
import json
import sys
import time

import _common

from ff3d_tf.data import pair_records
from ff3d_tf.data.pairs import list_segment_files
from ff3d_tf.labels import pseudo_records

# flag -> NsfpOptions field, for the fit's options a user may change here
_FIT_FLAGS = {"max_iterations": int, "patience": int, "min_delta": float, "learning_rate": float,
              "weight_decay": float, "reverse_every": int, "fit_every": int, "grid_cell_m": float, "seed": int}


def _args():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--input", required=True, help="directory of pair records")
    p.add_argument("--out_dir", required=True)
    job = pseudo_records.JobOptions()
    for flag, kind in _FIT_FLAGS.items():
        p.add_argument(f"--{flag}", type=kind, default=getattr(job.nsfp, flag))
    p.add_argument("--exact_chamfer", action="store_true", help="exact nearest neighbours (slow; for checking)")
    p.add_argument("--crop_m", type=float, default=job.nsfp.crop_xy_half_extent_m,
                   help="fit the points with |x|, |y| <= this (m); 0: no crop (the grid coarsens to fit)")
    p.add_argument("--z_range_m", type=float, nargs=2, default=job.nsfp.crop_z_range_m, metavar=("LO", "HI"))
    p.add_argument("--ground", choices=pseudo_records.GROUND_RULES, default=job.ground)
    p.add_argument("--ground_below_z_m", type=float, default=None, help="also drop points below this z (both clouds)")
    p.add_argument("--max_speed_mps", type=float, default=job.max_speed_mps)
    p.add_argument("--max_implausible_fraction", type=float, default=job.max_implausible_fraction)
    p.add_argument("--retries", type=int, default=job.retries)
    p.add_argument("--on_bad_fit", choices=pseudo_records.BAD_FIT_ACTIONS, default=job.on_bad_fit)
    p.add_argument("--skip_bad_records", action="store_true", help="skip and count records that do not parse")
    return p.parse_known_args()


def main():
    args, beam_args = _args()
    try:  # bad arguments fail before any work
        defaults = pseudo_records.JobOptions()
        nsfp = dataclasses.replace(
            defaults.nsfp, **{f: getattr(args, f) for f in _FIT_FLAGS}, exact_chamfer=args.exact_chamfer,
            crop_xy_half_extent_m=args.crop_m or None, crop_z_range_m=tuple(args.z_range_m),
            remove_ground_below_z_m=args.ground_below_z_m)
        job = pseudo_records.JobOptions(nsfp, args.ground, args.max_speed_mps, args.max_implausible_fraction,
                                        args.retries, args.on_bad_fit)
        files = [f for f in list_segment_files(args.input) if f.endswith(pair_records.FILE_SUFFIX)]
        if not files:
            raise FileNotFoundError(f"{args.input}: no pair records (*{pair_records.FILE_SUFFIX}); write them with "
                                    "tools/write_pair_records.py")
        pair_records.manifest_of_files(files)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"pseudo_label: {e}")
    print(f"pseudo-labelling {len(files)} records files -> {args.out_dir}", flush=True)
    written_by = " ".join(["tools/pseudo_label.py"] + sys.argv[1:])
    print(f"options: {json.dumps(dataclasses.asdict(job))}", flush=True)
    t0 = time.time()
    try:
        counts = pseudo_records.run_pseudo_label_job(files, args.out_dir, job, beam_args, written_by,
                                                     args.skip_bad_records)
    except (pseudo_records.BadFitError, ValueError) as e:
        sys.exit(f"pseudo_label: {e}")
    el = time.time() - t0
    scores = counts.pop("scores", None)
    print(f"done in {el:.1f} s ({counts.get('fitted_pairs', 0) / max(el, 1e-9):.3f} pairs/s): {counts}")
    if scores:
        print("against the records' human labels (Argoverse 2 challenge arithmetic, m): pseudo-labels three-way EPE "
              f"{scores['nsfp']['three_way/mean_epe_m']:.4f}, bucketed normalized dynamic "
              f"{scores['nsfp']['bucketed/mean_dynamic_norm_epe']:.3f}; zero flow "
              f"{scores['zero_flow']['three_way/mean_epe_m']:.4f}, "
              f"{scores['zero_flow']['bucketed/mean_dynamic_norm_epe']:.3f} "
              f"({args.out_dir}/{pseudo_records.SCORES_NAME})")


if __name__ == "__main__":
    _common.run(main)
