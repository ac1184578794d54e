"""Export the model's forward (and, with --train_points, its training step) as portable XLA artifacts (one per
point bucket, batch size and precision; CPU and CUDA), weights saved once.

python tools/export_xla.py --config C [--checkpoint M] --points 32000,100000 --out DIR [--precisions float32,tf32]
    [--train_points 177000 --train_batch_sizes 1,8 --train_precisions tf32,bfloat16] [--reference]
Without --checkpoint the weights are the model's random initialisation (enough for latency). --reference also saves
TensorFlow's results on fixed inputs, which the runner compares with the device's. Needs the `xla` extra
(`pip install .[xla]`); run the result where only JAX is installed with `python lab/tools/run_xla.py DIR`.
"""
import os

import _common

from ff3d_tf import xla_export_dir


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.inference.xla_export import PLATFORMS, export_forward
    from ff3d_tf.training.xla_step_export import export_train_steps
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", default=None, help="checkpoint prefix or model_dir (default: random weights)")
    p.add_argument("--points", default="32000,100000,255000,1000000", help="cloud sizes, comma-separated")
    p.add_argument("--precisions", default="float32",
                   help=f"comma-separated, of {', '.join(xla_export_dir.PRECISIONS)}")
    p.add_argument("--platforms", default=",".join(PLATFORMS))
    p.add_argument("--batch_size", type=int, default=1)
    p.add_argument("--train_points", default="", help="cloud sizes of training-step artifacts (default: none)")
    p.add_argument("--train_batch_sizes", default="1", help="batch sizes of the training-step artifacts")
    p.add_argument("--train_precisions", default=None, help="default: --precisions")
    p.add_argument("--reference", action="store_true", help="save TensorFlow's results for the runner to compare")
    p.add_argument("--variants", default="", help="other programs of the forward for lab/tools/profile_xla.py to "
                   "compare (comma-separated; each one of fold_bn, one_chunk or several joined with '+')")
    p.add_argument("--variant_points", default="", help="the variants' cloud sizes (default: --points)")
    p.add_argument("--variant_precisions", default="", help="the variants' precisions (default: --precisions)")
    p.add_argument("--out", required=True)
    args = p.parse_args()
    cfg = _common.load(args)
    def integers(flag, text):
        try:
            return [int(v) for v in text.split(",") if v]
        except ValueError:
            p.error(f"--{flag} must be comma-separated integers, got {text!r}")
    points = integers("points", args.points)
    train_points = integers("train_points", args.train_points)
    train_batch_sizes = integers("train_batch_sizes", args.train_batch_sizes)
    if args.checkpoint:
        from ff3d_tf.checkpoints import restore_model
        model = restore_model(cfg, args.checkpoint)
    else:
        from ff3d_tf.model import build_model
        model = build_model(cfg)
    precisions = args.precisions.split(",")
    train_precisions = args.train_precisions.split(",") if args.train_precisions else precisions
    try:
        xla_export_dir.check_precisions(precisions + train_precisions)  # before the forward is written
        manifest = export_forward(cfg, model, points, args.out, precisions, args.platforms.split(","),
                                  args.batch_size, weights_source=args.checkpoint or "random initialisation",
                                  reference=args.reference, variants=[v for v in args.variants.split(",") if v],
                                  variant_points=integers("variant_points", args.variant_points),
                                  variant_precisions=[v for v in args.variant_precisions.split(",") if v])
        if train_points:
            manifest = export_train_steps(cfg, model, args.out, train_points, train_batch_sizes, train_precisions,
                                          reference=args.reference)
    except ValueError as e:
        p.error(str(e))
    from ff3d_tf.checkpoints import with_model_partner
    # the tools given this export load it (tools/_common.py), the model's partner in it (as in manifest.json)
    with_model_partner(cfg, model).save(os.path.join(args.out, "config.yaml"))
    print(f"wrote {len(manifest['artifacts'])} forward and {len(manifest['train_artifacts'])} training-step artifacts "
          f"and {xla_export_dir.WEIGHTS_NAME} to {args.out}")


if __name__ == "__main__":
    _common.run(main)
