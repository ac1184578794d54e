"""lab.training.heads_benchmark: the stage plan, the result and its table against hand calculations, and the job
run over stand-in tools (no TensorFlow)."""
import json
import math
import textwrap

import numpy as np

from conftest import TINY_OVERRIDES
from ff3d_tf import schema
from lab.training import heads_benchmark as job

OPTIONS = job.Options(config="c.yaml", sets=("data.point_bucket_base=1024",), steps=2, seed=3, formats=("wod", "av2"),
                      train_segments=1, eval_segments=1, frames_per_segment=3, lidar_scale=0.12,
                      av2_points_per_sweep=500)
# Eval figures of the hand calculations below (m/s; *_epe_m in m; bucketed normalized).
PAPER = {"all/moving/mean_l2_mps": 2.0, "all/stationary/mean_l2_mps": 0.2, "three_way/fg_dynamic_epe_m": 0.2,
         "three_way/mean_epe_m": 0.1, "bucketed/mean_dynamic": 0.8, "vehicle/moving/mean_l2_mps": 3.0}
GRU = {"all/moving/mean_l2_mps": 1.5, "all/stationary/mean_l2_mps": 0.3, "three_way/fg_dynamic_epe_m": 0.15,
       "three_way/mean_epe_m": 0.12, "bucketed/mean_dynamic": 0.6}
ZERO = {"all/moving/mean_l2_mps": 2.5, "all/stationary/mean_l2_mps": 0.0, "three_way/fg_dynamic_epe_m": 0.25,
        "three_way/mean_epe_m": 0.09, "bucketed/mean_dynamic": 1.0}
HISTORY = {"loss": [[1, 3.0], [2, 2.5]]}


def _args_after(command, flag):
    return [command[i + 1] for i, a in enumerate(command) if a == flag]


def test_stage_plan():
    plan = job.stage_plan(OPTIONS, "/o", tools_dir="/t")
    assert [s.name for s in plan] == list(job.plan_names(OPTIONS.formats))
    assert len(plan) == 2 * (4 + 2 * len(job.VARIANTS))  # per format: 2 generate, 2 records, train and eval each
    by_name = {s.name: s for s in plan}
    assert _args_after(by_name["generate_wod_eval"].command, "--seed") == ["900"]
    av2 = by_name["generate_av2_train"].command
    assert _args_after(av2, "--format") == ["av2"] and _args_after(av2, "--sweeps_per_log") == ["3"]
    assert _args_after(by_name["records_av2_train"].command, "--input") == ["/o/av2/data/train/train"]
    assert _args_after(by_name["records_wod_eval"].command, "--source") == ["wod"]
    # Every training: the same records, config and common sets (the user's after the benchmark's); only the
    # variant's own sets and its model_dir differ.
    paper, gru = by_name["train_wod_paper_l2"].command, by_name["train_wod_gru_deflow_augment"].command
    assert _args_after(paper, "--data_dir") == _args_after(gru, "--data_dir") == ["/o/wod/records/train"]
    common = OPTIONS.config_sets()
    assert _args_after(paper, "--set")[:len(common)] == _args_after(gru, "--set")[:len(common)] == common
    assert common.index("data.point_bucket_base=8192") < common.index("data.point_bucket_base=1024")
    assert _args_after(gru, "--set")[len(common):] == list(job.VARIANTS["gru_deflow_augment"])
    # The evaluations: the model's own head, the AV2 protocol on AV2 data only
    wod_eval, av2_eval = by_name["eval_wod_gru_l2"].command, by_name["eval_av2_gru_l2"].command
    assert "model.head=gru" in _args_after(wod_eval, "--set") and "--protocol" not in wod_eval
    assert _args_after(av2_eval, "--protocol") == ["av2"]
    assert _args_after(av2_eval, "--checkpoint") == ["/o/av2/model_gru_l2"]


