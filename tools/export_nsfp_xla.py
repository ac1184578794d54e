"""Export NSFP's per-pair optimiser (distance grids and Adam steps of ff3d_tf.labels.nsfp) as portable XLA programs,
one set per point bucket, for CPU and CUDA.

python tools/export_nsfp_xla.py --out DIR [--points 64000,150000] [--segment_steps 50] [--precisions float32,tf32]
    [--reference_calls 1 --reference_points 64000] [--crop_m 35] [--hidden_layers 8 --hidden_units 128]
The pairs are synthetic (ff3d_tf.labels.nsfp_program.synthetic_pair: uniform clouds in the crop box, a box moving by a
known motion) and regenerated from a seed by the runner, so only programs and initial parameters are written.
The fit is the pseudo-label job's (`nsfp.MEASURED_FIT_OPTIONS`: two-sided Chamfer, --reverse_every 5). --points are
the points a fit sees: that job fits every 4th point (`fit_every`) and evaluates the MLP at all, so a pair of 150K
points is the 37,500-point entry.
--reference_calls N also saves TensorFlow's grids and fit after N segments on one pair, which the runner compares
with the device's. Needs the `xla` extra; time the result where only JAX is installed with
`python lab/tools/run_nsfp_xla.py DIR`, or on this machine's CPU against TensorFlow's own fit with
`python lab/tools/benchmark_nsfp_xla_cpu.py DIR`.
"""
import argparse
import dataclasses
import os

import _common

from ff3d_tf.labels import nsfp_program


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.labels.nsfp import MEASURED_FIT_OPTIONS
    from ff3d_tf.labels.nsfp_export import export_nsfp
    # NSFP's options are these flags: the tool reads no experiment config (no --config, no --set)
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True)
    p.add_argument("--points", default="64000,150000", help="cloud sizes (both clouds of a pair), comma-separated")
    p.add_argument("--segment_steps", type=int, default=50, help="Adam steps per call of the fit program")
    p.add_argument("--precisions", default="float32", help=f"of {', '.join(nsfp_program.PRECISIONS)}")
    p.add_argument("--platforms", default="cpu,cuda")
    p.add_argument("--reference_calls", type=int, default=0, help="segments of TensorFlow's reference fit")
    p.add_argument("--reference_points", type=int, default=None, help="the reference pair's size (default: first)")
    p.add_argument("--crop_m", type=float, default=35.0, help="keep |x|, |y| <= this (m): the grid's x-y extent")
    p.add_argument("--grid_cell_m", type=float, default=MEASURED_FIT_OPTIONS.grid_cell_m)
    p.add_argument("--hidden_layers", type=int, default=MEASURED_FIT_OPTIONS.hidden_layers)
    p.add_argument("--hidden_units", type=int, default=MEASURED_FIT_OPTIONS.hidden_units)
    p.add_argument("--reverse_every", type=int, default=MEASURED_FIT_OPTIONS.reverse_every,
                   help="two-sided Chamfer's correspondences found every k steps (0: one-sided)")
    p.add_argument("--seed", type=int, default=0, help="MLP initialisation")
    args = p.parse_args()
    try:
        points = [int(v) for v in args.points.split(",") if v]
        options = dataclasses.replace(
            MEASURED_FIT_OPTIONS, hidden_layers=args.hidden_layers, hidden_units=args.hidden_units,
            grid_cell_m=args.grid_cell_m, crop_xy_half_extent_m=args.crop_m, crop_z_range_m=(-3.0, 3.0),
            reverse_every=args.reverse_every, fit_every=1, seed=args.seed)
        manifest = export_nsfp(options, points, args.out, args.segment_steps, args.precisions.split(","),
                               args.platforms.split(","), args.reference_calls, args.reference_points)
    except ValueError as e:
        p.error(str(e))
    size = sum(os.path.getsize(os.path.join(args.out, n)) for n in os.listdir(args.out))
    print(f"wrote {len(manifest['entries'])} NSFP entries to {args.out} ({size / 2 ** 20:.1f} MiB)")


if __name__ == "__main__":
    main()
