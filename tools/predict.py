"""Run a model, or NSFP without one, over a WOD TFRecord, an Argoverse 2 log or your own point clouds: flows, BEV PNGs
and (optionally) a 3D recording for the Rerun viewer. The model (--checkpoint M) is a model_dir or checkpoint prefix, a
SavedModel directory, an .onnx file or a portable XLA export directory (batch 1): what the path holds chooses the
runtime (ff3d_tf/inference/predictor.py). --method nsfp needs no model: NSFP is fitted to each pair (the config's
nsfp section, as tools/pseudo_label.py; seconds to minutes a pair on a CPU; ff3d_tf/labels/nsfp_predictor.py), its
flow the motion over the pair's gap: D/timestamps.txt, else --sweep_period_s (0.1).

python tools/predict.py --config C --checkpoint M --input SEGMENT.tfrecord --out_dir O [--png_every 10]
python tools/predict.py --config C --checkpoint M --av2_log data/av2_sample_log --out_dir O
python tools/predict.py --config C --checkpoint M --points_tm1 A.pcd --points_t0 B.pcd [--pose_tm1 P --pose_t0 Q] \
    --out_dir O [--intensity_scale auto] [--rerun O/flow.rrd]
python tools/predict.py --config C --checkpoint M --sweeps_dir D --out_dir O [--rerun O/flow.rrd]
python tools/predict.py --method nsfp --sweeps_dir D --out_dir O [--sweep_period_s 0.1] [--set nsfp.KEY=VALUE]

Own point clouds (.npy, .npz, KITTI .bin, PCD, PLY; points in the vehicle frame, metres): formats, the intensity
rule and the poses of a sweeps directory (D/poses.txt or D/<sweep>.pose.txt|.pose.npy) are described in
ff3d_tf/data/files/point_files.py. Without poses the past clouds are taken as already in the t0 vehicle frame. Each
predicted sweep writes <sweep name>.npz (flow_mps, point_valid, points_xyz_t0) and <sweep name>.feather, one row per
point of the sweep's file in its order (points outside the grid: point_valid false, flow 0), and a BEV PNG every
--png_every pairs. The examples are built in the order of the sweeps the model reads (its data.num_frames and
data.partner, saved with it): every sweep after the first for a model of the previous sweep, every sweep before the
last for a model of the next sweep (Argoverse 2 challenge records); a sweep further than data.max_frame_gap_s after
the one before it (D/timestamps.txt) is an error (data.skip_bad_records: the examples across it skipped). Every flow
written is the velocity of the t0 points (m/s). --rerun (any input) writes both clouds and the flow arrows of every
pair on a `sweep` time line (ff3d_tf/viz3d.py); open it with `rerun O/flow.rrd`. The job:
ff3d_tf/inference/predict_job.py.
"""
import argparse
import itertools

import _common
import numpy as np

from ff3d_tf.data.files import point_files