def test_summary_and_table_against_a_hand_calculation():
    metrics = {v: (GRU if v.startswith("gru") else PAPER, ZERO) for v in job.VARIANTS}
    part = job.format_summary("wod", metrics, {v: HISTORY for v in job.VARIANTS})
    assert part["headline"]["paper_l2"]["moving_mps"] == 2.0 and part["headline"]["zero_flow"]["moving_mps"] == 2.5
    assert part["headline"]["gru_l2"]["bucketed_dynamic_norm_epe"] == 0.6  # WOD: bucketed/mean_dynamic
    assert part["headline"]["gru_l2"]["bg_static_epe_m"] is None  # not in the eval's figures
    # GRU over paper: moving 1.5 / 2.0 = 0.75; stationary 0.3 / 0.2 = 1.5; mean three-way 0.12 / 0.1 = 1.2
    ratios = part["versus_paper_l2"]["gru_deltaflow"]
    assert math.isclose(ratios["moving_mps"], 0.75) and math.isclose(ratios["stationary_mps"], 1.5)
    assert math.isclose(ratios["three_way_mean_epe_m"], 1.2)
    assert part["versus_paper_l2"]["zero_flow"]["stationary_mps"] == 0.0  # 0.0 / 0.2
    assert part["best_on_moving"] == "gru_l2"  # 1.5 < 2.0; the first of the equal GRU variants
    assert all(part["beats_zero_flow_on_moving"].values())  # 2.0 and 1.5 < 2.5
    assert part["per_class_mps"]["paper_l2"]["vehicle/moving/mean_l2_mps"] == 3.0
    assert part["per_class_mps"]["zero_flow"]["vehicle/moving/mean_l2_mps"] is None
    assert part["zero_flow_same_in_every_evaluation"]
    assert part["training"]["gru_l2"]["last_logged_loss"] == [2, 2.5]
    lines = job.table({"formats": {"wod": part}})
    assert lines[1] == "|---|---|---:|---:|---:|---:|---:|"
    assert lines[2] == "| wod | paper head + L2 | 2.000 | 0.200 | 0.200 | 0.100 | 0.800 |"
    assert lines[-1] == "| wod | zero flow | 2.500 | 0.000 | 0.250 | 0.090 | 1.000 |"
    assert len(lines) == 2 + len(job.VARIANTS) + 1


def test_av2_metrics_merge_the_challenge_over_the_paper_tables(tmp_path):
    (tmp_path / "metrics_av2.json").write_text(json.dumps({
        "model": {"three_way/mean_epe_m": 0.07, "bucketed/mean_dynamic_norm_epe": 0.5},
        "zero_flow": {"three_way/mean_epe_m": 0.09, "bucketed/mean_dynamic_norm_epe": 1.0},
        "paper_model": {"all/moving/mean_l2_mps": 1.0, "three_way/mean_epe_m": 0.3},
        "paper_zero_flow": {"all/moving/mean_l2_mps": 2.0}}))
    model, zero = job.eval_metrics(str(tmp_path), "av2")
    # the challenge's three-way EPE (0.07, over its eval mask) wins over the paper tables' own (0.3)
    assert job.headline(model, "av2")["three_way_mean_epe_m"] == 0.07
    assert job.headline(model, "av2")["bucketed_dynamic_norm_epe"] == 0.5
    assert job.headline(zero, "av2")["moving_mps"] == 2.0


def test_pillar_sharing_against_a_hand_calculation(tmp_path):
    """One pair record (WOD manifest) of 6 t0 points on the tiny grid (32 x 32 pillars of 2.5 m over +-40 m)."""
    from ff3d_tf.config import load_config
    from ff3d_tf.data import pair_records
    cfg = load_config(None, TINY_OVERRIDES + ("data.source=pair_records",))
    d = cfg.data
    pair_records.write_manifest(str(tmp_path), pair_records.Manifest(
        source="wod", laser_names=tuple(d.laser_names), returns=tuple(d.returns), max_frame_gap_s=d.max_frame_gap_s))
    # pillar (x, y) = floor((x + 40) / 2.5): A (1, 1) and B (1.5, 1.5) -> (16, 16); C (10, 10) and D (10.5, 10.2)
    # -> (20, 20); E (-20, -20) -> (8, 8); F x = 60 m: outside the grid.
    xyz = np.array([[1, 1, 0], [1.5, 1.5, 0], [10, 10, 0], [10.5, 10.2, 0], [-20, -20, 0], [60, 0, 0]], np.float32)
    # speeds 1, 0, 2, 0.6, 0.1, 3 m/s: moving (>= 0.5) A, C, D (and F, outside)
    speed = np.array([1, 0, 2, 0.6, 0.1, 3], np.float32)
    example = {
        "points_xyz_t0": xyz, "point_features_t0": np.zeros((6, 2), np.float32),
        "flow_mps_t0": np.stack([speed, np.zeros(6), np.zeros(6)], axis=1).astype(np.float32),
        "class_id_t0": np.full(6, schema.CLASS_VEHICLE, np.int32),
        "points_xyz_tm1_in_t0": xyz[:3], "point_features_tm1": np.zeros((3, 2), np.float32),
        "pose_t0": np.eye(4), "pose_tm1": np.eye(4), pair_records.TIMESTAMP_KEY: 2_000_000_000,
        pair_records.PARTNER_TIMESTAMP_KEY: 1_900_000_000, pair_records.SEQUENCE_KEY: "seg"}
    path = str(tmp_path / pair_records.records_file_name("seg"))
    pair_records.write_records_atomically(path, [pair_records.serialize_pair(example)])
    found = job.pillar_sharing(cfg, [path])
    # 5 points in the grid; moving A, C, D; pillars with a mover (16, 16) and (20, 20); shared by a stationary
    # point only (16, 16) (B), holding 1 of the 3 movers (A)
    assert {k: found[k] for k in ("pairs", "points_in_grid", "moving_points", "moving_points_in_shared_pillars",
                                  "pillars_with_moving_points", "shared_pillars")} == {
        "pairs": 1, "points_in_grid": 5, "moving_points": 3, "moving_points_in_shared_pillars": 1,
        "pillars_with_moving_points": 2, "shared_pillars": 1}
    assert math.isclose(found["share_of_moving_points_in_shared_pillars"], 1 / 3)
    assert found["share_of_moving_pillars_shared"] == 0.5  # 1 / 2


