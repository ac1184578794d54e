"""Run a SavedModel or checkpoint over a WOD TFRecord (or an Argoverse 2 log): per-frame flows (.npz) and BEV PNGs.

python tools/predict.py --config C --checkpoint M --input SEGMENT.tfrecord --out_dir O [--png_every 10]
python tools/predict.py --config C --checkpoint M --av2_log data/av2_sample_log --out_dir O
"""
import os

import _common
import numpy as np
import tensorflow as tf

from ff3d_tf import viz
from ff3d_tf.data import pairs, waymo
from ff3d_tf.data.wod_errors import MissingFlowLabelsError
from ff3d_tf.inference.predictor import load_predictor


def _examples(args, cfg) -> tf.data.Dataset:
    if args.av2_log:
        from ff3d_tf.labels import av2
        return tf.data.Dataset.from_tensors(av2.model_example(args.av2_log, cfg))
    first = next(waymo.iterate_records(args.input))[1]
    try:
        waymo.decode_frame(first, laser_names=cfg.data.laser_names, source=args.input)
        inference_only = False
    except MissingFlowLabelsError:
        inference_only = True
        print(f"{args.input}: no flow labels; predicting without ground truth", flush=True)
    return pairs.pair_dataset([args.input], cfg, inference_only=inference_only)


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", required=True, help="SavedModel directory, model_dir or checkpoint prefix")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", help="one WOD segment TFRecord")
    src.add_argument("--av2_log", help="an Argoverse 2 log directory (two consecutive sweeps)")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--png_every", type=int, default=10, help="a BEV PNG every this many frames (first included)")
    args = p.parse_args()
    cfg = _common.load(args)
    os.makedirs(args.out_dir, exist_ok=True)
    predictor = load_predictor(cfg, args.checkpoint)

    def examples():  # a bad record in --input: FrameDecodeError naming file, record and field
        with pairs.input_errors_named([args.input or args.av2_log]):
            yield from pairs.padded_singletons(_examples(args, cfg), cfg.data.point_bucket_base)

    n = 0
    for i, (batch, ex) in enumerate(examples()):
        ex = {k: v.numpy() for k, v in ex.items()}
        flow, valid = predictor.predict(batch, ex)
        has_labels = bool(np.any(ex["class_id_t0"] >= 0))
        name = f"frame_{i:04d}"
        np.savez_compressed(os.path.join(args.out_dir, name + ".npz"), points_xyz_t0=ex["points_xyz_t0"],
                            flow_mps_pred=flow, point_valid=valid, flow_mps_true=ex["flow_mps_t0"],
                            class_id_t0=ex["class_id_t0"])
        if i % args.png_every == 0:
            panels = {"prediction": np.where(valid[:, None], flow, 0.0)}
            if has_labels:
                panels["ground truth"] = np.where((ex["class_id_t0"] >= 0)[:, None], ex["flow_mps_t0"], 0.0)
            png = viz.bev_flow_png(os.path.join(args.out_dir, name + "_bev.png"), ex["points_xyz_t0"], panels,
                                   title=f"{args.input or args.av2_log} pair {i}: colour = direction, "
                                         f"brightness = speed")
            print(f"wrote {png}", flush=True)
        n += 1
        print(f"predicted pair {i}: {int(valid.sum())}/{len(valid)} points with a prediction", flush=True)
    print(f"wrote {n} frames to {args.out_dir}")


if __name__ == "__main__":
    _common.run(main)