def _intensity_scale(text: str):
    try:
        return point_files.parse_intensity_scale(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _arguments():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--method", choices=("model", "nsfp"), default="model",
                   help="model: the trained model at --checkpoint; nsfp: NSFP fitted to each pair, no model")
    p.add_argument("--checkpoint", help="--method model: model_dir, checkpoint prefix, SavedModel directory, .onnx "
                                        "file or portable XLA export directory")
    p.add_argument("--sweep_period_s", type=float, default=0.1, help="your clouds: the time between sweeps (s) "
                                                                     "where a sweeps directory has no timestamps.txt")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", help="one WOD segment TFRecord")
    src.add_argument("--av2_log", help="an Argoverse 2 log directory: every sweep with a partner")
    src.add_argument("--points_t0", help="your t0 point cloud (.npy, .npz, .bin, .pcd, .ply); with --points_tm1")
    src.add_argument("--sweeps_dir", help="a directory of consecutive sweeps (sorted by name), each pair predicted; "
                                          "poses from D/poses.txt or D/<sweep>.pose.txt|.pose.npy if present")
    p.add_argument("--points_tm1", help="your t-1 point cloud (the sweep before --points_t0)")
    p.add_argument("--pose_tm1", help="vehicle -> world pose of --points_tm1: 4x4 (or 3x4) text, or .npy")
    p.add_argument("--pose_t0", help="vehicle -> world pose of --points_t0 (with --pose_tm1)")
    p.add_argument("--intensity_scale", type=_intensity_scale, default=None, metavar="auto|NUMBER|A/B",
                   help="multiply the stored intensity of your files by this (e.g. 1/255); default auto: integer "
                        "columns divided by their type's maximum (uint8: 255, as Argoverse 2), floats as stored")
    p.add_argument("--rerun", metavar="OUT.rrd", help="also write a Rerun recording of both clouds and the flow "
                                                      "arrows, one time step per sweep (needs the viz3d extra)")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--png_every", type=int, default=10, help="a BEV PNG every this many frames (first included)")
    args = p.parse_args()
    own = args.points_t0 or args.sweeps_dir
    if (args.method == "model") != bool(args.checkpoint):
        p.error("--method model needs --checkpoint; --method nsfp fits each pair and takes no model")
    if not args.sweep_period_s > 0:
        p.error("--sweep_period_s must be > 0")
    if bool(args.points_t0) != bool(args.points_tm1):
        p.error("--points_t0 and --points_tm1 go together (one pair of your own clouds)")
    if (args.pose_tm1 is None) != (args.pose_t0 is None):
        p.error("--pose_tm1 and --pose_t0 go together (or give neither: the t-1 cloud is then taken as already in "
                "the t0 frame)")
    if args.pose_t0 is not None and not args.points_t0:
        p.error("--pose_tm1/--pose_t0 are the poses of --points_tm1/--points_t0 (a sweeps directory has its own: "
                "D/poses.txt)")
    if args.intensity_scale is not None and not own:
        p.error("--intensity_scale applies to your own clouds (--points_t0 or --sweeps_dir)")
    if args.png_every < 1:
        p.error("--png_every must be at least 1")
    return args


def _source(args, cfg, order):
    """The pair source of the command line (`predict_job.PairSource`), its examples in the model's `order` (which
    only an Argoverse 2 log's needs when the source is made)."""
    from ff3d_tf.inference import predict_job
    if args.av2_log:  # its labelled pairs come from the labels pipeline, which the inference job does not import
        import tensorflow as tf
        from ff3d_tf.labels import av2
        partner = "next" if order.partner_matters and order.partner == "next" else "previous"

        def examples():  # read lazily, one example at a time (a log's sweeps would not fit in memory together)
            rows = av2.log_examples(args.av2_log, cfg, order.num_frames, partner)
            first = next(rows)
            spec = {k: tf.TensorSpec([None] * np.ndim(v), tf.as_dtype(np.asarray(v).dtype)) for k, v in first.items()}
            return tf.data.Dataset.from_generator(lambda: itertools.chain([first], rows), output_signature=spec)
        return predict_job.ExampleDataset(args.av2_log, examples, partner)
    if args.input:
        return predict_job.WodSegment(args.input)
    if args.sweeps_dir:
        return predict_job.SweepsDirectory(args.sweeps_dir, args.intensity_scale, args.sweep_period_s)
    return predict_job.PointFilePair(args.points_tm1, args.points_t0, args.pose_tm1, args.pose_t0,
                                     args.intensity_scale, args.sweep_period_s)


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.config import replace_config
    from ff3d_tf.inference import predict_job
    from ff3d_tf.inference.predictor import load_predictor, sweep_order
    args = _arguments()
    cfg = _common.load(args, runs_model=args.method == "model")
    if args.method == "nsfp":  # the labels pipeline's fit, wired in here: the inference job does not import it
        from ff3d_tf.labels import nsfp_predictor
        predictor = nsfp_predictor.predictor_from_config(cfg, args.sweep_period_s, predict_job.print_line)
    else:  # loaded first: the examples are built in the order of the sweeps it reads
        if args.sweeps_dir or args.points_t0:  # the user's files (a directory's poses and times) checked first
            _source(args, cfg, None).check(cfg)
        predictor = load_predictor(replace_config(cfg, {"data.partner": None}), args.checkpoint)
    predict_job.predict(cfg, args.checkpoint, _source(args, cfg, sweep_order(predictor)), args.out_dir,
                        args.png_every, args.rerun, predictor=predictor)


if __name__ == "__main__":
    _common.run(main)
