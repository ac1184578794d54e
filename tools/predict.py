"""Run a model over a WOD TFRecord, an Argoverse 2 log or your own point clouds: flows, BEV PNGs and (optionally) a
3D recording for the Rerun viewer. The model (--checkpoint M) is a model_dir or checkpoint prefix, a SavedModel
directory, an .onnx file or a portable XLA export directory (batch 1): what the path holds chooses the runtime
(ff3d_tf/inference/predictor.py).

python tools/predict.py --config C --checkpoint M --input SEGMENT.tfrecord --out_dir O [--png_every 10]
python tools/predict.py --config C --checkpoint M --av2_log data/av2_sample_log --out_dir O
python tools/predict.py --config C --checkpoint M --points_tm1 A.pcd --points_t0 B.pcd [--pose_tm1 P --pose_t0 Q] \
    --out_dir O [--intensity_scale auto] [--rerun O/flow.rrd]
python tools/predict.py --config C --checkpoint M --sweeps_dir D --out_dir O [--rerun O/flow.rrd]

Own point clouds (.npy, .npz, KITTI .bin, PCD, PLY; points in the vehicle frame, metres): formats, the intensity
rule and the poses of a sweeps directory (D/poses.txt or D/<sweep>.pose.txt|.pose.npy) are described in
ff3d_tf/data/files/point_files.py. Without poses the t-1 cloud is taken as already in the t0 vehicle frame. Each pair
writes <t0 sweep name>.npz (flow_mps, point_valid, points_xyz_t0) and <t0 sweep name>.feather, one row per point
of the t0 file in its order (points outside the grid: point_valid false, flow 0), and a BEV PNG every --png_every
pairs. --rerun (any input) writes both clouds and the flow arrows of every pair on a `sweep` time line
(ff3d_tf/viz3d.py); open it with `rerun O/flow.rrd`.
"""
import argparse
import os
import sys

import _common
import numpy as np
import tensorflow as tf

from ff3d_tf import viz, viz3d
from ff3d_tf.config import replace_config
from ff3d_tf.data import pairs
from ff3d_tf.data.files import point_files
from ff3d_tf.data.wod import waymo
from ff3d_tf.data.files.point_file_errors import PointFileError
from ff3d_tf.data.wod_errors import MissingFlowLabelsError
from ff3d_tf.inference.predictor import load_predictor

# Own clouds are predicted point for point: no crop (points outside the grid get point_valid false) and no study.
OWN_CLOUD_CONFIG = {"data.crop_to_grid": False, "data.point_keep_fraction": 1.0,
                    "data.remove_ground_below_z_m": None, "data.class_ablation": "none"}


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


def _dataset_pairs(args, cfg):
    """(name, sweep index of t0, batch, example) of each pair of --input or --av2_log."""
    with pairs.input_errors_named([args.input or args.av2_log]):  # a bad record: FrameDecodeError naming it
        for i, (batch, ex) in enumerate(pairs.padded_singletons(_examples(args, cfg), cfg.data.point_bucket_base)):
            yield f"frame_{i:04d}", i + 1, batch, {k: v.numpy() for k, v in ex.items()}


class _Notes:
    """Prints each remark about the user's files once (a log of many sweeps repeats the same ones)."""

    def __init__(self):
        self.seen = set()

    def say(self, key: str, text: str) -> None:
        if key not in self.seen:
            self.seen.add(key)
            print(text, flush=True)


def _read_sweep(path: str, pose, scale, notes: _Notes) -> dict:
    cols = point_files.read_point_file(path)
    for note in cols.notes:
        notes.say(note, f"{path}: {note}")
    if cols.ignored:
        notes.say("ignored " + ",".join(cols.ignored), f"{path}: columns not used: {', '.join(cols.ignored)}")
    if cols.intensity is None:
        notes.say("no intensity", f"{path}: no intensity column ({'/'.join(point_files.INTENSITY_FIELDS)}): "
                                  "intensity 0")
    else:
        factor = point_files.intensity_scale_of(cols.intensity_dtype, scale)
        rule = "--intensity_scale" if scale is not None else "auto: integer types / their maximum, floats as stored"
        notes.say(f"scale {cols.intensity_dtype} {factor}", f"{path}: intensity stored as {cols.intensity_dtype}, "
                                                            f"multiplied by {factor:.6g} ({rule})")
    return point_files.frame_from_columns(cols, pose, scale)


