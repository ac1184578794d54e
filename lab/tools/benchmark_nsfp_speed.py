"""NSFP (ff3d_tf.labels.nsfp) at traffic speeds: end-point error of candidate fits on synthetic pairs whose moving
vehicles drive at 0-5 m/s and at 10-20 m/s, and on the real Argoverse 2 sample pair. JSON out.

python lab/tools/benchmark_nsfp_speed.py --out benchmarks/nsfp_speed.json [--points 8192] [--sensor timed]
    [--tune_seeds 1,2] [--held_out_seeds 3,4] [--bands 0-5,10-20] [--candidates baseline,nsfp_rate,...]
    [--held_out_candidates baseline] [--real_candidates baseline] [--real_log data/av2_sample_log] [--skip_real]

Every fit is written to --out as it completes, with a progress line and an ETA; a rerun fits only what the file
lacks (a candidate whose options changed is fitted again). The candidates are changes to the pseudo-label job's fit
(`nsfp.MEASURED_FIT_OPTIONS`), `CANDIDATES` below. What each figure is: `lab.labels.nsfp_speed`.
"""
import argparse
import json
import os
import sys

# tools/ on sys.path, also when run through runpy: the tools' shared flags (_common)
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tools"))

import _common  # noqa: E402, F401  (puts the repository root on sys.path too)

from lab import paths  # noqa: E402

# name -> changes to the job's fit (NsfpOptions fields): what might lose fast movers (issue 53, item 5)
CANDIDATES = {
    "baseline": {},  # the pseudo-label job's fit
    "nsfp_rate": {"learning_rate": 8e-3},  # NSFP's published rate (the job's: 0.002)
    "patient": {"patience": 400, "min_delta": 0.0},  # the early stop: four times the patience, any improvement
    "every_point": {"fit_every": 1},  # no sampling: every kept point in the fit
    "no_crop": {"crop_xy_half_extent_m": None},  # no x-y crop: objects leaving the 35 m box keep their partner
    "fine_grid": {"grid_cell_m": 0.05},  # a finer distance transform
}


def _ints(text: str) -> list[int]:
    return [int(t) for t in text.split(",") if t]


def _names(text: str) -> list[str]:
    names = [t for t in text.split(",") if t]
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown candidates {unknown}; they are {sorted(CANDIDATES)}")
    return names


def main():
    _common.start("inference")  # before TensorFlow is imported
    from lab.labels import nsfp_speed
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=paths.benchmark_file("nsfp_speed.json"))
    p.add_argument("--points", type=int, default=8192, help="points per synthetic sweep")
    p.add_argument("--sensor", default=nsfp_speed.DEFAULT_SENSOR, choices=sorted(nsfp_speed.SENSORS))
    p.add_argument("--tune_seeds", type=_ints, default=[1, 2])
    p.add_argument("--held_out_seeds", type=_ints, default=[3, 4])
    p.add_argument("--bands", default="0-5,10-20", help=f"speed bands, of {sorted(nsfp_speed.BANDS_MPS)}")
    p.add_argument("--candidates", type=_names, default=list(CANDIDATES))
    p.add_argument("--held_out_candidates", type=_names, default=["baseline"])
    p.add_argument("--real_candidates", type=_names, default=["baseline"])
    p.add_argument("--real_log", default=os.path.join(paths.ROOT, "data", "av2_sample_log"))
    p.add_argument("--skip_real", action="store_true")
    args = p.parse_args()
    bands = [b for b in args.bands.split(",") if b]
    unknown = [b for b in bands if b not in nsfp_speed.BANDS_MPS]
    if unknown:
        p.error(f"unknown bands {unknown}; they are {sorted(nsfp_speed.BANDS_MPS)}")
    names = list(dict.fromkeys(args.candidates + args.held_out_candidates + args.real_candidates))
    result = nsfp_speed.run(args.out, {n: CANDIDATES[n] for n in names}, args.tune_seeds, args.held_out_seeds,
                            args.held_out_candidates, bands, args.points, args.sensor,
                            None if args.skip_real else args.real_log, args.real_candidates,
                            log=lambda line: print(line, flush=True))
    print(json.dumps({k: result[k] for k in ("tune", "held_out", "real_pair")}, indent=1))


if __name__ == "__main__":
    main()
