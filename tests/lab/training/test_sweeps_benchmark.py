"""lab/training/sweeps_benchmark.py without training: the stages it plans (records per number of sweeps, a run per
variant and seed on the records of its sweeps), the spread over seeds by hand, and when two variants count as apart."""
import pytest

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
    trains = [s for s in plan if s.name.startswith("train_")]
    assert len(trains) == len(sb.VARIANTS) * 3
    delta_5 = next(s for s in plan if s.name == "train_wod_delta_5_2")
    command = " ".join(delta_5.command)
    assert "--set data.num_frames=5" in command and "--set model.temporal=delta" in command
    assert "--set train.seed=2" in command and f"{tmp_path}/wod/records_5/train" in command
    # the user's overrides come after the benchmark's own, the variant's after both
    assert command.index("train.learning_rate=1e-3") < command.index("data.num_frames=5")
    records_5 = next(s for s in plan if s.name == "records_wod_train_5")
    assert "data.num_frames=5" in " ".join(records_5.command)


def test_spread_and_apart_by_hand():
    s = sb.spread([1.0, 2.0, 4.0, None])
    # mean 7/3; sample variance ((1-7/3)^2 + (2-7/3)^2 + (4-7/3)^2) / 2 = (16/9 + 1/9 + 25/9) / 2 = 7/3
    assert s["mean"] == pytest.approx(7 / 3) and s["std"] == pytest.approx((7 / 3) ** 0.5)
    assert (s["min"], s["max"], s["n"]) == (1.0, 4.0, 3)
    a, b = sb.spread([1.0, 1.2]), sb.spread([2.0, 2.5])
    assert sb.apart(a, b) == pytest.approx({"difference": 1.15, "largest_range": 0.5, "apart": True})
    # means 1.1 and 1.35 are 0.25 apart; the ranges are 0.2 and 0.4: not apart
    assert not sb.apart(a, sb.spread([1.15, 1.55]))["apart"]


def test_format_summary_picks_the_best_and_compares_it_with_the_paper():
    heads = {"paper_pair": [{"moving_mps": v} for v in (2.0, 2.1, 2.2)],
             "delta_3": [{"moving_mps": v} for v in (1.0, 1.5, 1.1)]}
    per_seed = {k: [{name: h.get(name) for name in sb.HEADLINE_KEYS} for h in rows] for k, rows in heads.items()}
    summary = sb.format_summary(per_seed, {name: (5.0 if name == "moving_mps" else None) for name in sb.HEADLINE_KEYS})
    assert summary["best_on_moving"] == "delta_3"
    assert summary["separations"]["zero_flow_vs_paper_pair"]["apart"]  # 5.0 vs 2.1, ranges 0 and 0.2
    versus = summary["separations"]["paper_pair_vs_best_delta_3"]
    assert versus["difference"] == pytest.approx(2.1 - 3.6 / 3) and versus["largest_range"] == pytest.approx(0.5)
    assert versus["apart"]
    assert summary["best_variant"] == "delta_3"


def test_the_best_variant_is_compared_with_the_paper_also_when_the_paper_is_best():
    heads = {"paper_pair": [1.0, 1.1, 1.2], "delta_3": [3.0, 2.0, 2.4], "delta_5": [2.5, 2.4, 2.3, 2.4]}
    per_seed = {k: [{name: (v if name == "moving_mps" else None) for name in sb.HEADLINE_KEYS} for v in values]
                for k, values in heads.items()}
    zero = {name: (5.0 if name == "moving_mps" else None) for name in sb.HEADLINE_KEYS}
    summary = sb.format_summary(per_seed, zero)
    assert (summary["best_on_moving"], summary["best_variant"]) == ("paper_pair", "delta_5")  # means 1.1, 2.47, 2.4
    versus = summary["separations"]["paper_pair_vs_best_delta_5"]
    # |1.1 - 2.4| = 1.3 against the larger of the two ranges, delta_3's (1.0) not counted: max(0.2, 0.2) = 0.2
    assert versus["difference"] == pytest.approx(1.3) and versus["largest_range"] == pytest.approx(0.2)
    # summarized again from the per-seed figures a JSON keeps: the same summary, the command recorded
    again = sb.summarize_again({"formats": {"wod": summary}, "command": "run"}, "again")
    assert again["formats"]["wod"] == summary and again["summarized_again_by"] == "again"
