"""Write an Argoverse 2 scene-flow challenge submission (av2-api SUBMISSION_FORMAT.md) for a split, and check it.

python tools/av2_submission.py --checkpoint M --data_dir AV2_RECORDS --out submission.zip [--config C] [--set ...]
AV2_RECORDS: `tools/write_pair_records.py --source av2 --input <split> --out_dir AV2_RECORDS` (each sweep paired with
the next one). One folder per log, one `<timestamp_ns>.feather` per evaluated sweep with flow_tx_m, flow_ty_m,
flow_tz_m (float16, metres to the next sweep, ego motion included, first sweep's ego frame) and is_dynamic (bool),
one row per eval-mask point (not ground, max(|x|, |y|) < 35 m) in point order; zipped, then the archive is read back
and checked against the format and the expected row counts before the tool says done. Sweeps already written under
<out>.parts/ are kept, so an interrupted run resumes. `--ground_truth` writes the records' own labels instead of a
model's flow (a check of the pipeline: it scores ~0).
"""
import os
import sys
import time

import _common

import numpy as np

from ff3d_tf import geometry, metrics_av2
from ff3d_tf.data import pair_records
from ff3d_tf.data.av2 import av2_submission
from ff3d_tf.data.pairs import list_segment_files
from ff3d_tf.training.evaluation import av2_challenge_examples, challenge_flow_m


class _LabelsAsPrediction:
    """A predictor whose flow is the example's own label (`--ground_truth`)."""

    def predict(self, batch, example):
        flow = np.asarray(example["flow_mps_t0"])
        return flow, np.ones(len(flow), bool)


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", required=True, help="Argoverse 2 pair records of the split")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="model_dir, checkpoint prefix, SavedModel directory, .onnx file or "
                                          "portable XLA export directory")
    src.add_argument("--ground_truth", action="store_true", help="submit the records' labels (pipeline check)")
    p.add_argument("--out", required=True, help="the submission .zip")
    p.add_argument("--max_pairs", type=int, default=0)
    args = p.parse_args()
    cfg = _common.load(args)
    from ff3d_tf.config import replace_config
    cfg = replace_config(cfg, {"data.source": "pair_records"})
    files = list_segment_files(args.data_dir)
    if args.ground_truth:
        predictor = _LabelsAsPrediction()
    else:
        from ff3d_tf.inference.predictor import load_predictor
        predictor = load_predictor(cfg, args.checkpoint)
    parts = args.out + ".parts"
    expected, t0 = {}, time.time()
    for ex, flow_pred, _, mask in av2_challenge_examples(cfg, files, predictor, args.max_pairs,
                                                         log_fn=lambda s: print(s, flush=True)):
        log_id = ex[pair_records.SEQUENCE_KEY].decode()
        timestamp_ns = int(ex[pair_records.TIMESTAMP_KEY])
        expected[(log_id, timestamp_ns)] = int(mask.sum())
        path = os.path.join(parts, *av2_submission.sweep_entry(log_id, timestamp_ns).split("/"))
        if os.path.exists(path):
            continue  # written by an interrupted run
        flow_m = challenge_flow_m(flow_pred, ex)  # ego-free, metres to the next sweep, sweep-t frame
        ego1_from_ego0 = geometry.t0_from_tm1_np(ex["pose_tm1"], ex["pose_t0"])  # sweep t -> next sweep's frame
        flow_av2 = av2_submission.av2_flow_from_ego_free(ex["points_xyz_t0"], flow_m, ego1_from_ego0)
        av2_submission.write_sweep(parts, log_id, timestamp_ns, flow_av2[mask], metrics_av2.is_dynamic(flow_m)[mask])
    print(f"{len(expected)} sweeps predicted in {time.time() - t0:.0f} s; zipping and checking {args.out}",
          flush=True)
    summary = av2_submission.make_archive(parts, args.out, expected)
    print(f"done: {args.out} holds {summary['sweeps']} sweeps of {summary['logs']} logs, {summary['rows']} rows, "
          "checked against the submission format")


if __name__ == "__main__":
    try:
        _common.run(main)
    except av2_submission.SubmissionFormatError as e:
        sys.exit(f"error: {e}")
