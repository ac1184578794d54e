"""Write decode-once pair records (training and evaluation input with no decoding), as an Apache Beam job.

python tools/write_pair_records.py --source wod --input 'segments/*.tfrecord' --out_dir records/ [--config C]
python tools/write_pair_records.py --source av2 --input av2/sensor/train --out_dir records/train
python tools/write_pair_records.py --source av2 --input av2/sensor/test --out_dir records/test --no_labels
python tools/write_pair_records.py --source files --input 'scans/*' --out_dir records/ [--class_map M.yaml] \
    [--box_margin_m 0] [--sweep_period_s 0.1] [--intensity_scale auto] [--no_labels]
Then train or evaluate with `--set data.source=pair_records` and the records directory as the data directory.
One Beam element per WOD segment, Argoverse 2 log or sequence of your own sweeps; outputs that exist are skipped, so a
rerun resumes. Your own sweeps (--source files): one or many sweeps directories as `tools/predict.py --sweeps_dir`
reads them, with poses (required), an optional timestamps.txt (s, one a sweep; else one sweep every --sweep_period_s)
and a box table boxes.csv|boxes.feather labelling the points by the paper's box rule (ff3d_tf/labels/own_records.py,
docs/datasets.md); --no_labels writes them unlabelled, for tools/pseudo_label.py. Argoverse 2 logs without
annotations.feather (the test split) need --no_labels: the same points and pairs, the map's ground, no labels (for
tools/av2_submission.py --split test).
`--precision compact` stores point features and flows as float16 (coordinates stay float32); `--compression zlib`
trades read CPU for disk. Any other arguments are Beam options (e.g. --direct_num_workers=2
--direct_running_mode=multi_processing, or a cloud runner's).
An input whose data fails the project's checks (a bad record, a missing or reordered sweep: each error names file,
record and field) fails alone: the others are written, then the tool prints one line per failed input and exits 1
(a rerun after the fix resumes). The summary counts what was written and what was skipped and why (skipped_pairs:
left out by data.skip_bad_records; pairs_without_full_history: examples whose history reaches before their
sequence's start, which training does not read).
"""
import argparse
import sys
import time

import _common  # noqa: F401

from ff3d_tf.config import ConfigError
from ff3d_tf.data.files import point_files


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.data import pair_records, pairs
    p = _common.parser(__doc__)
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--source", choices=pair_records.SOURCES, required=True)
    p.add_argument("--input", required=True, help="WOD: directory or glob of segment TFRecords; AV2: a split "
                   "directory of logs (<split>/<log_id>/sensors/lidar/...) or one log directory; files: a sweeps "
                   "directory, a directory of them, or a glob of them")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--precision", choices=pair_records.PRECISIONS, default="exact")
    p.add_argument("--compression", choices=pair_records.COMPRESSIONS, default="none")
    p.add_argument("--no_labels", action="store_true", help="WOD segments without scene-flow labels, Argoverse 2 "
                   "logs without annotations.feather (the test split), or your sweeps without their boxes (raw "
                   "LiDAR; for tools/pseudo_label.py or, AV2, a test submission)")
    p.add_argument("--class_map", help="files: YAML mapping your box classes to vehicle, pedestrian, cyclist, sign, "
                                       "background or null (dropped)")
    p.add_argument("--box_margin_m", type=float, default=0.0, help="files: added to each box's length and width")
    p.add_argument("--sweep_period_s", type=float, default=0.1, help="files: sweep times without timestamps.txt")
    p.add_argument("--intensity_scale", default="auto", metavar="auto|NUMBER|A/B",
                   help="files: the intensity rule of tools/predict.py (auto: integer types / their maximum)")
    args, beam_args = p.parse_known_args()
    cfg = _common.load(args, runs_model=False)  # no model runs here: data.num_frames alone says the sweeps
    written_by = " ".join(["tools/write_pair_records.py"] + sys.argv[1:])
    try:  # bad arguments fail before any work
        if args.source == "wod" and args.no_labels:
            from ff3d_tf.data.wod import write_records
            inputs = pairs.list_segment_files(args.input)
            run = lambda: write_records.run_wod_job(inputs, args.out_dir, cfg, args.precision,  # noqa: E731
                                                    args.compression, beam_args, written_by, human_labels=False)
        elif args.source == "wod":  # labelled segments: the records also hold each point's box (instance_id_t0)
            from ff3d_tf.labels import pipeline
            inputs = pairs.list_segment_files(args.input)
            run = lambda: pipeline.run_wod_records_job(inputs, args.out_dir, cfg, args.precision,  # noqa: E731
                                                       args.compression, beam_args, written_by)
        elif args.source == "av2":
            from ff3d_tf.labels import av2
            inputs = av2.list_logs(args.input)
            for log_dir in inputs:  # a log without annotations fails before any work, naming it
                av2.check_log(log_dir, not args.no_labels)
            run = lambda: av2.run_records_job(inputs, args.out_dir, cfg, args.precision,  # noqa: E731
                                              args.compression, beam_args, written_by, labels=not args.no_labels)
        else:
            from ff3d_tf.data.files import box_table, sequences
            from ff3d_tf.labels import own_records
            inputs = sequences.list_sequences(args.input)
            class_map = box_table.read_class_map(args.class_map) if args.class_map else {}
            options = own_records.OwnRecordsOptions(not args.no_labels, args.sweep_period_s,
                                                    point_files.parse_intensity_scale(args.intensity_scale),
                                                    args.box_margin_m, tuple(class_map.items()))
            for directory in inputs:  # poses and box tables checked before any work
                own_records.check_sequence(directory, options)
            run = lambda: own_records.run_records_job(inputs, args.out_dir, cfg, options,  # noqa: E731
                                                      args.precision, args.compression, beam_args, written_by)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        sys.exit(f"write_pair_records: {e}")
    unit = {"wod": "segments", "av2": "logs", "files": "sequences"}[args.source]
    print(f"writing pair records of {len(inputs)} {unit} -> {args.out_dir}", flush=True)
    t0 = time.time()
    counts = run()
    el = time.time() - t0
    print(f"done in {el:.1f} s ({counts.get('pairs', 0) / max(el, 1e-9):.2f} pairs/s end to end): {counts}")


if __name__ == "__main__":
    _common.run(main)
