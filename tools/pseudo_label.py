"""NSFP pseudo-labels for pair records (ZeroFlow's label job), as an Apache Beam job.

python tools/pseudo_label.py --input RECORDS --out_dir PSEUDO [--config C.yaml] [--set nsfp.KEY=VALUE ...]
    [--skip_bad_records] [beam options]
The job's options are the config's `nsfp` section (`ff3d_tf.config.NsfpConfig` documents each key): the fit, e.g.
--set nsfp.max_iterations=1000 --set nsfp.fit_every=8 --set nsfp.crop_xy_half_extent_m=null (no crop), and what the
job does around it, e.g. --set nsfp.ground=height --set nsfp.on_bad_fit=stop. Defaults: the job's fit
(`nsfp.MEASURED_FIT_OPTIONS`): NSFP's two-sided Chamfer on every 4th point, the region the Argoverse 2 challenge
scores (|x|, |y| <= 35 m) and z in [-3, 3] m, ground removed from both clouds (the records' map masks for Argoverse 2
records, else a local height rule). Points outside the fitted region get no pseudo-label (`pseudo_valid_t0` False).
NSFP's published fit: --set nsfp.learning_rate=0.008 --set nsfp.weight_decay=1e-4 --set nsfp.reverse_every=1
--set nsfp.min_delta=1e-4 --set nsfp.fit_every=1. A bad value stops the tool naming its key, before any work.
RECORDS: `tools/write_pair_records.py` output (WOD or Argoverse 2; raw LiDAR with --no_labels works too). PSEUDO then
trains with `--set data.source=pair_records --set data.labels=pseudo`; it holds the resolved config
(PSEUDO/config.yaml; a rerun into PSEUDO with another nsfp section stops). Resumable per pair; a bad record stops the
job naming file, record and field, or with --skip_bad_records is skipped and counted; a fit that stays implausible is
named in the report and its pair written without pseudo-labels (nsfp.on_bad_fit=stop: the job stops). On Argoverse 2
records the pseudo-labels are scored against Argoverse's labels (PSEUDO/pseudo_label_scores.json).
"""
import dataclasses
import json
import sys
import time

import _common

from ff3d_tf.config import NsfpConfig


def _args():
    p = _common.parser(__doc__)
    p.add_argument("--input", required=True, help="directory of pair records")
    p.add_argument("--out_dir", required=True)
    p.add_argument("--skip_bad_records", action="store_true", help="skip and count records that do not parse")
    args, beam_args = p.parse_known_args()
    # Unknown flags go to Beam, which drops the ones it does not know: a job option given as a flag would be lost.
    keys = {f.name for f in dataclasses.fields(NsfpConfig)}
    for arg in beam_args:
        name = arg[2:].split("=", 1)[0] if arg.startswith("--") else ""
        if name in keys:
            p.error(f"{arg}: the job's options are config keys: --set nsfp.{name}=VALUE")
    return args, beam_args


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.labels import pseudo_records
    args, beam_args = _args()
    cfg = _common.load(args, runs_model=False)  # a bad value exits naming its key, before any work; no model runs
    try:
        files = pseudo_records.records_files(args.input)
    except FileNotFoundError as e:
        sys.exit(f"pseudo_label: {e}")
    print(f"pseudo-labelling {len(files)} records files -> {args.out_dir}", flush=True)
    print(f"nsfp: {json.dumps(dataclasses.asdict(cfg.nsfp))}", flush=True)
    written_by = " ".join(["tools/pseudo_label.py"] + sys.argv[1:])
    t0 = time.time()
    try:
        counts = pseudo_records.run_pseudo_label_job(files, args.out_dir, cfg, beam_args, written_by,
                                                     args.skip_bad_records)
    except (pseudo_records.BadFitError, ValueError, FileNotFoundError) as e:
        sys.exit(f"pseudo_label: {e}")
    el = time.time() - t0
    scores = counts.pop("scores", None)
    print(f"done in {el:.1f} s ({counts.get('fitted_pairs', 0) / max(el, 1e-9):.3f} pairs/s): {counts}")
    if scores:
        print("against the records' human labels (Argoverse 2 challenge arithmetic, m): pseudo-labels three-way EPE "
              f"{scores['nsfp']['three_way/mean_epe_m']:.4f}, bucketed normalized dynamic "
              f"{scores['nsfp']['bucketed/mean_dynamic_norm_epe']:.3f}; zero flow "
              f"{scores['zero_flow']['three_way/mean_epe_m']:.4f}, "
              f"{scores['zero_flow']['bucketed/mean_dynamic_norm_epe']:.3f} "
              f"({args.out_dir}/{pseudo_records.SCORES_NAME})")


if __name__ == "__main__":
    _common.run(main)
