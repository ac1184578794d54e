"""Every sweep's ground mask for pair records (`data.drop_ground`), as an Apache Beam job.

python tools/add_ground_masks.py --data_dir RECORDS --out_dir GROUND [--config C.yaml] [--set k=v ...]
    [--skip_bad_records] [beam options]
Writes RECORDS again into GROUND with `is_ground_t0`, `is_ground_tm1`, `is_ground_tm2`, ... (one per sweep of the
records, `ff3d_tf.schema.ground_keys`) beside everything they held (`ff3d_tf.labels.ground_records`): a sweep's mask
is the records' own where their manifest lists it (Argoverse 2's map raster, kept bit for bit), else the local
height rule of `ff3d_tf.labels.ground` on that sweep's points. Records that already hold every sweep's mask are
copied unchanged (said in the log and the summary: `masks_computed` 0). RECORDS: `tools/write_pair_records.py` output
of any source (WOD, Argoverse 2, your own sequences, synthetic; raw LiDAR with --no_labels works too), of any number
of sweeps (the records' manifest says how many); --input is the same flag as --data_dir. GROUND then trains with
`--set data.source=pair_records --set data.drop_ground=true`. The job has no options of its own: --config and --set
are read as by every tool (a bad value stops it before any work). Resumable per pair (a finished file is skipped); a
record that does not parse stops its file naming file, record and field (the other files are written), or with
--skip_bad_records is skipped and counted.
"""
import sys
import time

import _common


def _args():
    p = _common.parser(__doc__)
    p.add_argument("--data_dir", "--input", dest="data_dir", required=True, help="directory of pair records")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--skip_bad_records", action="store_true", help="skip and count records that do not parse")
    return p.parse_known_args()


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.labels import ground_records, pseudo_records
    args, beam_args = _args()
    _common.load(args, runs_model=False)  # a bad value exits naming its key, before any work; no model runs
    try:
        files = pseudo_records.records_files(args.data_dir)
    except FileNotFoundError as e:
        sys.exit(f"add_ground_masks: {e}")
    print(f"adding every sweep's ground mask to {len(files)} records files -> {args.out_dir}", flush=True)
    written_by = " ".join(["tools/add_ground_masks.py"] + sys.argv[1:])
    t0 = time.time()
    try:
        counts = ground_records.run_ground_job(files, args.out_dir, beam_args, written_by, args.skip_bad_records)
    except (ValueError, FileNotFoundError) as e:
        sys.exit(f"add_ground_masks: {e}")
    elapsed = time.time() - t0
    kept, added = counts.pop("ground_keys_kept"), counts.pop("ground_keys_added")
    print(f"done in {elapsed:.1f} s ({counts.get('pairs', 0) / max(elapsed, 1e-9):.1f} pairs/s): {counts}")
    print(f"ground masks kept from the records: {', '.join(kept) or 'none'}; added by the height rule: "
          f"{', '.join(added) or 'none (the output is a copy)'}")
    computed, ground = counts.get("points_computed", 0), counts.get("ground_points_computed", 0)
    if computed:
        print(f"the height rule found {ground} of {computed} points ground ({ground / computed:.1%})")


if __name__ == "__main__":
    _common.run(main)
