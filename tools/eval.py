"""Evaluate a checkpoint or SavedModel on validation records; prints the paper's tables beside the zero-flow baseline.

python tools/eval.py --config C --data_dir VAL --checkpoint MODEL_DIR_OR_SAVED_MODEL [--out_dir O]
"""
import os

import _common

from ff3d_tf import metrics as M
from ff3d_tf.data.pairs import list_segment_files
from ff3d_tf.inference.predictor import load_predictor
from ff3d_tf.training.evaluation import evaluate, write_results


def main():
    p = _common.parser(__doc__, "configs/fastflow3d_waymo.yaml")
    p.add_argument("--data_dir", required=True)
    p.add_argument("--checkpoint", required=True, help="model_dir, checkpoint prefix, or SavedModel directory")
    p.add_argument("--out_dir", default=None, help="where metrics.json / metrics_zero_flow.json / metrics.csv go")
    p.add_argument("--max_pairs", type=int, default=0)
    args = p.parse_args()
    cfg = _common.load(args)
    files = list_segment_files(args.data_dir)
    predictor = load_predictor(cfg, args.checkpoint)
    result, zero = evaluate(cfg, files, predictor, max_pairs=args.max_pairs,
                            log_fn=lambda s: print(s, flush=True))
    print(M.format_paper_table(result, "FastFlow3D (this checkpoint), mean L2 error"))
    print(M.format_extra_tables(result))
    print()
    print(M.format_paper_table(zero, "zero-flow baseline (for context)"))
    print(M.format_extra_tables(zero))
    import tensorflow as tf
    out_dir = args.out_dir or (args.checkpoint if tf.io.gfile.isdir(args.checkpoint) else
                               os.path.dirname(args.checkpoint))
    write_results(out_dir, result, zero, cfg)
    print(f"wrote {out_dir}/metrics.json, metrics_zero_flow.json, metrics.csv")


if __name__ == "__main__":
    _common.run(main)
