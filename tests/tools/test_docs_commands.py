"""Every command in the fenced blocks of docs/datasets.md, docs/deployment.md and docs/training.md runs as written: each
through bash, in a workspace where the paths they name hold small synthetic data in the formats the docs say (WOD
segments, Argoverse 2 logs with their masks, your own sweeps and PCD files), in the pages' order, each later command
reading what the ones before it wrote. Nothing in a command is rewritten but an optional part (`[--flag value]`: run
with it, the first of `a|b`, unless `SKIPPED_OPTIONS` says why not) and `...` (the arguments of the command before it,
as the page says). The sizes are the configs': `configs/` in the workspace holds each of the project's configs with
the tests' tiny model and 2 training steps (`TINY`), so `--config configs/fastflow3d_waymo.yaml` trains the paper's
structure at a test's size; the placeholders C, M, D, O, S, DIR, V are paths in the workspace (C: the tiny
synthetic_cpu config).
A placeholder holds what its page says it is, so the pages have workspaces of their own (`WORKSPACES`): on
datasets.md D is a folder of your own sweeps, on training.md D and V are folders of WOD segments (train, validation).
What a page's command reads from another page's, or from its prose, is written first by that command, named with its
source (`GIVEN_IN_TEXT`). On training.md every `tools/train.py` command is a recipe of its own in M: the M of the one
before is moved aside first (`NEW_MODEL_EACH_TRAINING`).

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

PAGES = ("docs/datasets.md", "docs/deployment.md", "docs/training.md")
# The fixture each page's commands run in. datasets.md and deployment.md share one (deployment.md's commands read what
# datasets.md's wrote); training.md's placeholders mean other things.
WORKSPACES = {"docs/datasets.md": "workspace", "docs/deployment.md": "workspace",
              "docs/training.md": "training_workspace"}
# Commands of the pages that are no tool run: what they do, and where it is done instead.
NOT_RUN = {'pip install -c constraints.txt -e ".[xla]"': "installs the xla extra (make install does: the venv has it)",
           "python tools/fuzz_reader.py": "its thousands of mutants take 12 minutes on 2 cores; tests/fuzz/ runs the "
                                          "same fuzzers on a few hundred",
           # docs/training.md
           "make demo MODEL=gru":
               "a make target: installs the package first (pip) and runs the whole demo (minutes of training on the "
               "demo config); tests/tools/test_demo_resume.py runs tools/demo.py end to end (paper head), "
               "tests/training/test_gru_head_training.py trains the GRU head",
           "TF_CONFIG=":
               "one worker of a cluster of two hosts (host-a, host-b) on gs:// paths; "
               "tests/training/test_multiworker.py runs the same two-worker job on 127.0.0.1",
           "python tools/data_service.py --dispatcher --port 5050":
               "a server that runs until it is stopped, for input workers on other hosts; "
               "tests/training/test_data_service.py starts the roles as processes and trains from them",
           "python tools/data_service.py --worker --dispatcher_address host:5050":
               "a server on an input machine, for a dispatcher on another host; tests/training/test_data_service.py",
           "python tools/train.py ... --data_service_address grpc://host:5050":
               "reads from a service on another host; tests/training/test_data_service.py trains from one on "
               "localhost",
           "python lab/tools/soak_train.py":
               "20 faults on a two-worker job with its service, each with its restart: 9 minutes on 2 cores (wall_s of "
               "benchmarks/soak_train.json), and with no --out it rewrites that file of the checkout; "
               "tests/lab/training/test_soak.py runs one fault end to end",
           "python lab/tools/benchmark_heads.py":
               "200 steps of each of 7 variants on 2 formats, each a training and an evaluation in its own process: "
               "39 minutes on 2 cores (the timings_s of benchmarks/heads_synthetic.json); "
               "tests/lab/training/test_heads_benchmark.py runs its stages over stand-in tools",
           "python lab/tools/benchmark_head_cost.py":
               "3 variants' forwards at up to 1,000,000 points and their training steps, each reading in its own "
               "process: 4.6 minutes on 2 cores at the tiny config; tests/lab/training/test_head_cost.py runs it end "
               "to end at 300 points"}
# Optional parts left out, each with its reason.
SKIPPED_OPTIONS = {"[--train_points 177000 --train_batch_sizes 1,8]": "the training step's programs at 177,000 points "
                   "take minutes to export; tests/training/test_xla_step.py exports and runs them small",
                   "[--set k=v]": "k=v stands for any config override; training.md's later commands run real ones "
                   "(--set train.loss=deltaflow, --set data.num_frames=3 --set model.temporal=stack)"}
# Pages whose `tools/train.py` commands each start a model of their own in M (the recipes are alternatives, and M of
# another config stops training, docs/training.md): before each, the M of the one before is moved to M.1, M.2, ...
NEW_MODEL_EACH_TRAINING = ("docs/training.md",)
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


@pytest.fixture(scope="module")
def training_workspace(tmp_path_factory):
    """docs/training.md's workspace: tools/ and lab/ of the checkout, the tiny configs, D and V folders of WOD segments
    (train, validation), Argoverse 2 logs of train and val in AV2/ (datasets.md's) and av2/sensor/ (training.md's)."""
    from ff3d_tf.data.synthetic import av2 as synthetic_av2
    from ff3d_tf.data.synthetic import wod as synthetic
    ws = str(tmp_path_factory.mktemp("docs_commands_training"))
    for name in ("tools", "lab"):
        os.symlink(os.path.join(ROOT, name), os.path.join(ws, name))
    _tiny_configs(ws)
    for folder, seed in (("D", 0), ("V", 1)):
        synthetic.write_segment(os.path.join(ws, folder, f"segment-{seed}.tfrecord"),
                                synthetic.SegmentSpec(seed=seed, num_frames=4, lidar_scale=TINY_SCALE))
    # 8 sweeps: 3 examples of 5 sweeps (configs/deltaflow_av2.yaml) in a log
    for root, split, seed in (("AV2", "train", 1), ("AV2", "val", 2), ("av2/sensor", "train", 0),
                              ("av2/sensor", "val", 4)):
        synthetic_av2.write_synthetic_split(os.path.join(ws, root), 1, split, 8, seed, 3000)
    return ws


def _run(ws, command):
    env = {**os.environ, "HOME": ws, "PYTHONPATH": ROOT}
    return subprocess.run(["bash", "-c", command], cwd=ws, env=env, capture_output=True, text=True,
                          timeout=TIMEOUT_S)


# Commands that a page's fenced command needs first and that are not in a fenced block before it (in the page's prose,
# or another page's block): {the start of the fenced command they come before: ((the command, where it is given),
# ...)}.
GIVEN_IN_TEXT = {
    "python tools/av2_submission.py": (
        ("python tools/write_pair_records.py --source av2 --input AV2/test --out_dir records/av2_test --no_labels",
         "docs/datasets.md, Submitting to the leaderboards, step 1"),),
    "python tools/train.py --config configs/deflow_av2.yaml": (
        ("python tools/write_pair_records.py --source av2 --input AV2/train --out_dir records/av2_train [--config C]",
         "docs/datasets.md, Argoverse 2 (its fenced block)"),
        ("python tools/write_pair_records.py --source av2 --input AV2/val --out_dir records/av2_val",
         "docs/datasets.md, Argoverse 2 (its fenced block)")),
    "python tools/train.py --config configs/deltaflow_av2.yaml": (
        ("python tools/write_pair_records.py --source av2 --config configs/deltaflow_av2.yaml --input av2/sensor/val "
         "--out_dir records5/av2_val",
         "docs/training.md, Several sweeps: the comment `# and av2/sensor/val -> records5/av2_val`"),)}


def test_the_pages_name_only_commands_this_test_knows():
    for page in PAGES:
        assert page in WORKSPACES, page
        commands = fenced_commands(page)
        assert commands, page
        for command in commands:
            if _not_run(command):
                continue
            assert command.startswith("python tools/") or command.startswith("python lab/tools/"), (page, command)
            for option in re.findall(r"\[--[^\[\]]*\]", command):
                assert option in SKIPPED_OPTIONS or "|" not in option or option.count("|") == 1, (page, option)
    every = [c for page in PAGES for c in fenced_commands(page)]
    for known in NOT_RUN:  # no stale entry: each still names a command of a page
        assert any(c.startswith(known) for c in every), known
    for prefix, givens in GIVEN_IN_TEXT.items():
        assert any(c.startswith(prefix) for c in every), prefix
        for given, where in givens:  # one of another page's fenced commands is there as written
            assert where.split(",")[0] in PAGES, where
            assert "fenced block" not in where or given in fenced_commands(where.split(",")[0]), (given, where)


def _move_model_aside(ws):
    """M to the first free M.<n>, if there is an M."""
    if os.path.exists(os.path.join(ws, "M")):
        n = 1
        while os.path.exists(os.path.join(ws, f"M.{n}")):
            n += 1
        os.rename(os.path.join(ws, "M"), os.path.join(ws, f"M.{n}"))


@pytest.mark.parametrize("page", PAGES)
def test_every_command_of_the_page_runs_as_written(request, page):
    workspace = request.getfixturevalue(WORKSPACES[page])
    if WORKSPACES[page] == "workspace" and not os.path.exists(os.path.join(workspace, "M")):
        # the model datasets.md and deployment.md name M (trained by datasets.md's)
        run = _run(workspace, f"{sys.executable} tools/train.py --config C --data_dir train --model_dir M")
        assert run.returncode == 0, run.stderr[-3000:]
    failures, before = [], []
    for command in fenced_commands(page):
        if _not_run(command):
            continue
        for prefix, givens in GIVEN_IN_TEXT.items():
            for given, where in givens:
                if command.startswith(prefix) and given not in before:
                    run = _run(workspace, as_run(given, before))
                    assert run.returncode == 0, f"{where}: {given}\n{run.stderr[-3000:]}"
                    before.append(given)
        if page in NEW_MODEL_EACH_TRAINING and command.startswith("python tools/train.py "):
            _move_model_aside(workspace)
        run = _run(workspace, as_run(command, before))
        before.append(command)
        if run.returncode != 0 or "Traceback" in run.stderr:
            failures.append(f"{command}\n  -> exit {run.returncode}\n{run.stderr[-2000:]}")
    assert not failures, f"{len(failures)} commands of {page} failed:\n\n" + "\n\n".join(failures)
