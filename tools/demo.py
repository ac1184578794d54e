"""`make demo`: the main job end to end on the embedded synthetic default, everything under --out_dir.

generate train/val segments -> dataset statistics -> train (configs/synthetic_cpu.yaml) -> evaluate (model and zero-flow
baseline) -> export SavedModel -> predict with the SavedModel and write BEV PNGs. `--model gru` (`make demo
MODEL=gru`) trains DeFlow's GRU head instead of the paper's (`--set model.head=gru` on the same config).

Resumable (`ff3d_tf.stages`): a finished stage leaves a record `OUT/stages/<stage>.json` of its command, a hash of
the project's code and configs, and the outputs it wrote (sizes); a rerun skips every stage whose record matches the
command and the code and whose outputs are all still there, and reruns the others. A stage whose command or code
changed starts again from nothing (its outputs removed first). An interrupted stage resumes its own way: segments
already generated are skipped, training resumes from its newest intact checkpoint, the SavedModel is written to
`saved_model.partial` and renamed when complete. So a demo interrupted at any stage continues where it stopped: run
the same command again.

At the end `OUT/demo_summary.json` holds the CPU (and any ISA caps, `make demo EMULATE_CPU=zen3`), each stage's
seconds, the whole run's, and the model's error on moving points against zero flow (docs/benchmarks.md quotes one).
"""
import argparse
import json
import os
import shutil
import sys
import time

import _common

from ff3d_tf import cpu
from ff3d_tf.json_io import write_json
from ff3d_tf.stages import StageError, Stages

HERE = os.path.dirname(os.path.abspath(__file__))
PLAN = ("generate train", "generate val", "dataset statistics", "train", "evaluate", "export", "predict")


def _tool(name: str) -> str:
    return os.path.join(HERE, name)


def _replace_dir(src: str, dst: str) -> None:
    if os.path.isdir(dst):
        shutil.rmtree(dst)  # an older export (its stage record no longer matched)
    os.replace(src, dst)


# --model: the per-point head the demo trains (model.head): the paper's, or DeFlow's GRU decoder on the same config.
MODEL_OVERRIDES = {"paper": [], "gru": ["model.head=gru"]}


def _run_stages(args, stages: Stages) -> None:
    out = args.out_dir
    config = ["--config", args.config] + [a for s in MODEL_OVERRIDES[args.model] + args.set for a in ("--set", s)]
    for split, count, seed in (("train", args.train_segments, 100), ("val", args.val_segments, 900)):
        stages.run(f"generate {split}", [_tool("make_synthetic_data.py"), "--out_dir", f"{out}/data/{split}",
                                         "--num_segments", str(count), "--frames_per_segment",
                                         str(args.frames_per_segment), "--seed", str(seed), "--lidar_scale",
                                         str(args.lidar_scale)], [f"{out}/data/{split}"])
    stages.run("dataset statistics", [_tool("dataset_stats.py"), "--data_dir", f"{out}/data/train", "--out_dir",
                                      f"{out}/stats"], [f"{out}/stats"])
    stages.run("train", [_tool("train.py"), *config, "--data_dir", f"{out}/data/train", "--val_dir",
                         f"{out}/data/val", "--model_dir", f"{out}/model"], [f"{out}/model"])
    stages.run("evaluate", [_tool("eval.py"), *config, "--data_dir", f"{out}/data/val", "--checkpoint",
                            f"{out}/model", "--out_dir", out],
               [f"{out}/metrics.json", f"{out}/metrics_zero_flow.json", f"{out}/metrics.csv"])
    partial = f"{out}/saved_model.partial"
    if os.path.isdir(partial):
        shutil.rmtree(partial)  # an export cut short: written again from the start
    stages.run("export", [_tool("export.py"), *config, "--checkpoint", f"{out}/model", "--out", partial],
               [f"{out}/saved_model"], after=lambda: _replace_dir(partial, f"{out}/saved_model"))
    val_files = sorted(f for f in os.listdir(f"{out}/data/val") if f.endswith(".tfrecord"))
    stages.run("predict", [_tool("predict.py"), *config, "--checkpoint", f"{out}/saved_model", "--input",
                           f"{out}/data/val/{val_files[0]}", "--out_dir", f"{out}/predictions", "--png_every", "5"],
               [f"{out}/predictions"])


def main():
    _common.start("inference")  # before TensorFlow is imported
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out_dir", default="demo_out")
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--model", choices=sorted(MODEL_OVERRIDES), default="paper",
                   help="the per-point head: paper (the paper's rows W-Z) or gru (DeFlow's GRU decoder: "
                   "--set model.head=gru)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for training, evaluation, export and prediction (repeatable)")
    p.add_argument("--train_segments", type=int, default=4)
    p.add_argument("--val_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=12)
    p.add_argument("--lidar_scale", type=float, default=0.5,
                   help="the synthetic lidars' resolution: range images of this fraction of WOD's rows and columns "
                        "(1: WOD's own; the default keeps the demo within minutes on 2 cores, docs/benchmarks.md)")
    args = p.parse_args()
    out = args.out_dir
    t0 = time.time()
    stages = Stages(f"{out}/stages", PLAN)
    try:
        _run_stages(args, stages)
    except StageError as e:
        sys.exit(f"demo: {e}")
    seconds = time.time() - t0
    with open(f"{out}/metrics.json") as f:
        m = json.load(f)
    with open(f"{out}/metrics_zero_flow.json") as f:
        z = json.load(f)
    moving, moving_zero = m["all/moving/mean_l2_mps"], z["all/moving/mean_l2_mps"]
    ratio = moving / moving_zero if moving_zero else float("nan")
    write_json(f"{out}/demo_summary.json", {
        "cpu": cpu.describe(), "model": args.model, "config": args.config, "set": args.set,
        "seconds": seconds, "stage_seconds": stages.seconds, "skipped": stages.skipped,
        "moving_mean_l2_mps": moving, "zero_flow_moving_mean_l2_mps": moving_zero, "moving_over_zero_flow": ratio,
        "stationary_mean_l2_mps": m["all/stationary/mean_l2_mps"]})
    print(f"\ndemo finished in {seconds:.0f} s")
    print(f"all/moving/mean_l2_mps: model {moving:.3f} vs zero flow {moving_zero:.3f} (ratio {ratio:.2f})")
    print(f"all/stationary/mean_l2_mps: model {m['all/stationary/mean_l2_mps']:.3f}")
    print(f"outputs under {out}/: metrics.json, metrics_zero_flow.json, metrics.csv, saved_model/, predictions/*.png, "
          f"stats/*.png, demo_summary.json")


if __name__ == "__main__":
    main()
