"""Write decode-once pair records (training and evaluation input with no decoding), as an Apache Beam job.

python tools/write_pair_records.py --source wod --input 'segments/*.tfrecord' --out_dir records/ [--config C]
python tools/write_pair_records.py --source av2 --input av2/sensor/train --out_dir records/train
Then train or evaluate with `--set data.source=pair_records` and the records directory as the data directory.
One Beam element per WOD segment or Argoverse 2 log; outputs that exist are skipped, so a rerun resumes.
`--precision compact` stores point features and flows as float16 (coordinates stay float32); `--compression zlib`
trades read CPU for disk. Any other arguments are Beam options (e.g. --direct_num_workers=2
--direct_running_mode=multi_processing, or a cloud runner's).
"""
import argparse
import sys
import time

import _common  # noqa: F401

from ff3d_tf.config import ConfigError
from ff3d_tf.data import pair_records, pairs


def main():
    p = _common.parser(__doc__)
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--source", choices=pair_records.SOURCES, required=True)
    p.add_argument("--input", required=True, help="WOD: directory or glob of segment TFRecords; AV2: a split "
                   "directory of logs (<split>/<log_id>/sensors/lidar/...) or one log directory")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--precision", choices=pair_records.PRECISIONS, default="exact")
    p.add_argument("--compression", choices=pair_records.COMPRESSIONS, default="none")
    p.add_argument("--no_labels", action="store_true",
                   help="WOD segments without scene-flow labels (raw LiDAR; for tools/pseudo_label.py)")
    args, beam_args = p.parse_known_args()
    cfg = _common.load(args)
    written_by = " ".join(["tools/write_pair_records.py"] + sys.argv[1:])
    try:  # bad arguments fail before any work
        if args.source == "wod":
            from ff3d_tf.data.wod import write_records
            inputs = pairs.list_segment_files(args.input)
            run = lambda: write_records.run_wod_job(inputs, args.out_dir, cfg, args.precision,  # noqa: E731
                                                    args.compression, beam_args, written_by, not args.no_labels)
        else:
            from ff3d_tf.labels import av2
            inputs = av2.list_logs(args.input)
            run = lambda: av2.run_records_job(inputs, args.out_dir, cfg, args.precision,  # noqa: E731
                                              args.compression, beam_args, written_by)
    except (ConfigError, ValueError, FileNotFoundError) as e:
        sys.exit(f"write_pair_records: {e}")
    print(f"writing pair records of {len(inputs)} {'segments' if args.source == 'wod' else 'logs'} -> "
          f"{args.out_dir}", flush=True)
    t0 = time.time()
    counts = run()
    el = time.time() - t0
    print(f"done in {el:.1f} s ({counts.get('pairs', 0) / max(el, 1e-9):.2f} pairs/s end to end): {counts}")


if __name__ == "__main__":
    _common.run(main)
