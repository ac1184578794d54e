"""Bootstrap scene-flow labels from tracked boxes for WOD segments (paper Sec. 3), as an Apache Beam pipeline.

python tools/annotate_flow.py --input 'segments/*.tfrecord' --out_dir labelled/ [beam options, e.g. --runner ...]
Needs the `beam` extra (pip install -e '.[beam]'; `make install` includes it). One Beam element per segment; outputs
that exist are skipped, so a rerun resumes. On a cloud runner pass gs:// paths and the standard options, e.g.
--runner=DataflowRunner --project P --region R --temp_location gs://B/tmp --setup_file ./setup.py
"""
import argparse
import logging
import sys
import time

import _common  # noqa: F401


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.labels.pipeline import decode_options, run_pipeline
    from ff3d_tf.data.pairs import list_segment_files
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--input", required=True, help="directory or glob of WOD segment TFRecords with laser_labels")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--returns", default="1,2", help="returns to label, e.g. 1 or 1,2")
    p.add_argument("--skip_bad_records", action="store_true")
    args, beam_args = p.parse_known_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:  # bad arguments fail before any work
        returns = tuple(int(r) for r in args.returns.split(","))
        decode_options(returns=returns)
        files = list_segment_files(args.input)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"annotate_flow: {e}")
    print(f"annotating {len(files)} segments -> {args.out_dir}", flush=True)
    t0 = time.time()
    counts = run_pipeline(files, args.out_dir, beam_args, returns=returns, skip_bad_records=args.skip_bad_records)
    el = time.time() - t0
    print(f"done in {el:.1f} s ({counts.get('frames', 0) / max(el, 1e-9):.2f} frames/s end to end): {counts}")


if __name__ == "__main__":
    main()
