"""lab/tools/benchmark_distillation.py end to end at the tiniest size: its JSON's structure, and its figures recomputed
here from the records it wrote (zero flow's EPE is the mean speed of the evaluated points; the pseudo-labels' EPE is
their distance to the human labels)."""
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, TINY_OVERRIDES, TINY_SCALE

# The end-to-end run: nine stages, each a tool in its own process (TensorFlow's import alone is seconds each): about
# 100 s of CPU, 3 minutes on this shared 2-core machine under load.
slow = pytest.mark.slow

STEPS = 2
NSFP_ITERATIONS = 3
OVERRIDES = TINY_OVERRIDES + ("train.log_every_steps=1",)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("distillation")
    json_path = out / "distillation.json"
    command = [sys.executable, "lab/tools/benchmark_distillation.py", "--out_dir", str(out / "work"), "--json",
               str(json_path), "--config", "", "--steps", str(STEPS), "--train_segments", "1", "--eval_segments",
               "1", "--frames_per_segment", "3", "--lidar_scale", str(TINY_SCALE), "--nsfp_max_iterations",
               str(NSFP_ITERATIONS), "--nsfp_patience", str(NSFP_ITERATIONS), "--nsfp_grid_cell_m", "0.5",
               "--nsfp_crop_m", "16", *[a for s in OVERRIDES for a in ("--set", s)]]
    proc = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    with open(json_path) as f:
        return json.load(f), out / "work", proc.stdout


def _grid_points(records_dir, extras=()):
    """Every pair of a records directory as NumPy, cropped to the tiny config's grid as the input pipeline crops
    (written out here, not through ff3d_tf.data.pairs)."""
    from ff3d_tf.config import load_config
    from ff3d_tf.data import pair_records, pairs
    g = load_config(None, OVERRIDES).grid
    files = pairs.list_segment_files(str(records_dir))
    manifest = pair_records.manifest_of_files(files)
    for path in files:
        for ex in pair_records.records_dataset(path, manifest, extras):
            ex = {k: v.numpy() for k, v in ex.items()}
            p = ex["points_xyz_t0"]
            inside = ((p[:, 0] >= g.x_range_m[0]) & (p[:, 0] < g.x_range_m[1]) & (p[:, 1] >= g.y_range_m[0]) &
                      (p[:, 1] < g.y_range_m[1]) & (p[:, 2] >= g.z_range_m[0]) & (p[:, 2] <= g.z_range_m[1]))
            yield {k: ex[k][inside] for k in ("flow_mps_t0", "class_id_t0") + tuple(extras)}


@slow
def test_json_structure_and_finite_figures(run):
    result, _, stdout = run
    for key in ("verdict", "eval_summary", "eval_metrics", "pseudo_labels", "options", "nsfp_job", "timings_s",
                "training"):
        assert key in result, key
    assert set(result["eval_summary"]) == {"human", "pseudo", "zero_flow"}
    for name, summary in list(result["eval_summary"].items()) + [("pseudo-labels",
                                                                   result["pseudo_labels"]["summary"])]:
        for key in ("all/moving/mean_l2_mps", "all/stationary/mean_l2_mps", "vehicle/moving/mean_l2_mps",
                    "three_way/fg_dynamic_epe_m"):
            assert math.isfinite(summary[key]) and summary[key] >= 0, (name, key, summary.get(key))
        assert summary["all/moving/count"] > 0 and summary["all/stationary/count"] > 0
    verdict = result["verdict"]
    assert verdict["pseudo_beats_zero_flow_on_moving"] == (
        verdict["all_moving_mean_l2_mps"]["pseudo"] < verdict["all_moving_mean_l2_mps"]["zero_flow"])
    for k in ("human", "pseudo", "zero_flow"):
        assert verdict["all_moving_mean_l2_mps"][k] == result["eval_summary"][k]["all/moving/mean_l2_mps"]
    # The paper's tables as the eval wrote them, for both models and zero flow.
    assert set(result["eval_metrics"]) == {"human", "pseudo", "zero_flow"}
    assert "pedestrian/moving/frac_l2_le_0.1" in result["eval_metrics"]["human"]
    assert result["zero_flow_same_in_both_evaluations"] is True
    # Same steps for both models; NSFP fitted every training pair within its step cap.
    for k in ("human", "pseudo"):
        assert result["training"][k]["last_logged_step"] == STEPS
    job = result["nsfp_job"]
    assert job["fitted_pairs"] == job["pairs"] == 2
    assert 1 <= job["iterations_per_fitted_pair"] <= NSFP_ITERATIONS
    assert result["options"]["nsfp"]["max_iterations"] == NSFP_ITERATIONS
    assert result["options"]["steps"] == STEPS
    for stage in ("generate_train", "generate_eval", "records_train", "records_eval", "pseudo_label", "train_human",
                  "train_pseudo", "eval_human", "eval_pseudo"):
        assert result["timings_s"][stage] > 0, stage
    assert "=== [9/9] eval_pseudo done in" in stdout
    assert "pseudo-trained beats zero flow on moving points" in stdout


