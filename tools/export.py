"""Export a checkpoint as a SavedModel for serving: python tools/export.py --config C --checkpoint M --out DIR

The SavedModel records the order of the sweeps its model reads (data.num_frames, data.partner, model.temporal;
docs/deployment.md, "Several sweeps"), and DIR/config.yaml is the config with the model's partner."""
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
    # config.yaml beside it: the tools given this SavedModel load it (tools/_common.py)
    export_saved_model(model, args.out, cfg.data.point_bucket_base, cfg.model.jit_compile, cfg=cfg)
    print(f"wrote SavedModel {args.out} (signature serving_default, {model.num_frames} sweeps, partner "
          f"{model.partner}) and its config.yaml")


if __name__ == "__main__":
    _common.run(main)