FAKE_TOOL = """
import os, shutil, sys
args = sys.argv[1:]
out = args[args.index("--model_dir" if "--model_dir" in args else "--out_dir") + 1]
with open(os.path.join({fixtures!r}, "calls.txt"), "a") as f:
    f.write(os.path.basename(__file__)[:-3] + "\\n")
shutil.copytree(os.path.join({fixtures!r}, os.path.basename(__file__)[:-3]), out, dirs_exist_ok=True)
"""


def test_run_over_stand_in_tools_writes_the_result_and_a_rerun_skips_every_stage(tmp_path, monkeypatch):
    """Each tool replaced by a script that copies what the real one would write into its output folder (the records:
    one empty file, counted by a stand-in `pillar_sharing`)."""
    monkeypatch.setattr(job, "pillar_sharing", lambda cfg, files: {"files": len(files)})
    fixtures, tools = tmp_path / "fixtures", tmp_path / "tools"
    tools.mkdir()
    for name in ("make_synthetic_data", "write_pair_records", "train", "eval"):
        (fixtures / name).mkdir(parents=True)
        (tools / f"{name}.py").write_text(textwrap.dedent(FAKE_TOOL.format(fixtures=str(fixtures))))
    (fixtures / "train" / "train_history.json").write_text(json.dumps(HISTORY))
    (fixtures / "write_pair_records" / "seg.tfrecord").write_text("")
    (fixtures / "eval" / "metrics.json").write_text(json.dumps(GRU))
    (fixtures / "eval" / "metrics_zero_flow.json").write_text(json.dumps(ZERO))
    options = job.Options(**{**OPTIONS.__dict__, "formats": ("wod",), "config": ""})  # "": built-in defaults
    out, json_path, lines = str(tmp_path / "out"), str(tmp_path / "result.json"), []
    job.run(options, out, json_path, "the command", tools_dir=str(tools), log=lines.append)
    assert (fixtures / "calls.txt").read_text().split() == ["make_synthetic_data"] * 2 + \
        ["write_pair_records"] * 2 + ["train"] * len(job.VARIANTS) + ["eval"] * len(job.VARIANTS)
    with open(json_path) as f:
        result = json.load(f)
    assert result["command"] == "the command" and result["stages_skipped_this_run"] == []
    assert result["cpu"]["cpu_count"] and len(result["stage_commands"]) == len(job.plan_names(("wod",)))
    assert "make_synthetic_data.py --out_dir" in result["stage_commands"][0]
    assert result["pillar_sharing_training_records"] == {"wod": {"files": 1}}
    assert result["formats"]["wod"]["headline"]["paper_l2"]["moving_mps"] == 1.5  # the eval fixture: GRU's figures
    assert lines[-1].startswith(f"wrote {json_path}") and "\n| wod | zero flow |" in lines[-2]
    job.run(options, out, json_path, "the command", tools_dir=str(tools), log=lines.append)
    with open(json_path) as f:
        assert json.load(f)["stages_skipped_this_run"] == list(job.plan_names(("wod",)))
