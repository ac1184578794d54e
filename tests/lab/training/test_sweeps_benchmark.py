"""lab/training/sweeps_benchmark.py without training: the stages it plans (records per number of sweeps and their
full and filled parts, a run per variant and seed on the full part of its sweeps, the planted defect through the
lab's runner), the parts by hand, the spread over seeds by hand, when two variants count as apart, and when the
planted defect counts as caught."""
import os

import pytest
import tensorflow as tf

from ff3d_tf.data import pair_records
from lab.training import sweeps_benchmark as sb


def _options(**changes):
    base = dict(config="configs/synthetic_cpu.yaml", sets=("train.learning_rate=1e-3",), steps=7, seeds=(0, 1, 2),
                formats=("wod",), train_segments=2, eval_segments=1, frames_per_segment=6, lidar_scale=0.12,
                av2_points_per_sweep=1000)
    return sb.Options(**{**base, **changes})


def test_stage_plan_writes_records_per_sweeps_and_runs_every_variant_and_seed(tmp_path):
    plan = sb.stage_plan(_options(), str(tmp_path))
    names = [s.name for s in plan]
    assert [n for n in names if n.startswith("records_")] == [
        f"records_wod_{split}_{n}" for n in (2, 3, 5) for split in ("train", "eval")]
    # every number of sweeps split at the same rank: 5 sweeps read t0, its partner and 3 more
    subsets = [s for s in plan if s.name.startswith("subset_") and not any(f"_{job}_" in s.name
                                                                           for job in sb.PREPARATIONS)]
    assert [s.name for s in subsets] == [f"subset_wod_{sp}_{part}_{n}" for n in (2, 3, 5)
                                         for sp, part in (("train", "full"), ("eval", "full"), ("eval", "filled"))]
    assert all(s.command[-1].endswith(":3") for s in subsets)
    trains = [s for s in plan if s.name.startswith("train_")]
    assert len(trains) == len(sb.VARIANTS) * 3
    assert len([s for s in plan if s.name.startswith("eval_")]) == len(sb.VARIANTS) * 3 * 2
    delta_5 = next(s for s in plan if s.name == "train_wod_delta_5_2")
    command = " ".join(delta_5.command)
    assert "--set data.num_frames=5" in command and "--set model.temporal=delta" in command
    assert "--set train.seed=2" in command and f"{tmp_path}/wod/records_5/train_full" in command
    assert delta_5.command[0].endswith("tools/train.py")
    planted = next(s for s in plan if s.name == "train_wod_delta_5_reversed_0")
    assert planted.command[0].endswith("lab/tools/run_planted.py") and planted.command[1].endswith("tools/train.py")
    assert "model.temporal=delta_reversed" in " ".join(planted.command)
    # the user's overrides come after the benchmark's own, the variant's after both
    assert command.index("train.learning_rate=1e-3") < command.index("data.num_frames=5")
    records_5 = next(s for s in plan if s.name == "records_wod_train_5")
    assert "data.num_frames=5" in " ".join(records_5.command)


def test_variants_without_labels_or_ground_train_on_their_prepared_records(tmp_path):
    """NSFP's pseudo-labels, self-supervision's fields and (on WOD, whose records carry none) every sweep's ground mask
    are added once per split's records, whole (DUFOMap reads every sweep of a log), before those are cut into the
    parts the runs read; the labels a variant trains on are set for its training only (its evaluation scores human
    labels)."""
    plan = sb.stage_plan(_options(formats=("wod", "av2")), str(tmp_path))
    prepare = {s.name: s for s in plan if s.name.startswith("prepare_")}
    assert sorted(prepare) == sorted(
        [f"prepare_{fmt}_train_{job}" for fmt in ("wod", "av2") for job in ("pseudo_2", "self_2", "self_5")] +
        ["prepare_wod_train_ground_5", "prepare_wod_eval_ground_5"])
    ground = prepare["prepare_wod_eval_ground_5"]
    assert ground.command[0].endswith("tools/add_ground_masks.py")
    assert ground.command[-4:] == ["--input", f"{tmp_path}/wod/records_5/eval", "--out_dir",
                                   f"{tmp_path}/wod/records_5/eval_ground"]
    filled = next(s for s in plan if s.name == "subset_wod_eval_filled_ground_5")
    assert filled.command[-3:] == [f"{tmp_path}/wod/records_5/eval_ground",
                                   f"{tmp_path}/wod/records_5/eval_filled_ground", "filled:3"]
    names = [s.name for s in plan]
    assert names.index("prepare_wod_train_self_5") < names.index("subset_wod_train_full_self_5") < \
        names.index("train_wod_teflow_5_0")
    by_name = {s.name: " ".join(s.command) for s in plan}
    teflow = by_name["train_wod_teflow_5_1"]
    assert "--set data.labels=self --set train.loss=teflow" in teflow
    assert f"--data_dir {tmp_path}/wod/records_5/train_full_self " in teflow
    assert "data.labels" not in by_name["eval_wod_teflow_5_1_full"]
    assert f"--data_dir {tmp_path}/wod/records_5/eval_full " in by_name["eval_wod_teflow_5_1_full"]
    assert "records_5/eval_full_ground " in by_name["eval_wod_delta_5_no_ground_0_full"]
    assert "records_5/eval_full " in by_name["eval_av2_delta_5_no_ground_0_full"]  # the raster's masks
    assert "--set data.labels=pseudo" in by_name["train_av2_nsfp_pair_2"]
    assert by_name["prepare_av2_train_pseudo_2"].split()[0].endswith("tools/pseudo_label.py")


