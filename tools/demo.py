"""`make demo`: the main job end to end on the embedded synthetic default, everything under --out_dir.

generate train/val segments -> dataset statistics -> train (configs/synthetic_cpu.yaml) -> evaluate (model and zero-flow
baseline) -> export SavedModel -> predict with the SavedModel and write BEV PNGs.

Resumable: a finished stage leaves a record `OUT/stages/<stage>.json` (written atomically) of its command and of the
outputs it wrote (sizes); a rerun skips every stage whose record matches the command and whose outputs are all still
there, and reruns the others. An interrupted stage resumes its own way: segments already generated are skipped,
training resumes from its newest intact checkpoint, the SavedModel is written to `saved_model.partial` and renamed
when complete. So a demo interrupted at any stage continues where it stopped: run the same command again.
"""
import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def _tool(name: str) -> str:
    return os.path.join(HERE, name)


def _listing(path: str) -> dict:
    """{relative file: size} of a file or of every file under a folder (what a stage's record holds)."""
    if os.path.isfile(path):
        return {"": os.path.getsize(path)}
    found = {}
    for root, _, files in os.walk(path):
        for name in files:
            full = os.path.join(root, name)
            found[os.path.relpath(full, path)] = os.path.getsize(full)
    return found


def _replace_dir(src: str, dst: str) -> None:
    if os.path.isdir(dst):
        shutil.rmtree(dst)  # an older export (its stage record no longer matched)
    os.replace(src, dst)


class Stages:
    """Runs the demo's stages as subprocesses; skips those whose record says they are complete."""

    def __init__(self, out_dir: str):
        self.record_dir = os.path.join(out_dir, "stages")
        self.ran = False  # once a stage runs, every later one runs too (its inputs may have changed)

    def _record_path(self, stage: str) -> str:
        return os.path.join(self.record_dir, stage.replace(" ", "_") + ".json")

    def complete(self, stage: str, command: list[str]) -> bool:
        try:
            with open(self._record_path(stage)) as f:
                record = json.load(f)
        except (OSError, ValueError):  # no record, or one cut short: the stage is not known to be complete
            return False
        return record.get("command") == command[1:] and all(
            os.path.exists(path) and _listing(path) == listing for path, listing in record["outputs"].items())

    def _write_record(self, stage: str, command: list[str], outputs: list[str]) -> None:
        os.makedirs(self.record_dir, exist_ok=True)
        path = self._record_path(stage)
        with open(path + ".partial", "w") as f:
            json.dump({"command": command[1:], "outputs": {p: _listing(p) for p in outputs}}, f, indent=1)
        os.replace(path + ".partial", path)  # a record is whole or absent

    def run(self, stage: str, args: list[str], outputs: list[str], after=None) -> None:
        """Runs `args` (a tool and its flags) unless complete; `after()` finishes the outputs (e.g. a rename)."""
        command = [sys.executable] + args
        if not self.ran and self.complete(stage, command):
            print(f"=== {stage}: complete ({', '.join(outputs)}), skipped", flush=True)
            return
        self.ran = True
        print(f"\n=== {stage}: {' '.join(args)}", flush=True)
        t = time.time()
        proc = subprocess.Popen(command)
        # Ctrl-C reaches the whole process group: the stage handles it (training writes a checkpoint) and this
        # process waits for it instead of killing it mid-write.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            returncode = proc.wait()
        finally:
            signal.signal(signal.SIGINT, previous)
        if returncode != 0:
            sys.exit(f"demo: stage {stage} stopped (exit status {returncode}); run the same command again to resume")
        if after is not None:
            after()
        missing = [p for p in outputs if not os.path.exists(p)]
        if missing:
            raise RuntimeError(f"stage {stage} finished without writing {missing}")
        self._write_record(stage, command, outputs)
        print(f"=== {stage} done in {time.time() - t:.0f} s", flush=True)


def main():
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out_dir", default="demo_out")
    p.add_argument("--config", default="configs/synthetic_cpu.yaml")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="config override for training, evaluation, export and prediction (repeatable)")
    p.add_argument("--train_segments", type=int, default=4)
    p.add_argument("--val_segments", type=int, default=2)
    p.add_argument("--frames_per_segment", type=int, default=12)
    p.add_argument("--lidar_scale", type=float, default=1.0, help="< 1 shrinks the range images (tests)")
    args = p.parse_args()
    out = args.out_dir
    t0 = time.time()
    stages = Stages(out)
    config = ["--config", args.config] + [a for s in args.set for a in ("--set", s)]

    def generate(split, count, seed):
        stages.run(f"generate {split}", [_tool("make_synthetic_data.py"), "--out_dir", f"{out}/data/{split}",
                                         "--num_segments", str(count), "--frames_per_segment",
                                         str(args.frames_per_segment), "--seed", str(seed), "--lidar_scale",
                                         str(args.lidar_scale)], [f"{out}/data/{split}"])

    generate("train", args.train_segments, 100)
    generate("val", args.val_segments, 900)
    stages.run("dataset statistics", [_tool("dataset_stats.py"), "--data_dir", f"{out}/data/train", "--out_dir",
                                      f"{out}/stats"], [f"{out}/stats/dataset_stats.json"])
    stages.run("train", [_tool("train.py"), *config, "--data_dir", f"{out}/data/train", "--val_dir",
                         f"{out}/data/val", "--model_dir", f"{out}/model"], [f"{out}/model/train_history.json"])
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
    with open(f"{out}/metrics.json") as f:
        m = json.load(f)
    with open(f"{out}/metrics_zero_flow.json") as f:
        z = json.load(f)
    print(f"\ndemo finished in {time.time() - t0:.0f} s")
    ratio = m["all/moving/mean_l2_mps"] / z["all/moving/mean_l2_mps"] if z["all/moving/mean_l2_mps"] else float("nan")
    print(f"all/moving/mean_l2_mps: model {m['all/moving/mean_l2_mps']:.3f} vs zero flow "
          f"{z['all/moving/mean_l2_mps']:.3f} (ratio {ratio:.2f})")
    print(f"all/stationary/mean_l2_mps: model {m['all/stationary/mean_l2_mps']:.3f}")
    print(f"outputs under {out}/: metrics.json, metrics_zero_flow.json, metrics.csv, saved_model/, predictions/*.png, "
          f"stats/*.png")


if __name__ == "__main__":
    main()
