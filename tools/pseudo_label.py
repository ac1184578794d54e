"""NSFP pseudo-labels for pair records (ZeroFlow's label job), as an Apache Beam job.

python tools/pseudo_label.py --input RECORDS --out_dir PSEUDO [--max_iterations 5000] [--crop_m 51.2]
    [--learning_rate 0.002 --weight_decay 0 --reverse_every 5 --min_delta 1e-5 --fit_every 4]
    [--skip_bad_records] [beam options]
The fit's defaults are the settings measured best on the Argoverse 2 sample pair (`nsfp.MEASURED_FIT_OPTIONS`, README
"Label-free training"); NSFP's published ones are --learning_rate 0.008 --weight_decay 1e-4 --reverse_every 1
--min_delta 1e-4 --fit_every 1.
RECORDS: `tools/write_pair_records.py` output (WOD or Argoverse 2; raw LiDAR with --no_labels works too). PSEUDO then
trains with `--set data.source=pair_records --set data.labels=pseudo` (ZeroFlow's speed-scaled loss); evaluation on
records with human labels still scores those. One Beam element per records file; each pair's fit is kept as soon as
it is done, so a rerun after an interruption fits only the rest; outputs that exist are skipped. A bad record stops
the job naming file, record and field, or with --skip_bad_records is skipped and counted. Argoverse 2 records use
their map's ground mask for the t0 cloud; --ground_below_z_m removes ground by height (both clouds) instead or too.
"""
import argparse
import dataclasses
import logging
import sys
import time

import _common

from ff3d_tf.data import pair_records
from ff3d_tf.data.pairs import list_segment_files
from ff3d_tf.labels.nsfp import MEASURED_FIT_OPTIONS
from ff3d_tf.labels.pseudo_records import run_pseudo_label_job


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--input", required=True, help="directory of pair records")
    p.add_argument("--out_dir", required=True)
    fit = MEASURED_FIT_OPTIONS
    p.add_argument("--max_iterations", type=int, default=fit.max_iterations)
    p.add_argument("--patience", type=int, default=fit.patience)
    p.add_argument("--min_delta", type=float, default=fit.min_delta, help="early stopping's improvement (m^2)")
    p.add_argument("--learning_rate", type=float, default=fit.learning_rate, help="Adam's")
    p.add_argument("--weight_decay", type=float, default=fit.weight_decay, help="L2 on both MLPs")
    p.add_argument("--reverse_every", type=int, default=fit.reverse_every,
                   help="two-sided Chamfer, its correspondences found every k steps (0: one-sided)")
    p.add_argument("--fit_every", type=int, default=fit.fit_every,
                   help="fit on every k-th point, then evaluate the MLP at every point")
    p.add_argument("--grid_cell_m", type=float, default=fit.grid_cell_m, help="distance transform cell")
    p.add_argument("--exact_chamfer", action="store_true", help="exact nearest neighbours (slow; for checking)")
    p.add_argument("--ground_below_z_m", type=float, default=None, help="drop points below this z (vehicle frame)")
    p.add_argument("--crop_m", type=float, default=None, help="keep |x|, |y| <= this (m)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--skip_bad_records", action="store_true", help="skip and count records that do not parse")
    args, beam_args = p.parse_known_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:  # bad arguments fail before any work
        options = dataclasses.replace(
            fit, max_iterations=args.max_iterations, patience=args.patience, min_delta=args.min_delta,
            learning_rate=args.learning_rate, weight_decay=args.weight_decay, reverse_every=args.reverse_every,
            fit_every=args.fit_every, grid_cell_m=args.grid_cell_m, exact_chamfer=args.exact_chamfer,
            remove_ground_below_z_m=args.ground_below_z_m, crop_xy_half_extent_m=args.crop_m, seed=args.seed)
        files = [f for f in list_segment_files(args.input) if f.endswith(pair_records.FILE_SUFFIX)]
        if not files:
            raise FileNotFoundError(f"{args.input}: no pair records (*{pair_records.FILE_SUFFIX}); write them with "
                                    "tools/write_pair_records.py")
        pair_records.manifest_of_files(files)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"pseudo_label: {e}")
    print(f"pseudo-labelling {len(files)} records files -> {args.out_dir}", flush=True)
    t0 = time.time()
    fit_options = {k: v for k, v in dataclasses.asdict(options).items() if v != getattr(fit, k) or k in (
        "learning_rate", "weight_decay", "reverse_every", "min_delta", "fit_every", "max_iterations")}
    print(f"NSFP options: {fit_options}", flush=True)
    written_by = " ".join(["tools/pseudo_label.py"] + sys.argv[1:]) + f" (NSFP options: {fit_options})"
    counts = run_pseudo_label_job(files, args.out_dir, options, beam_args, written_by, args.skip_bad_records)
    el = time.time() - t0
    print(f"done in {el:.1f} s ({counts.get('fitted_pairs', 0) / max(el, 1e-9):.3f} pairs/s): {counts}")


if __name__ == "__main__":
    _common.run(main)