def _own_pairs(args, cfg):
    """(name, sweep index of t0, batch, example) of each consecutive pair of the user's clouds."""
    if args.sweeps_dir:
        sweeps = point_files.list_sweeps(args.sweeps_dir)
        poses = point_files.sweep_poses(args.sweeps_dir, sweeps)
        print(f"{args.sweeps_dir}: {len(sweeps)} sweeps, {len(sweeps) - 1} pairs, "
              f"{'poses given' if poses is not None else 'no poses'}", flush=True)
    else:
        sweeps = [args.points_tm1, args.points_t0]
        poses = None if args.pose_t0 is None else [point_files.read_pose(args.pose_tm1),
                                                   point_files.read_pose(args.pose_t0)]
    if poses is None:
        print("no poses: the t-1 cloud of each pair is taken as already in the t0 vehicle frame (no ego-motion "
              "compensation)", flush=True)
    own_cfg = replace_config(cfg, OWN_CLOUD_CONFIG)
    notes, frame_tm1 = _Notes(), None
    for i, path in enumerate(sweeps):
        frame_t0 = _read_sweep(path, None if poses is None else poses[i], args.intensity_scale, notes)
        if frame_tm1 is not None:
            ex = pairs.make_pair({k: tf.constant(v) for k, v in frame_tm1.items()},
                                 {k: tf.constant(v) for k, v in frame_t0.items()}, own_cfg, seed=tf.constant([1, 7]))
            for batch, example in pairs.padded_singletons(tf.data.Dataset.from_tensors(ex),
                                                          cfg.data.point_bucket_base):
                name = os.path.splitext(os.path.basename(path))[0]
                yield name, i, batch, {k: v.numpy() for k, v in example.items()}
        frame_tm1 = frame_t0


def _intensity_scale(text: str):
    try:
        return point_files.parse_intensity_scale(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _arguments():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--checkpoint", required=True, help="model_dir, checkpoint prefix, SavedModel directory, .onnx "
                                                       "file or portable XLA export directory")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", help="one WOD segment TFRecord")
    src.add_argument("--av2_log", help="an Argoverse 2 log directory (two consecutive sweeps)")
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


def main():
    args = _arguments()
    cfg = _common.load(args)
    own = bool(args.points_t0 or args.sweeps_dir)
    source = args.input or args.av2_log or args.points_t0 or args.sweeps_dir
    try:
        recording = None
        if args.rerun:  # before any work: a missing extra fails at once
            recording = viz3d.FlowRecording(args.rerun, recording_name=os.path.basename(os.path.normpath(source)))
        os.makedirs(args.out_dir, exist_ok=True)
        # Own clouds: the model loads after the first pair is read, so a bad file fails at once.
        predictor, n = None if own else load_predictor(cfg, args.checkpoint), 0
        for i, (name, sweep, batch, ex) in enumerate((_own_pairs if own else _dataset_pairs)(args, cfg)):
            if predictor is None:
                predictor = load_predictor(cfg, args.checkpoint)
            flow, valid = predictor.predict(batch, ex)
            if own:
                written = point_files.write_predictions(os.path.join(args.out_dir, name), ex["points_xyz_t0"], flow,
                                                        valid)
                print(f"wrote {', '.join(written)}", flush=True)
                has_labels = False
            else:
                has_labels = bool(np.any(ex["class_id_t0"] >= 0))
                np.savez_compressed(os.path.join(args.out_dir, name + ".npz"), points_xyz_t0=ex["points_xyz_t0"],
                                    flow_mps_pred=flow, point_valid=valid, flow_mps_true=ex["flow_mps_t0"],
                                    class_id_t0=ex["class_id_t0"])
            if i % args.png_every == 0:
                panels = {"prediction": np.where(valid[:, None], flow, 0.0)}
                if has_labels:
                    panels["ground truth"] = np.where((ex["class_id_t0"] >= 0)[:, None], ex["flow_mps_t0"], 0.0)
                png = viz.bev_flow_png(os.path.join(args.out_dir, name + "_bev.png"), ex["points_xyz_t0"], panels,
                                       title=f"{source} pair {i}: colour = direction, brightness = speed")
                print(f"wrote {png}", flush=True)
            if recording is not None:
                recording.log_pair(sweep, ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"], flow, valid,
                                   ex["pose_t0"])
            n += 1
            print(f"predicted pair {i}: {int(valid.sum())}/{len(valid)} points with a prediction", flush=True)
        if recording is not None:
            print(f"wrote {recording.close()} (open it with: rerun {args.rerun})", flush=True)
    except (PointFileError, viz3d.Viz3dUnavailableError) as e:
        sys.exit(f"error: {e}")
    print(f"wrote {n} frames to {args.out_dir}")


if __name__ == "__main__":
    _common.run(main)
