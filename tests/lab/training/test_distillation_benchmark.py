"""lab.training.distillation_benchmark: the stage plan, the pseudo-labels' scores, the result and its table
against hand calculations, and the job run over stand-in tools. The tool end to end with the real tools:
tests/lab/tools/test_benchmark_distillation.py."""
import dataclasses
import json
import math
import os
import textwrap

import numpy as np

from conftest import TINY_OVERRIDES
from ff3d_tf import schema
from lab.training import distillation_benchmark as job

OPTIONS = job.Options(config="", sets=("data.point_bucket_base=1024",), steps=2, seed=3, train_segments=1,
                      eval_segments=1, frames_per_segment=3, lidar_scale=0.12, nsfp_max_iterations=3,
                      nsfp_patience=2, nsfp_grid_cell_m=0.5, nsfp_ground_below_z_m=-1.0, nsfp_crop_m=16.0,
                      nsfp_seed=5, nsfp_args=("--set=nsfp.learning_rate=0.01",))
NAN = float("nan")
# Eval figures (m/s, fg dynamic in m) of the hand calculations below; NaN: a class without points.
HUMAN = {"all/moving/mean_l2_mps": 0.5, "all/stationary/mean_l2_mps": 0.1, "three_way/fg_dynamic_epe_m": 0.05,
         "cyclist/moving/mean_l2_mps": NAN, "pedestrian/moving/frac_l2_le_0.1": 0.3}
PSEUDO = {"all/moving/mean_l2_mps": 0.8, "all/stationary/mean_l2_mps": 0.2, "three_way/fg_dynamic_epe_m": 0.08}
ZERO = {"all/moving/mean_l2_mps": 2.0, "all/stationary/mean_l2_mps": 0.05, "cyclist/moving/mean_l2_mps": NAN}
NSFP_COUNTS = {"pairs": 4, "fitted_pairs": 4, "nsfp_seconds": 10.0, "nsfp_iterations": 300}
HISTORIES = {"human": {"loss": [[1, 3.0], [2, 2.5]]}, "pseudo": {}}


def _args_after(command, flag):
    return [command[i + 1] for i, a in enumerate(command) if a == flag]


def test_stage_plan():
    plan = job.stage_plan(OPTIONS, "/o", tools_dir="/t")
    assert [s.name for s in plan] == list(job.PLAN)
    by_name = {s.name: s for s in plan}
    assert _args_after(by_name["generate_train"].command, "--seed") == ["100"]
    assert _args_after(by_name["generate_eval"].command, "--seed") == ["900"]
    label = by_name["pseudo_label"].command
    assert label[0] == "/t/pseudo_label.py" and _args_after(label, "--input") == ["/o/records/train"]
    # NSFP's options as config keys; a ground height below 0 keeps every point (no remove_ground_below_z_m)
    assert _args_after(label, "--set") == ["nsfp.max_iterations=3", "nsfp.patience=2", "nsfp.grid_cell_m=0.5",
                                           "nsfp.crop_xy_half_extent_m=16.0", "nsfp.seed=5"]
    assert label[-1] == "--set=nsfp.learning_rate=0.01"
    # Both trainings: the same records and config but data.labels; the user's --set comes after the benchmark's
    human, pseudo = by_name["train_human"].command, by_name["train_pseudo"].command
    assert [a.replace("human", "pseudo") for a in human] == pseudo  # data.labels=, model_<labels>
    assert _args_after(human, "--model_dir") == ["/o/model_human"]
    sets = _args_after(human, "--set")
    assert sets.index("data.point_bucket_base=8192") < sets.index("data.point_bucket_base=1024")
    assert {"train.num_steps=2", "train.seed=3", "data.source=pair_records"} <= set(sets)
    assert _args_after(human, "--data_dir") == ["/o/records/train_pseudo"]
    assert by_name["eval_pseudo"].outputs == ["/o/eval_pseudo"]
    assert _args_after(by_name["eval_pseudo"].command, "--checkpoint") == ["/o/model_pseudo"]
    ground = dataclasses.replace(OPTIONS, nsfp_ground_below_z_m=0.3).nsfp_sets()
    assert ground["remove_ground_below_z_m"] == 0.3


