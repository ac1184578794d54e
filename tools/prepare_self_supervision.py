"""Self-supervision's preparation (SeFlow, TeFlow) for pair records, as an Apache Beam job.

python tools/prepare_self_supervision.py --input RECORDS --out_dir PREPARED [--config C.yaml]
    [--set selfsup.KEY=VALUE ...] [--skip_bad_records] [beam options]
For every log (records file) of RECORDS: DUFOMap over the whole log, HDBSCAN clusters of each sweep's dynamic points,
written into the records as `dynamic_cluster_<cloud>` for every sweep a record holds
(`ff3d_tf.labels.self_supervision`).
The options are the config's `selfsup` section (`ff3d_tf.config.SelfSupConfig` documents each key; the authors'
values by default), e.g. --set selfsup.sensor_origin_m=[1.35,0,1.9] (the lidar's position in the vehicle frame, m)
--set selfsup.ground=height --set selfsup.num_threads=4. RECORDS: `tools/write_pair_records.py` output of any source
(WOD, Argoverse 2, your own sequences; raw LiDAR with --no_labels works too). PREPARED then trains with
`--set data.source=pair_records --set data.labels=self --set train.loss=seflow` (or teflow over every sweep).
Resumable per log (a finished log's output is skipped); a bad log (one sweep, a non-rigid pose, a missing sweep, a
record that does not parse) fails alone naming file, record and field, the others are written; with
--skip_bad_records it is left out and counted.
"""
import dataclasses
import json
import sys
import time

import _common


def _args():
    p = _common.parser(__doc__)
    p.add_argument("--input", required=True, help="directory of pair records")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--skip_bad_records", action="store_true", help="leave out and count the logs that fail a check")
    return p.parse_known_args()


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.labels import pseudo_records, self_supervision
    args, beam_args = _args()
    cfg = _common.load(args, runs_model=False)  # a bad value exits naming its key, before any work
    try:
        files = pseudo_records.records_files(args.input)
    except FileNotFoundError as e:
        sys.exit(f"prepare_self_supervision: {e}")
    print(f"preparing {len(files)} logs -> {args.out_dir}", flush=True)
    print(f"selfsup: {json.dumps(dataclasses.asdict(cfg.selfsup))}", flush=True)
    written_by = " ".join(["tools/prepare_self_supervision.py"] + sys.argv[1:])
    t0 = time.time()
    try:
        counts = self_supervision.run_preparation_job(files, args.out_dir, cfg, beam_args, written_by,
                                                      args.skip_bad_records)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"prepare_self_supervision: {e}")
    elapsed = time.time() - t0
    print(f"done in {elapsed:.1f} s ({counts.get('records', 0) / max(elapsed, 1e-9):.2f} records/s): {counts}")


if __name__ == "__main__":
    _common.run(main)