def test_spread_and_apart_by_hand():
    s = sb.spread([1.0, 2.0, 4.0, None])
    # mean 7/3; sample variance ((1-7/3)^2 + (2-7/3)^2 + (4-7/3)^2) / 2 = (16/9 + 1/9 + 25/9) / 2 = 7/3
    assert s["mean"] == pytest.approx(7 / 3) and s["std"] == pytest.approx((7 / 3) ** 0.5)
    assert (s["min"], s["max"], s["n"]) == (1.0, 4.0, 3)
    a, b = sb.spread([1.0, 1.2]), sb.spread([2.0, 2.5])
    assert sb.apart(a, b) == pytest.approx({"difference": 1.15, "largest_range": 0.5, "apart": True})
    # means 1.1 and 1.35 are 0.25 apart; the ranges are 0.2 and 0.4: not apart
    assert not sb.apart(a, sb.spread([1.15, 1.55]))["apart"]


def _per_seed(figures: dict) -> dict:
    """{variant: [{figure: value}] per seed} with every other headline figure None."""
    return {v: [{name: seed.get(name) for name in sb.HEADLINE_KEYS} for seed in seeds] for v, seeds in figures.items()}


def test_format_summary_picks_the_best_and_compares_it_with_the_paper_on_each_figure():
    per_seed = _per_seed({
        "paper_pair": [{"moving_mps": v, "bucketed_dynamic_norm_epe": b} for v, b in [(2.0, .6), (2.1, .7), (2.2, .8)]],
        "delta_3": [{"moving_mps": v, "bucketed_dynamic_norm_epe": .3} for v in (1.0, 1.5, 1.1)],
        "stack_3": [{"moving_mps": 3.0, "bucketed_dynamic_norm_epe": b} for b in (.1, .2, .3)]})
    zero = {name: {"moving_mps": 5.0, "bucketed_dynamic_norm_epe": 1.0}.get(name) for name in sb.HEADLINE_KEYS}
    summary = sb.format_summary(per_seed, zero)
    assert summary["best_on_moving"] == "delta_3"
    moving = summary["separations"]["moving_mps"]
    assert moving["best_variant"] == "delta_3"
    assert moving["zero_flow_vs_paper_pair"]["apart"]  # 5.0 vs 2.1, ranges 0 and 0.2
    versus = moving["paper_pair_vs_best_variant"]
    # |2.1 - 3.6 / 3| = 0.9 against the larger range, delta_3's 0.5: apart
    assert versus["difference"] == pytest.approx(2.1 - 3.6 / 3) and versus["largest_range"] == pytest.approx(0.5)
    assert versus["apart"]
    # the board's figure has its own best variant: stack_3 (mean 0.2) before delta_3 (0.3); |0.7 - 0.2| = 0.5
    # against the larger range, 0.2 for both: apart; zero flow's 1.0 against the paper's 0.7, range 0.2: apart
    bucketed = summary["separations"]["bucketed_dynamic_norm_epe"]
    assert bucketed["best_variant"] == "stack_3"
    assert bucketed["paper_pair_vs_best_variant"] == pytest.approx(
        {"difference": 0.5, "largest_range": 0.2, "apart": True})
    assert bucketed["zero_flow_vs_paper_pair"] == pytest.approx(
        {"difference": 0.3, "largest_range": 0.2, "apart": True})