def test_summary_and_table_against_a_hand_calculation():
    outputs = job.StageOutputs({"human": HUMAN, "pseudo": PSEUDO, "zero_flow_human": ZERO,
                                "zero_flow_pseudo": dict(ZERO)}, NSFP_COUNTS, HISTORIES)
    scores = ({"all/moving/mean_l2_mps": 0.25, "all/stationary/mean_l2_mps": 0.15}, {}, {"pairs": 1})
    result = job.summary(OPTIONS, "cmd", outputs, scores, {"train_human": 1.0}, [])
    verdict = result["verdict"]
    assert verdict["pseudo_beats_zero_flow_on_moving"] is True  # 0.8 < 2.0
    assert verdict["pseudo_over_human_moving"] == 0.8 / 0.5  # 1.6
    assert verdict["pseudo_over_zero_flow_moving"] == 0.8 / 2.0  # 0.4
    assert verdict["fg_dynamic_epe_m"] == {"human": 0.05, "pseudo": 0.08, "zero_flow": None}
    assert result["zero_flow_same_in_both_evaluations"] is True  # NaN in both: the same empty cell
    assert set(result["eval_summary"]["human"]) == {"all/moving/mean_l2_mps", "all/stationary/mean_l2_mps",
                                                    "three_way/fg_dynamic_epe_m", "cyclist/moving/mean_l2_mps"}
    assert result["nsfp_job"]["seconds_per_fitted_pair"] == 2.5  # 10 s / 4 pairs
    assert result["nsfp_job"]["iterations_per_fitted_pair"] == 75  # 300 / 4
    assert result["training"]["human"] == {"last_logged_step": 2, "first_logged_loss": [1, 3.0],
                                           "last_logged_loss": [2, 2.5]}
    assert result["training"]["pseudo"]["last_logged_step"] is None
    assert result["options"]["set"][-1] == "data.point_bucket_base=1024"
    assert result["options"]["nsfp"]["ground_below_z_m"] is None
    assert job.json_without_nan(result)["eval_metrics"]["human"]["cyclist/moving/mean_l2_mps"] is None
    lines = job.table(result)
    assert lines[2].split() == ["FastFlow3D,", "NSFP", "pseudo-labels", "0.800", "0.200", "0.080"]
    assert lines[3].split() == ["zero", "flow", "2.000", "0.050", "nan"]
    assert lines[4].split()[-3:] == ["0.250", "0.150", "nan"]
    assert lines[-1] == "pseudo-trained beats zero flow on moving points: True"
    other_zero = dict(ZERO, **{"all/moving/mean_l2_mps": 2.1})
    outputs = job.StageOutputs({**outputs.eval_metrics, "zero_flow_pseudo": other_zero}, NSFP_COUNTS, HISTORIES)
    assert job.summary(OPTIONS, "cmd", outputs, scores, {}, [])["zero_flow_same_in_both_evaluations"] is False


def _write_pseudo_records(directory):
    """One pseudo-labelled pair record (WOD manifest) of 5 t0 points, the last outside the tiny grid (x = 60 m):
    human flow (1, 0, 0), 0, (2, 0, 0), (0.1, 0, 0) m/s; pseudo-flow off by 0.5, 0, 0, 0.3 m/s."""
    from ff3d_tf.data import pair_records
    from ff3d_tf.config import load_config
    d = load_config(None, TINY_OVERRIDES).data
    manifest = pair_records.Manifest(source="wod", laser_names=tuple(d.laser_names), returns=tuple(d.returns),
                                     max_frame_gap_s=d.max_frame_gap_s, extras=(schema.PSEUDO_FLOW_KEY,))
    pair_records.write_manifest(str(directory), manifest)
    xyz = np.array([[1, 1, 0], [2, 2, 0], [3, 3, 0], [4, 4, 0], [60, 0, 0]], np.float32)
    example = {
        "points_xyz_t0": xyz, "point_features_t0": np.zeros((5, 2), np.float32),
        "flow_mps_t0": np.array([[1, 0, 0], [0, 0, 0], [2, 0, 0], [0.1, 0, 0], [3, 0, 0]], np.float32),
        "class_id_t0": np.array([schema.CLASS_VEHICLE, schema.CLASS_BACKGROUND, schema.CLASS_VEHICLE,
                                 schema.CLASS_BACKGROUND, schema.CLASS_VEHICLE], np.int32),
        schema.PSEUDO_FLOW_KEY: np.array([[1, 0.5, 0], [0, 0, 0], [2, 0, 0], [0.4, 0, 0], [9, 9, 9]], np.float32),
        "points_xyz_tm1_in_t0": xyz[:3], "point_features_tm1": np.zeros((3, 2), np.float32),
        "pose_t0": np.eye(4), "pose_tm1": np.eye(4), pair_records.TIMESTAMP_KEY: 2_000_000_000,
        pair_records.PARTNER_TIMESTAMP_KEY: 1_900_000_000, pair_records.SEQUENCE_KEY: "seg"}
    pair_records.write_records_atomically(str(directory / pair_records.records_file_name("seg")),
                                          [pair_records.serialize_pair(example, extras=(schema.PSEUDO_FLOW_KEY,))])


