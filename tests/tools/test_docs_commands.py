"""Every command in the fenced blocks of docs/datasets.md and docs/deployment.md runs as written: each through bash, in
a workspace where the paths they name hold small synthetic data in the formats the docs say (WOD segments, Argoverse 2
logs with their masks, your own sweeps and PCD files), in the pages' order, each later command reading what the ones
before it wrote. Nothing in a command is rewritten but an optional part (`[--flag value]`: run with it, the first
of `a|b`, unless `SKIPPED_OPTIONS` says why not) and `...` (the arguments of the command before it, as the page
says). The sizes are the configs': `configs/` in the workspace holds each of the project's configs with the tests'
tiny model and 2 training steps (`TINY`), so `--config configs/fastflow3d_waymo.yaml` trains the paper's structure
at a test's size; the placeholders C, M, D, O, S, DIR are paths in the workspace (C: the tiny synthetic_cpu config).

Run by `make test-docs-commands` (CI's leg in .ci/run): it takes minutes."""
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import yaml

from conftest import ROOT, TINY_OVERRIDES, TINY_SCALE

pytestmark = pytest.mark.slow

PAGES = ("docs/datasets.md", "docs/deployment.md")
# Commands of the pages that are no tool run: what they do, and where it is done instead.
NOT_RUN = {'pip install -c constraints.txt -e ".[xla]"': "installs the xla extra (make install does: the venv has it)",
           "python tools/fuzz_reader.py": "its thousands of mutants take 12 minutes on 2 cores; tests/fuzz/ runs the "
                                          "same fuzzers on a few hundred"}
# Optional parts left out, each with its reason.
SKIPPED_OPTIONS = {"[--train_points 177000 --train_batch_sizes 1,8]": "the training step's programs at 177,000 points "
                   "take minutes to export; tests/training/test_xla_step.py exports and runs them small"}
TINY = (*TINY_OVERRIDES, "train.num_steps=2", "train.warmup_steps=0", "train.eval_every_steps=0",
        "train.checkpoint_every_steps=1", "train.log_every_steps=1")
TIMEOUT_S = 1800


def fenced_commands(page: str) -> list[str]:
    """The commands of a page's fenced blocks, one per logical line (continuations joined), comments kept (bash
    drops them)."""
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        text = f.read()
    commands = []
    for block in re.findall(r"^```[^\n]*\n(.*?)^```", text, re.M | re.S):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                commands.append(line.strip())
    return commands


def _not_run(command: str) -> bool:
    return any(command.startswith(known) for known in NOT_RUN)


def as_run(command: str, before: list[str]) -> str:
    """The command as bash runs it here: each optional part with its first alternative (or left out, by
    `SKIPPED_OPTIONS`), `...` as the arguments of the command of the same tool before it, `python` this venv's."""
    if " ... " in command:
        tool = command.split(" ... ")[0]
        earlier = next(c for c in reversed(before) if c.startswith(tool + " ") and " ... " not in c)
        arguments = re.sub(r"\s--out \S+", "", earlier[len(tool):].split("#")[0]).strip()
        command = command.replace(" ... ", f" {arguments} ")
    for group in SKIPPED_OPTIONS:
        command = command.replace(group, "")
    command = re.sub(r"\[(--[^\[\]]*)\]", lambda m: re.sub(r"(\S+)\|\S+", r"\1", m.group(1)), command)
    if command.startswith("python "):
        command = f"{sys.executable} {command[len('python '):]}"
    return command


def _tiny_configs(ws):
    """`configs/*.yaml` of the project, each with `TINY` on top, in the workspace's configs/; C is synthetic_cpu's."""
    from ff3d_tf.config import load_config
    os.makedirs(os.path.join(ws, "configs"))
    for name in sorted(os.listdir(os.path.join(ROOT, "configs"))):
        if not name.endswith(".yaml"):
            continue
        with open(os.path.join(ROOT, "configs", name)) as f:
            tree = yaml.safe_load(f) or {}
        for item in TINY:
            key, value = item.split("=", 1)
            section, field = key.split(".")
            tree.setdefault(section, {})[field] = yaml.safe_load(value)
        path = os.path.join(ws, "configs", name)
        with open(path, "w") as f:
            yaml.safe_dump(tree, f, sort_keys=False)
        load_config(path)  # valid
    shutil.copy(os.path.join(ws, "configs", "synthetic_cpu.yaml"), os.path.join(ws, "C"))


def _wod(ws):
    """Small synthetic WOD segments (with flow labels and tracked boxes) where the pages read them."""
    from ff3d_tf.data.synthetic import wod as synthetic
    first = None
    for folder, seed in (("wod_flow/train", 0), ("wod_flow/valid", 1), ("wod_v1/training", 2), ("train", 3)):
        path = os.path.join(ws, folder, f"segment-{seed}.tfrecord")
        synthetic.write_segment(path, synthetic.SegmentSpec(seed=seed, num_frames=4, lidar_scale=TINY_SCALE))
        first = first or path
    shutil.copy(first, os.path.join(ws, "SEGMENT.tfrecord"))


def _mask_archive(split_dir, zip_path):
    """A mask archive in the official layout (`<log_id>/<timestamp_ns>.feather`, one boolean column `mask`) over the
    first sweep of each log of `split_dir`; returns {entry: True values}."""
    import pyarrow as pa
    import pyarrow.feather as feather
    from ff3d_tf.data.av2 import argoverse2
    rng, rows = np.random.default_rng(0), {}
    with zipfile.ZipFile(zip_path, "w") as zf:
        for log in sorted(os.listdir(split_dir)):
            stamp = argoverse2.sweep_timestamps(os.path.join(split_dir, log))[0]
            n = len(argoverse2.read_sweep(os.path.join(split_dir, log), stamp)["points_xyz"])
            mask = rng.random(n) < 0.6
            sink = pa.BufferOutputStream()
            feather.write_feather(pa.table({"mask": pa.array(mask)}), sink)
            zf.writestr(f"{log}/{stamp}.feather", sink.getvalue().to_pybytes())
            rows[f"{log}/{stamp}.feather"] = int(mask.sum())
    return rows


