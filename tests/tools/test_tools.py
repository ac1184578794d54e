"""The thin tools run end to end (subprocesses, as a user calls them)."""
import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT


def _run(*args):
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_model_summary_last_line():
    lines = _run("tools/model_summary.py", "--config", "configs/fastflow3d_waymo.yaml").strip().splitlines()
    assert lines[-1] == "total_params 5233571"
    assert any(line.split() == ["Y", "4,384"] for line in lines)


def test_model_summary_of_the_gru_head():
    lines = _run("tools/model_summary.py", "--config", "configs/fastflow3d_waymo.yaml", "--set",
                 "model.head=gru").strip().splitlines()
    assert lines[-1] == "total_params 5385699" and "head gru, 4 iterations" in lines[0]
    rows = [line.split() for line in lines[1:-1]]
    assert rows[-7:] == [["W", "0"], ["GRU-x", "256"], ["GRU-z", "49,344"], ["GRU-r", "49,344"],
                         ["GRU-q", "49,344"], ["MLP-1", "8,224"], ["MLP-2", "99"]]


def test_dataset_stats_table_and_png(tiny_segment, tmp_path):
    out = _run("tools/dataset_stats.py", "--data_dir", os.path.dirname(tiny_segment), "--out_dir", str(tmp_path))
    assert "vehicle" in out and "pedestrian" in out
    stats = json.loads((tmp_path / "dataset_stats.json").read_text())
    assert stats["frames"] == 4 and stats["vehicle"]["moving"] > 0
    assert (tmp_path / "speed_histogram.png").stat().st_size > 1000


def test_bad_config_fails_before_work(tmp_path):
    out = subprocess.run([sys.executable, "tools/train.py", "--config", "configs/synthetic_cpu.yaml", "--set",
                          "grid.num_pillars_x=100", "--data_dir", str(tmp_path), "--model_dir", str(tmp_path / "m")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and "multiple of 8" in out.stderr
    assert not (tmp_path / "m").exists()


def test_run_study_without_validation_data_fails_before_work(tiny_segment, tmp_path):
    empty = tmp_path / "val"
    empty.mkdir()
    out = subprocess.run([sys.executable, "tools/run_study.py", "--study", "ground_removal", "--config", "",
                          "--train_dir", os.path.dirname(tiny_segment), "--val_dir", str(empty), "--out_dir",
                          str(tmp_path / "out")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode != 0 and f"study error: no TFRecord files at {empty}" in out.stderr
    assert "Traceback" not in out.stderr and not (tmp_path / "out").exists()


@pytest.mark.slow  # two trainings through the study tool: ~110 s
def test_run_study_ground_removal(tiny_segment, tmp_path):
    from conftest import TINY_OVERRIDES
    data_dir = os.path.dirname(tiny_segment)
    sets = [a for s in TINY_OVERRIDES + ("train.num_steps=2", "train.checkpoint_every_steps=2")
            for a in ("--set", s)]
    out = _run("tools/run_study.py", "--study", "ground_removal", "--config", "", "--train_dir", data_dir,
               "--val_dir", data_dir, "--out_dir", str(tmp_path), "--max_eval_pairs", "1", *sets)
    assert "change vs with_ground" in out
    report = json.loads((tmp_path / "ground_removal" / "ground_removal.json").read_text())
    with_ground, removed = (r["metrics"] for r in report["variants"])
    # Evaluated on the same pair: removing the ground leaves fewer stationary points to score.
    assert 0 < removed["all/stationary/count"] < with_ground["all/stationary/count"]
    assert (tmp_path / "ground_removal" / "ground_removal.png").stat().st_size > 1000
    # A bad study value fails before any work.
    bad = subprocess.run([sys.executable, "tools/run_study.py", "--study", "point_density", "--values", "0.5,3",
                          "--config", "", "--train_dir", data_dir, "--val_dir", data_dir, "--out_dir",
                          str(tmp_path / "bad")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "shares must be in (0, 1]" in bad.stderr and not (tmp_path / "bad").exists()


# Trains, then predicts through the tool on WOD and AV2 (~70 s); the fast suite runs the tool's paths in
# tests/tools/test_predict_own_clouds.py and tests/inference/test_predict_job.py.
@pytest.mark.slow
def test_predict_from_checkpoint_on_wod_and_av2(tiny_segment, tiny_config, tmp_path):
    import numpy as np
    from conftest import AV2_LOG, TINY_OVERRIDES
    from ff3d_tf.config import replace_config
    from ff3d_tf.training.trainer import Trainer
    cfg = replace_config(tiny_config, {"train.eval_every_steps": 0})
    Trainer(cfg, str(tmp_path / "m"), [tiny_segment], log_fn=lambda s: None).train(1)
    sets = [a for s in TINY_OVERRIDES for a in ("--set", s)]
    for source, out in ((["--input", tiny_segment], "wod"), (["--av2_log", AV2_LOG], "av2")):
        _run("tools/predict.py", "--config", "", "--checkpoint", str(tmp_path / "m"), *source, "--out_dir",
             str(tmp_path / out), *sets)
        pred = np.load(tmp_path / out / "frame_0000.npz")
        n = len(pred["points_xyz_t0"])
        assert pred["flow_mps_pred"].shape == (n, 3) and pred["point_valid"].sum() > 0.5 * n
        assert (tmp_path / out / "frame_0000_bev.png").stat().st_size > 10000
    assert len(list((tmp_path / "wod").glob("frame_*.npz"))) == 3  # 4 frames -> 3 pairs


def test_annotate_flow_bad_arguments_fail_before_work(tiny_segment, tmp_path):
    out = subprocess.run([sys.executable, "tools/annotate_flow.py", "--input", tiny_segment, "--out_dir",
                          str(tmp_path / "o"), "--returns", "3"], cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    from ff3d_tf.schema import ALL_LASERS, lidar_selection_problem
    assert out.returncode != 0 and lidar_selection_problem(ALL_LASERS, (3,)) in out.stderr
    assert not (tmp_path / "o").exists()


def test_pseudo_label_bad_fit_option_fails_before_work(tmp_path):
    """The job's options are the config's nsfp section: a bad value names its key; one given as a flag (which Beam
    would drop) names the --set that sets it. Both before any work."""
    for args, message in ((["--set", "nsfp.reverse_every=-1"], "nsfp.reverse_every=-1: must be an integer in [0, "),
                          (["--reverse_every", "1"], "--reverse_every: the job's options are config keys: --set "
                                                     "nsfp.reverse_every=VALUE")):
        out = subprocess.run([sys.executable, "tools/pseudo_label.py", "--input", str(tmp_path), "--out_dir",
                              str(tmp_path / "p"), *args], cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert out.returncode != 0 and message in out.stderr, out.stderr
        assert not (tmp_path / "p").exists()