def _check_scores(pseudo, zero, counts):
    """The 4 points in the grid: moving (speed >= 0.5 m/s) are rows 0 and 2, stationary rows 1 and 3."""
    np.testing.assert_allclose(pseudo["all/moving/mean_l2_mps"], (0.5 + 0.0) / 2, rtol=1e-6)
    np.testing.assert_allclose(pseudo["all/stationary/mean_l2_mps"], (0.0 + 0.3) / 2, rtol=1e-6)
    np.testing.assert_allclose(zero["all/moving/mean_l2_mps"], (1.0 + 2.0) / 2, rtol=1e-6)
    np.testing.assert_allclose(zero["all/stationary/mean_l2_mps"], (0.0 + 0.1) / 2, rtol=1e-6)
    assert pseudo["all/moving/count"] == 2 and pseudo["all/stationary/count"] == 2
    assert counts == {"pairs": 1, "points": 4, "points_with_pseudo_flow": 3}  # row 1's pseudo-flow is 0


def test_score_pseudo_labels_against_a_hand_calculation(tmp_path):
    from ff3d_tf.config import load_config
    _write_pseudo_records(tmp_path)
    cfg = load_config(None, TINY_OVERRIDES + ("data.source=pair_records",))
    files = [str(p) for p in tmp_path.glob("*.pairs.tfrecord")]
    _check_scores(*job.score_pseudo_labels(cfg, files))


FAKE_TOOL = """
import os, shutil, sys
args = sys.argv[1:]
out = args[args.index("--model_dir" if "--model_dir" in args else "--out_dir") + 1]
name = os.path.basename(__file__)[:-3]
with open(os.path.join({fixtures!r}, "calls.txt"), "a") as f:
    f.write(name + "\\n")
shutil.copytree(os.path.join({fixtures!r}, name), out, dirs_exist_ok=True)
"""


def test_run_over_stand_in_tools_writes_the_result_and_a_rerun_skips_every_stage(tmp_path):
    """Each tool replaced by a script that copies what the real one would write into its output folder."""
    fixtures, tools = tmp_path / "fixtures", tmp_path / "tools"
    tools.mkdir()
    for name in ("make_synthetic_data", "write_pair_records", "pseudo_label", "train", "eval"):
        (fixtures / name).mkdir(parents=True)
        (tools / f"{name}.py").write_text(textwrap.dedent(FAKE_TOOL.format(fixtures=str(fixtures))))
    _write_pseudo_records(fixtures / "pseudo_label")
    (fixtures / "pseudo_label" / "pseudo_label_counts.json").write_text(json.dumps(NSFP_COUNTS))
    (fixtures / "train" / "train_history.json").write_text(json.dumps(HISTORIES["human"]))
    (fixtures / "eval" / "metrics.json").write_text(json.dumps(PSEUDO))
    (fixtures / "eval" / "metrics_zero_flow.json").write_text(json.dumps(ZERO))
    options = dataclasses.replace(OPTIONS, sets=tuple(TINY_OVERRIDES))
    out, json_path, lines = str(tmp_path / "out"), str(tmp_path / "result.json"), []
    job.run(options, out, json_path, "the command", tools_dir=str(tools), log=lines.append)
    tools_in_plan_order = ["make_synthetic_data"] * 2 + ["write_pair_records"] * 2 + ["pseudo_label"] + \
        ["train"] * 2 + ["eval"] * 2
    assert (fixtures / "calls.txt").read_text().split() == tools_in_plan_order
    with open(json_path) as f:
        result = json.load(f)
    assert result["command"] == "the command" and result["stages_skipped_this_run"] == []
    assert set(result["timings_s"]) == set(job.PLAN) | {"score_pseudo_labels", "total_this_run"}
    assert result["eval_metrics"]["human"]["all/moving/mean_l2_mps"] == 0.8  # the eval fixture: PSEUDO's figures
    assert result["eval_metrics"]["zero_flow"]["cyclist/moving/mean_l2_mps"] is None  # NaN written as null
    labels = result["pseudo_labels"]
    _check_scores(labels["metrics"], labels["zero_flow_summary"], labels["points"])
    assert math.isclose(result["nsfp_job"]["iterations_per_fitted_pair"], 75)
    assert lines[-1].startswith(f"wrote {json_path}") and "pseudo-trained beats zero flow" in lines[-2]
    job.run(options, out, json_path, "the command", tools_dir=str(tools), log=lines.append)
    with open(json_path) as f:
        assert json.load(f)["stages_skipped_this_run"] == list(job.PLAN)
    assert len((fixtures / "calls.txt").read_text().split()) == len(job.PLAN)  # no tool ran again
    assert os.path.isdir(os.path.join(out, "stages"))