def test_the_best_variant_is_compared_with_the_paper_also_when_the_paper_is_best():
    heads = {"paper_pair": [1.0, 1.1, 1.2], "delta_3": [3.0, 2.0, 2.4], "delta_5": [2.5, 2.4, 2.3, 2.4]}
    per_seed = _per_seed({k: [{"moving_mps": v} for v in values] for k, values in heads.items()})
    zero = {name: (5.0 if name == "moving_mps" else None) for name in sb.HEADLINE_KEYS}
    summary = sb.format_summary(per_seed, zero)
    moving = summary["separations"]["moving_mps"]
    assert (summary["best_on_moving"], moving["best_variant"]) == ("paper_pair", "delta_5")  # means 1.1, 2.47, 2.4
    versus = moving["paper_pair_vs_best_variant"]
    # |1.1 - 2.4| = 1.3 against the larger of the two ranges, delta_3's (1.0) not counted: max(0.2, 0.2) = 0.2
    assert versus["difference"] == pytest.approx(1.3) and versus["largest_range"] == pytest.approx(0.2)
    # a figure no run has: no best variant, nothing apart
    bucketed = summary["separations"]["bucketed_dynamic_norm_epe"]
    assert bucketed["best_variant"] is None and not bucketed["zero_flow_vs_paper_pair"]["apart"]
    # summarized again from the per-seed figures a JSON keeps: the same summary, the command recorded
    again = sb.summarize_again({"formats": {"wod": summary}, "command": "run"}, "again")
    assert again["formats"]["wod"] == {**summary, "instrument": {}} and again["summarized_again_by"] == "again"


def _metadata_records(path, log_ids_and_stamps):
    """A pair-records file of records holding only the scalars `subset_records` reads."""
    def record(log_id, stamp):
        return tf.train.Example(features=tf.train.Features(feature={
            pair_records.SEQUENCE_KEY: tf.train.Feature(bytes_list=tf.train.BytesList(value=[log_id.encode()])),
            pair_records.TIMESTAMP_KEY: tf.train.Feature(int64_list=tf.train.Int64List(value=[stamp]))}
        )).SerializeToString()
    pair_records.write_records_atomically(path, [record(*k) for k in log_ids_and_stamps])


def test_subset_records_splits_each_log_at_the_rank_of_its_t0_sweep(tmp_path):
    """Log a: t0 stamps 30, 10, 20, 40 in file order (ranks 2, 0, 1, 3); log b: 5, 6 (ranks 0, 1). Rank 2: full keeps
    a's 30 and 40, filled keeps a's 10, 20 and all of b, each file in its own order, bytes unchanged."""
    source = tmp_path / "src"
    source.mkdir()
    pair_records.write_manifest(str(source), pair_records.Manifest(
        source="av2", laser_names=(1, 2), returns=(1,), max_frame_gap_s=0.15, partner="next", num_frames=5))
    _metadata_records(str(source / ("a" + pair_records.FILE_SUFFIX)), [("a", 30), ("a", 10), ("a", 20), ("a", 40)])
    _metadata_records(str(source / ("b" + pair_records.FILE_SUFFIX)), [("b", 5), ("b", 6)])

    def stamps(directory, name):
        return [k[1] for k in sb._t0_keys(os.path.join(directory, name + pair_records.FILE_SUFFIX), "none")]
    assert sb.subset_records(str(source), str(tmp_path / "full"), "full", 2) == {"kept": 2, "of": 6}
    assert sb.subset_records(str(source), str(tmp_path / "filled"), "filled", 2) == {"kept": 4, "of": 6}
    assert stamps(tmp_path / "full", "a") == [30, 40] and stamps(tmp_path / "full", "b") == []
    assert stamps(tmp_path / "filled", "a") == [10, 20] and stamps(tmp_path / "filled", "b") == [5, 6]
    assert pair_records.read_manifest(str(tmp_path / "full")) == pair_records.read_manifest(str(source))


def test_the_planted_defect_is_caught_only_when_worse_beyond_the_spread():
    """delta_5 moving 1.0, 1.1, 1.2 (range 0.2); reversed 1.5, 1.6, 1.7: 0.5 apart and worse: caught. Reversed 1.0,
    1.15, 1.3 (range 0.3): 0.05 apart: not caught. Reversed better: never caught, apart or not."""
    def rows(corrected, planted):
        return {sb.CORRECTED: {f: sb.spread(corrected) for f in sb.SEPARATION_FIGURES},
                sb.PLANTED: {f: sb.spread(planted) for f in sb.SEPARATION_FIGURES}}
    caught = sb.instrument(rows([1.0, 1.1, 1.2], [1.5, 1.6, 1.7]))["moving_mps"]
    assert caught["caught"] and caught["planted_worse"] and caught["difference"] == pytest.approx(0.5)
    assert not sb.instrument(rows([1.0, 1.1, 1.2], [1.0, 1.15, 1.3]))["moving_mps"]["caught"]
    better = sb.instrument(rows([1.5, 1.6, 1.7], [1.0, 1.1, 1.2]))["moving_mps"]
    assert better["apart"] and not better["planted_worse"] and not better["caught"]
    assert sb.instrument({sb.CORRECTED: {}}) == {}
    one_seed = sb.instrument(rows([1.0], [2.0]))["moving_mps"]  # apart by 1.0 against no spread: not evidence
    assert one_seed["planted_worse"] and one_seed["apart"] and not one_seed["caught"]
