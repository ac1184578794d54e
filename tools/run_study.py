"""Run one of the paper's studies: train and evaluate every variant, then write the table and the plot.

python tools/run_study.py --study point_density --config configs/synthetic_cpu.yaml --train_dir D --val_dir V \
    --out_dir studies/ [--values 0.1,0.5,1] [--set train.num_steps=400 ...]

Studies (ff3d_tf/training/studies.py): data_size, point_density, ground_removal, class_ablation, ego_motion. Each variant trains
in <out_dir>/<study>/<variant>/model (resumes) and is evaluated into .../eval (kept once written: delete it to
re-evaluate); every config is checked before any work starts. Writes <out_dir>/<study>/<study>.{json,md,png}.
"""
import json
import os
import subprocess
import sys
import time

import _common

from ff3d_tf.training import studies
from ff3d_tf.config import ConfigError, load_config

HERE = os.path.dirname(os.path.abspath(__file__))


def _sets(changes: dict) -> list[str]:
    return [f"{k}={json.dumps(v)}" for k, v in changes.items()]  # JSON values are valid YAML


def _run(args: list[str]) -> None:
    subprocess.run([sys.executable] + args, check=True)


def main():
    _common.start("train")  # before TensorFlow is imported
    from ff3d_tf.data.pairs import list_segment_files
    p = _common.parser(__doc__, "configs/synthetic_cpu.yaml")
    p.add_argument("--study", required=True, choices=sorted(studies.STUDIES))
    p.add_argument("--train_dir", required=True)
    p.add_argument("--val_dir", required=True)
    p.add_argument("--out_dir", required=True)
    p.add_argument("--values", default="", help="shares of the numeric studies, e.g. 0.1,0.25,1")
    p.add_argument("--max_eval_pairs", type=int, default=0, help="0 = every validation pair")
    args = p.parse_args()
    _common.load(args)  # the base config must be valid
    try:
        train_files = list_segment_files(args.train_dir)
        list_segment_files(args.val_dir)  # the evaluations' data is there before any variant trains
        values = tuple(float(v) for v in args.values.split(",") if v.strip())
        variants = studies.variants(args.study, len(train_files), values)
        for v in variants:  # every variant's training and evaluation config, before any work
            load_config(args.config, args.set + _sets(v.training_changes()))
            load_config(args.config, args.set + _sets(v.input_changes))
    except (ValueError, ConfigError, FileNotFoundError) as e:
        sys.exit(f"study error: {e}")
    study_dir = os.path.join(args.out_dir, args.study)
    print(f"study {args.study}: {len(variants)} variants ({', '.join(v.name for v in variants)}) -> {study_dir}",
          flush=True)
    rows, t0 = [], time.time()
    for i, v in enumerate(variants):
        vdir = os.path.join(study_dir, v.name)
        print(f"\n=== [{i + 1}/{len(variants)}] {v.name}: {v.training_changes() or 'base config'}", flush=True)
        _run([os.path.join(HERE, "train.py"), "--config", args.config, "--data_dir", args.train_dir,
              "--model_dir", os.path.join(vdir, "model")] + [a for s in args.set + _sets(v.training_changes())
                                                             for a in ("--set", s)])
        metrics_path = os.path.join(vdir, "eval", "metrics.json")
        if not os.path.exists(metrics_path):
            _run([os.path.join(HERE, "eval.py"), "--config", args.config, "--data_dir", args.val_dir, "--checkpoint",
                  os.path.join(vdir, "model"), "--out_dir", os.path.join(vdir, "eval"),
                  "--max_pairs", str(args.max_eval_pairs)] + [a for s in args.set + _sets(v.input_changes)
                                                             for a in ("--set", s)])
        with open(metrics_path) as f:
            rows.append({"variant": v.name, "x": v.x, "changes": v.training_changes(), "metrics": json.load(f)})
        elapsed = time.time() - t0
        print(f"=== {v.name} done; {elapsed:.0f} s so far, ETA {elapsed / (i + 1) * (len(variants) - i - 1):.0f} s",
              flush=True)
    paths = studies.write_report(args.study, rows, study_dir)
    print("\n" + studies.markdown_table(args.study, rows))
    print(f"\nwrote {paths['json']}, {paths['markdown']}, {paths['png']}")


if __name__ == "__main__":
    main()
