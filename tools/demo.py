"""`make demo`: the main job end to end on the embedded synthetic default, everything under --out_dir.

generate train/val segments -> dataset statistics -> train (configs/synthetic_cpu.yaml) -> evaluate (model and zero-flow
baseline) -> export SavedModel -> predict with the SavedModel and write BEV PNGs. Each stage resumes/skips finished
work, so an interrupted demo continues where it stopped.
"""
import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def run(stage: str, args: list[str]) -> None:
    print(f"\n=== {stage}: {' '.join(args)}", flush=True)
    t = time.time()
    subprocess.run([sys.executable] + args, check=True)
    print(f"=== {stage} done in {time.time() - t:.0f} s", flush=True)


def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out_dir", default="demo_out")
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--train_segments", type=int, default=4)
    p.add_argument("--val_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=12)
    args = p.parse_args()
    out = args.out_dir
    t0 = time.time()
    tool = lambda name: os.path.join(HERE, name)  # noqa: E731
    run("generate train", [tool("make_synthetic_data.py"), "--out_dir", f"{out}/data/train", "--num_segments",
                           str(args.train_segments), "--frames_per_segment", str(args.frames_per_segment),
                           "--seed", "100"])
    run("generate validation", [tool("make_synthetic_data.py"), "--out_dir", f"{out}/data/val", "--num_segments",
                                str(args.val_segments), "--frames_per_segment", str(args.frames_per_segment),
                                "--seed", "900"])
    run("dataset statistics", [tool("dataset_stats.py"), "--data_dir", f"{out}/data/train", "--out_dir",
                               f"{out}/stats"])
    run("train", [tool("train.py"), "--config", args.config, "--data_dir", f"{out}/data/train", "--val_dir",
                  f"{out}/data/val", "--model_dir", f"{out}/model"])
    run("evaluate", [tool("eval.py"), "--config", args.config, "--data_dir", f"{out}/data/val", "--checkpoint",
                     f"{out}/model", "--out_dir", out])
    run("export", [tool("export.py"), "--config", args.config, "--checkpoint", f"{out}/model", "--out",
                   f"{out}/saved_model"])
    val_files = sorted(os.listdir(f"{out}/data/val"))
    run("predict", [tool("predict.py"), "--config", args.config, "--checkpoint", f"{out}/saved_model", "--input",
                    f"{out}/data/val/{val_files[0]}", "--out_dir", f"{out}/predictions", "--png_every", "5"])
    with open(f"{out}/metrics.json") as f:
        m = json.load(f)
    with open(f"{out}/metrics_zero_flow.json") as f:
        z = json.load(f)
    print(f"\ndemo finished in {time.time() - t0:.0f} s")
    print(f"all/moving/mean_l2_mps: model {m['all/moving/mean_l2_mps']:.3f} vs zero flow "
          f"{z['all/moving/mean_l2_mps']:.3f} (ratio {m['all/moving/mean_l2_mps'] / z['all/moving/mean_l2_mps']:.2f})")
    print(f"all/stationary/mean_l2_mps: model {m['all/stationary/mean_l2_mps']:.3f}")
    print(f"outputs under {out}/: metrics.json, metrics_zero_flow.json, metrics.csv, saved_model/, predictions/*.png, "
          f"stats/*.png")


if __name__ == "__main__":
    main()
