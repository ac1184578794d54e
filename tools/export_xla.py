"""Export the model's forward as portable XLA artifacts (one per point bucket, CPU and CUDA), weights saved once.

python tools/export_xla.py --config C [--checkpoint M] --points 32000,100000 --out DIR [--precisions float32,tf32]
Without --checkpoint the weights are the model's random initialisation (enough for latency). Needs the `xla` extra
(`pip install .[xla]`); run the result where only JAX is installed with `python tools/run_xla.py DIR`.
"""
import _common

from ff3d_tf.inference import xla_artifact
from ff3d_tf.inference.xla_export import PLATFORMS, export_forward


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", default=None, help="checkpoint prefix or model_dir (default: random weights)")
    p.add_argument("--points", default="32000,100000,255000,1000000", help="cloud sizes, comma-separated")
    p.add_argument("--precisions", default="float32", help=f"comma-separated, of {', '.join(xla_artifact.PRECISIONS)}")
    p.add_argument("--platforms", default=",".join(PLATFORMS))
    p.add_argument("--batch_size", type=int, default=1)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    cfg = _common.load(args)
    try:
        points = [int(v) for v in args.points.split(",")]
    except ValueError:
        p.error(f"--points must be comma-separated integers, got {args.points!r}")
    if args.checkpoint:
        from ff3d_tf.inference.predictor import restore_model
        model = restore_model(cfg, args.checkpoint)
    else:
        from ff3d_tf.model import build_model
        model = build_model(cfg)
    try:
        manifest = export_forward(cfg, model, points, args.out, args.precisions.split(","), args.platforms.split(","),
                                  args.batch_size, weights_source=args.checkpoint or "random initialisation")
    except ValueError as e:
        p.error(str(e))
    print(f"wrote {len(manifest['artifacts'])} artifacts and {xla_artifact.WEIGHTS_NAME} to {args.out}")


if __name__ == "__main__":
    main()
