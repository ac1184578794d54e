"""Write an Argoverse 2 scene-flow submission in a leaderboard's layout, over the official masks, and check it.

python tools/av2_submission.py --leaderboard v1|v2|v3 --split test --masks test-masks.zip --checkpoint M
    --data_dir AV2_RECORDS --out submission.zip [--format_json test_submission_format.json] [--config C] [--set ...]
AV2_RECORDS: `tools/write_pair_records.py --source av2 --input <split> --out_dir AV2_RECORDS` (each sweep paired with
the next one; the test split's logs have no annotations: add --no_labels, which keeps every point in the same
order). --masks: Argoverse's official `{val,test}-masks.zip` (`<log_id>/<timestamp_ns>.feather`, one boolean
column over every point of the sweep), from s3://argoverse/tasks/3d_scene_flow/zips/: it chooses the sweeps (v1, v3)
and v1's rows; a sweep of it without a record, or with another point count, stops the tool naming both. Without it a
test split is refused; a val split falls back to av2-api's rule (every 5th pair; |x|, |y| <= 50 m, not ground), for
local validation only. The layouts (`ff3d_tf.data.av2.av2_submission.LAYOUTS`, docs/datasets.md):
  v1  av2-api (2023): <log_id>/<timestamp_ns>.feather, flow_tx_m, flow_ty_m, flow_tz_m float16 with the ego motion,
      is_dynamic bool, one row per mask point
  v2  bucketed_scene_flow_eval (2024): metadata.json and <log_id>/<sweep index:010d>.feather for sweep indices
      0, 5, 10, ... of each log, is_valid and the ego-motion-free flow (float16) of every point
  v3  the 2026 leaderboard (OpenSceneFlow's writer): the masks' sweeps, the ego-motion-free flow (float16) of every
      point, nothing else
The archive is read back and checked (and against --format_json, av2-api's `{val,test}_submission_format.json`:
entries and, for v1, row counts) before the tool says done. The sweeps are written under <out>.parts/ with the
fingerprint of what writes them (the model's files, the config, the records, the layout and the masks): an
interrupted run resumes there, a folder left by a run of anything else stops the tool naming what differs, and the
folder is removed once the archive is checked. The model must read the records' order (their next sweep as partner:
a model of several sweeps trained on other data is refused). `--ground_truth` writes the records' own labels instead
of a model's flow (a check of the pipeline: it scores ~0, float16 rounding).
"""
import sys

import _common

import numpy as np


class _LabelsAsPrediction:
    """A predictor whose flow is the example's own label (`--ground_truth`)."""

    def predict(self, batch, example):
        flow = np.asarray(example["flow_mps_t0"])
        return flow, np.ones(len(flow), bool)


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf.data.av2 import av2_submission
    from ff3d_tf.data import pair_records
    from ff3d_tf.data.pairs import list_segment_files, with_data_partner
    from ff3d_tf.training.evaluation import write_av2_submission
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", required=True, help="Argoverse 2 pair records of the split")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="model_dir, checkpoint prefix, SavedModel directory, .onnx file or "
                                          "portable XLA export directory")
    src.add_argument("--ground_truth", action="store_true", help="submit the records' labels (pipeline check)")
    p.add_argument("--leaderboard", required=True, choices=sorted(av2_submission.LAYOUTS),
                   help="v1: av2-api 2023; v2: bucketed_scene_flow_eval 2024; v3: the 2026 leaderboard")
    p.add_argument("--split", required=True, choices=("val", "test"))
    p.add_argument("--masks", help="the official {val,test}-masks.zip (required for test)")
    p.add_argument("--format_json", help="av2-api's {val,test}_submission_format.json, checked against (v1, v3)")
    p.add_argument("--self_supervised", action="store_true", help="v2's metadata.json: the model trained without "
                                                                  "human labels")
    p.add_argument("--out", required=True, help="the submission .zip")
    p.add_argument("--max_pairs", type=int, default=0, help="the first N sweeps only: a partial archive (a check)")
    args = p.parse_args()
    cfg = _common.load(args, runs_model=not args.ground_truth)
    from ff3d_tf.config import ConfigError, replace_config
    cfg = replace_config(cfg, {"data.source": "pair_records"})
    files = list_segment_files(args.data_dir)
    cfg = with_data_partner(cfg, files)  # the records' order (data.partner), which the model must read
    if args.ground_truth:
        manifest = pair_records.manifest_of_files(files)
        if not manifest.human_labels:
            raise ConfigError(f"{args.data_dir}: --ground_truth submits the records' labels, but these records hold "
                              "none (written with --no_labels, e.g. the test split): give --checkpoint")
        predictor, model = _LabelsAsPrediction(), {"kind": "ground_truth"}
    else:
        from ff3d_tf.inference.predictor import load_predictor, model_fingerprint
        predictor, model = load_predictor(cfg, args.checkpoint), model_fingerprint(args.checkpoint)
    summary = write_av2_submission(cfg, files, predictor, args.out, args.leaderboard,
                                   args.split, masks=args.masks, format_json=args.format_json,
                                   max_pairs=args.max_pairs, supervised=not args.self_supervised,
                                   log_fn=lambda s: print(s, flush=True), model=model)
    for note in summary["notes"]:
        print(note, file=sys.stderr)
    print(f"done: {args.out} holds {summary['sweeps']} sweeps of {summary['logs']} logs, {summary['rows']} rows, "
          f"layout {summary['leaderboard']} ({summary['selection']}), checked against the layout"
          + (" and " + args.format_json if args.format_json else ""))


if __name__ == "__main__":
    _common.run(main)
