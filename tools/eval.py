"""Evaluate a model on validation records; prints the paper's tables beside the zero-flow baseline.

python tools/eval.py --config C --data_dir VAL --checkpoint MODEL [--out_dir O]
    MODEL: a model_dir or checkpoint prefix, a SavedModel directory (tools/export.py), an .onnx file
    (tools/export_onnx.py) or a portable XLA export directory (tools/export_xla.py, batch 1): what the path holds
    chooses the runtime (ff3d_tf/inference/predictor.py).
python tools/eval.py --method nsfp --data_dir VAL --out_dir O [--sweep_period_s 0.1] [--set nsfp.KEY=VALUE]
    (no model: NSFP fitted to each pair, as tools/predict.py --method nsfp; any protocol)
python tools/eval.py --protocol av2 --set data.source=pair_records --data_dir AV2_VAL_RECORDS --checkpoint M
    [--masks val-masks.zip]
    (the Argoverse 2 2024 challenge: three-way and bucketed normalized EPE in metres per frame over the eval mask,
    35 m box, no ground; and the paper's tables in m/s on the same points. Records: tools/write_pair_records.py.
    --masks, Argoverse's official {val,test}-masks.zip: exactly its sweeps and the points its masks select, the
    points a leaderboard scores; a sweep of it without a record of as many points stops the tool naming both)
"""
import json
import os

import _common


def main():
    _common.start("inference")  # before TensorFlow is imported
    from ff3d_tf import metrics as M
    from ff3d_tf.data.pairs import list_segment_files, with_data_partner
    from ff3d_tf.inference.predictor import load_predictor
    from ff3d_tf.training.evaluation import evaluate, write_results
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", required=True)
    p.add_argument("--checkpoint", help="model_dir, checkpoint prefix, SavedModel directory, .onnx "
                                        "file or portable XLA export directory")
    p.add_argument("--method", choices=("model", "nsfp"), default="model", help="nsfp: no model, NSFP fitted to "
                   "each pair (ff3d_tf/labels/nsfp_predictor.py; the config's nsfp section; needs --out_dir)")
    p.add_argument("--sweep_period_s", type=float, default=0.1, help="--method nsfp: the pairs' gap (s)")
    p.add_argument("--out_dir", default=None, help="where metrics.json / metrics_zero_flow.json / metrics.csv go "
                                                   "(default: --checkpoint, or the folder of a prefix or file)")
    p.add_argument("--max_pairs", type=int, default=0)
    p.add_argument("--protocol", choices=("paper", "av2"), default="paper")
    p.add_argument("--masks", help="--protocol av2: the official {val,test}-masks.zip, whose points are scored")
    args = p.parse_args()
    if args.masks and args.protocol != "av2":
        p.error("--masks needs --protocol av2")
    if (args.method == "model") != bool(args.checkpoint) or (args.method == "nsfp" and not args.out_dir):
        p.error("--method model needs --checkpoint; --method nsfp takes no model and needs --out_dir")
    cfg = _common.load(args, runs_model=args.method == "model")
    files = list_segment_files(args.data_dir)
    # The order of the data's sweeps (data.partner: the records' manifest, WOD's previous), which the model must read.
    cfg = with_data_partner(cfg, files)
    if args.method == "nsfp":
        from ff3d_tf.labels import nsfp_predictor
        predictor = nsfp_predictor.predictor_from_config(cfg, args.sweep_period_s, lambda s: print(s, flush=True))
    else:
        predictor = load_predictor(cfg, args.checkpoint)
    import tensorflow as tf
    out_dir = args.out_dir or (args.checkpoint if tf.io.gfile.isdir(args.checkpoint) else
                               os.path.dirname(args.checkpoint))
    if args.protocol == "av2":
        return _av2(cfg, files, predictor, args.max_pairs, out_dir, args.masks)
    result, zero = evaluate(cfg, files, predictor, max_pairs=args.max_pairs,
                            log_fn=lambda s: print(s, flush=True))
    print(M.format_paper_table(result, "FastFlow3D (this checkpoint), mean L2 error"))
    print(M.format_extra_tables(result))
    print()
    print(M.format_paper_table(zero, "zero-flow baseline (for context)"))
    print(M.format_extra_tables(zero))
    write_results(out_dir, result, zero, cfg)
    print(f"wrote {out_dir}/metrics.json, metrics_zero_flow.json, metrics.csv")


def _av2(cfg, files, predictor, max_pairs, out_dir, masks):
    import tensorflow as tf
    from ff3d_tf import metrics as M
    from ff3d_tf import metrics_av2
    from ff3d_tf.training.evaluation import EVAL_CONFIG_NAME, evaluate_av2
    r = evaluate_av2(cfg, files, predictor, max_pairs=max_pairs, log_fn=lambda s: print(s, flush=True), masks=masks)
    print(f"points scored: {r['points']}")
    print(metrics_av2.format_challenge_table(r["model"], "FastFlow3D (this checkpoint)"))
    print()
    print(metrics_av2.format_challenge_table(r["zero_flow"], "zero flow"))
    print()
    print(M.format_paper_table(r["paper_model"], "FastFlow3D on the same points, paper classes, m/s"))
    print(M.format_paper_table(r["paper_zero_flow"], "zero flow on the same points, paper classes, m/s"))
    if r["points_without_prediction"]:
        print(f"{r['points_without_prediction']} eval-mask points lie outside the model's grid: scored with flow 0")
    tf.io.gfile.makedirs(out_dir)
    path = os.path.join(out_dir, "metrics_av2.json")
    with tf.io.gfile.GFile(path, "w") as f:
        json.dump(r, f, indent=1, sort_keys=True, default=float)
    cfg.save(os.path.join(out_dir, EVAL_CONFIG_NAME))  # the evaluation's own config, beside its results
    print(f"wrote {path} and {EVAL_CONFIG_NAME}")


if __name__ == "__main__":
    _common.run(main)
