"""Export a checkpoint as a SavedModel for serving: python tools/export.py --config C --checkpoint M --out DIR"""
import os

import _common


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.inference.saved_model import export_saved_model
    from ff3d_tf.checkpoints import restore_model
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    cfg = _common.load(args)
    model = restore_model(cfg, args.checkpoint)
    export_saved_model(model, args.out, cfg.data.point_bucket_base, cfg.model.jit_compile)
    cfg.save(os.path.join(args.out, "config.yaml"))  # the tools given this SavedModel load it (tools/_common.py)
    print(f"wrote SavedModel {args.out} (signature serving_default) and its config.yaml")


if __name__ == "__main__":
    _common.run(main)