@slow
def test_zero_flow_epe_is_the_mean_speed_of_the_evaluated_points(run):
    result, work, _ = run
    from ff3d_tf import schema
    moving, stationary = [], []
    for ex in _grid_points(work / "records" / "eval"):
        speed = np.linalg.norm(ex["flow_mps_t0"].astype(np.float64), axis=1)
        labelled = ex["class_id_t0"] >= 0
        moving.append(speed[labelled & (speed >= schema.MOVING_THRESHOLD_MPS)])
        stationary.append(speed[labelled & (speed < schema.MOVING_THRESHOLD_MPS)])
    moving, stationary = np.concatenate(moving), np.concatenate(stationary)
    zero = result["eval_summary"]["zero_flow"]
    assert zero["all/moving/count"] == len(moving) > 0
    assert zero["all/stationary/count"] == len(stationary)
    np.testing.assert_allclose(zero["all/moving/mean_l2_mps"], moving.mean(), rtol=1e-6)
    np.testing.assert_allclose(zero["all/stationary/mean_l2_mps"], stationary.mean(), rtol=1e-6, atol=1e-9)


@slow
def test_pseudo_label_epe_is_their_distance_to_the_human_labels(run):
    result, work, _ = run
    from ff3d_tf import schema
    errors, speeds, fitted = [], [], 0
    for ex in _grid_points(work / "records" / "train_pseudo", ("flow_mps_pseudo_t0",)):
        labelled = ex["class_id_t0"] >= 0
        human = ex["flow_mps_t0"][labelled].astype(np.float64)
        pseudo = ex["flow_mps_pseudo_t0"][labelled].astype(np.float64)
        errors.append(np.linalg.norm(pseudo - human, axis=1))
        speeds.append(np.linalg.norm(human, axis=1))
        fitted += int(np.any(ex["flow_mps_pseudo_t0"] != 0, axis=1).sum())
    errors, speeds = np.concatenate(errors), np.concatenate(speeds)
    moving = speeds >= schema.MOVING_THRESHOLD_MPS
    labels = result["pseudo_labels"]
    np.testing.assert_allclose(labels["summary"]["all/moving/mean_l2_mps"], errors[moving].mean(), rtol=1e-5)
    np.testing.assert_allclose(labels["summary"]["all/stationary/mean_l2_mps"], errors[~moving].mean(), rtol=1e-5)
    np.testing.assert_allclose(labels["zero_flow_summary"]["all/moving/mean_l2_mps"], speeds[moving].mean(),
                               rtol=1e-6)
    assert labels["points"]["points_with_pseudo_flow"] == fitted > 0
    assert labels["points"]["pairs"] == 2
    assert os.path.exists(work / "model_pseudo" / "train_history.json")


def test_a_stage_reruns_when_its_command_or_the_code_changed(tmp_path, capsys):
    """A finished stage is skipped only for the same command on the same code: a tool whose defaults changed
    (same command line) reruns it, and its outputs are removed first. (The tool's runner, in its job
    `lab.training.distillation_benchmark`, is `ff3d_tf.stages`; its other rules: tests/test_stages.py.)"""
    from ff3d_tf import stages
    from lab.training import distillation_benchmark as tool
    output = tmp_path / "output"
    marker = tmp_path / "runs.txt"
    args = ["-c", f"import os; os.makedirs({str(output)!r}, exist_ok=True); open({str(marker)!r}, 'a').write('x')"]

    def run_stage(code=None, command=args):
        job = tool.Stages(str(tmp_path / "stages"), tool.PLAN[:1], code=code)
        job.run(tool.PLAN[0], command, [str(output)])
        return job

    assert run_stage().skipped == [] and marker.read_text() == "x"
    assert run_stage().skipped == [tool.PLAN[0]] and marker.read_text() == "x"  # same command, same code: skipped
    capsys.readouterr()
    (output / "stale").write_text("")
    assert run_stage(code="other").skipped == [] and marker.read_text() == "xx"
    assert "removing" in capsys.readouterr().out and not (output / "stale").exists()
    assert run_stage(code="other").skipped == [tool.PLAN[0]]
    assert run_stage(code="other", command=args + ["again"]).skipped == [] and marker.read_text() == "xxx"
    assert tool.Stages is stages.Stages and len(stages.code_fingerprint()) == 64