def _av2(ws):
    """Synthetic Argoverse 2 logs of each split the pages name (the test split without annotations), the official
    masks' archives of val and test, av2-api's test format JSON."""
    from ff3d_tf.data.synthetic import av2 as synthetic_av2
    for root, split, seed in (("av2/sensor", "train", 0), ("AV2", "train", 1), ("AV2", "val", 2), ("AV2", "test", 3)):
        synthetic_av2.write_synthetic_split(os.path.join(ws, root), 1, split, 6, seed, 3000)
    for log in os.listdir(os.path.join(ws, "AV2", "test")):
        os.remove(os.path.join(ws, "AV2", "test", log, "annotations.feather"))
    _mask_archive(os.path.join(ws, "AV2", "val"), os.path.join(ws, "val-masks.zip"))
    rows = _mask_archive(os.path.join(ws, "AV2", "test"), os.path.join(ws, "test-masks.zip"))
    with open(os.path.join(ws, "test_submission_format.json"), "w") as f:
        json.dump(rows, f)


def _own_clouds(ws):
    """Your own sweeps: D (four .bin sweeps, poses.txt, timestamps.txt) and scans/ (two PCD files, each with its
    pose file)."""
    from ff3d_tf import geometry
    from ff3d_tf.data.files import sequences
    rng = np.random.default_rng(1)
    clouds = [(f"{k:06d}", rng.uniform([-30, -30, -1], [30, 30, 2], (300, 3)), rng.uniform(0, 1, 300))
              for k in range(4)]
    poses = [geometry.box_matrices_np((0.9 * k, 0.1 * k, 0.0), 0.02 * k)[0] for k in range(4)]
    sequences.write_sequence(os.path.join(ws, "D"), clouds, poses, [k * 100_000_000 for k in range(4)])
    os.makedirs(os.path.join(ws, "scans"))
    for k, (stem, xyz, intensity) in zip((41, 42), clouds[:2]):
        rows = "".join(f"{x:.4f} {y:.4f} {z:.4f} {i:.3f}\n" for (x, y, z), i in zip(xyz, intensity))
        with open(os.path.join(ws, "scans", f"{k:06d}.pcd"), "w") as f:
            f.write(f"VERSION .7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                    f"WIDTH {len(xyz)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\nDATA ascii\n{rows}")
        np.savetxt(os.path.join(ws, "scans", f"{k:06d}.pose.txt"), poses[k - 41])


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """The folder the commands run in (also their HOME, for ~/...): tools/ and lab/ of the checkout, the tiny
    configs, the data; demo_out/model is the model the pages train as M."""
    ws = str(tmp_path_factory.mktemp("docs_commands"))
    for name in ("tools", "lab"):
        os.symlink(os.path.join(ROOT, name), os.path.join(ws, name))
    _tiny_configs(ws)
    _wod(ws)
    _av2(ws)
    _own_clouds(ws)
    os.makedirs(os.path.join(ws, "demo_out"))
    os.symlink(os.path.join(ws, "M"), os.path.join(ws, "demo_out", "model"))
    return ws


def _run(ws, command):
    env = {**os.environ, "HOME": ws, "PYTHONPATH": ROOT}
    return subprocess.run(["bash", "-c", command], cwd=ws, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S)


# Commands of the pages that are not in a fenced block but that one needs first: (the fenced command they come
# before, the command, the page's section that gives it).
GIVEN_IN_TEXT = {"python tools/av2_submission.py": (
    "python tools/write_pair_records.py --source av2 --input AV2/test --out_dir records/av2_test --no_labels",
    "docs/datasets.md, Submitting to the leaderboards, step 1")}


def test_the_pages_name_only_commands_this_test_knows():
    for page in PAGES:
        for command in fenced_commands(page):
            if _not_run(command):
                continue
            assert command.startswith("python tools/") or command.startswith("python lab/tools/"), (page, command)
            for option in re.findall(r"\[--[^\[\]]*\]", command):
                assert option in SKIPPED_OPTIONS or "|" not in option or option.count("|") == 1, (page, option)


@pytest.mark.parametrize("page", PAGES)
def test_every_command_of_the_page_runs_as_written(workspace, page):
    if not os.path.exists(os.path.join(workspace, "M")):  # the model the pages name M (trained by datasets.md's)
        run = _run(workspace, f"{sys.executable} tools/train.py --config C --data_dir train --model_dir M")
        assert run.returncode == 0, run.stderr[-3000:]
    failures, before = [], []
    for command in fenced_commands(page):
        if _not_run(command):
            continue
        for prefix, (given, where) in GIVEN_IN_TEXT.items():
            if command.startswith(prefix) and given not in before:
                run = _run(workspace, as_run(given, before))
                assert run.returncode == 0, f"{where}: {given}\n{run.stderr[-3000:]}"
                before.append(given)
        run = _run(workspace, as_run(command, before))
        before.append(command)
        if run.returncode != 0 or "Traceback" in run.stderr:
            failures.append(f"{command}\n  -> exit {run.returncode}\n{run.stderr[-2000:]}")
    assert not failures, f"{len(failures)} commands of {page} failed:\n\n" + "\n\n".join(failures)
