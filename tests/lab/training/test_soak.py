"""lab.training.soak: the fault schedule, the per-fault measurements from made-up output and timelines, the hang and
lost-checkpoint rules, the summary, the end comparisons, and one short soak of the trainers end to end."""
import json
import os
import random
import signal

import numpy as np
import pytest
import tensorflow as tf

from ff3d_tf import cpu
from ff3d_tf.config import ConfigError
from ff3d_tf.training.cluster import EXIT_PEER_LOST, EXIT_PREEMPTED
from lab.training import soak
from lab.training.soak import Ending


# -- the fault schedule ------------------------------------------------------------------------------------------------
def test_fault_targets_by_kind_and_service():
    assert soak.fault_targets(("trainer",), False, 2) == ["trainer0", "trainer1"]
    assert soak.fault_targets(soak.TARGET_KINDS, True, 3) == ["trainer0", "trainer1", "dispatcher", "input0",
                                                              "input1", "input2"]
    assert soak.fault_targets(soak.TARGET_KINDS, False, 3) == ["trainer0", "trainer1"]  # no service: trainers only
    assert soak.fault_targets(("input",), True, 1) == ["input0"]
    with pytest.raises(soak.SoakError, match="no target"):
        soak.fault_targets(("dispatcher", "input"), False, 2)
    with pytest.raises(soak.SoakError, match="unknown target kinds"):
        soak.fault_targets(("trainer", "disk"), False, 2)


def test_fault_schedule_replays_for_a_seed_in_its_documented_order():
    targets = ["trainer0", "trainer1", "dispatcher"]

    def draws(schedule, n=12):
        return [(schedule.next_gap_s(), *schedule.next_fault(targets)) for _ in range(n)]

    first = draws(soak.FaultSchedule(7, (1.0, 3.0), 0.5))
    assert first == draws(soak.FaultSchedule(7, (1.0, 3.0), 0.5))
    assert first != draws(soak.FaultSchedule(8, (1.0, 3.0), 0.5))
    # The order: per fault a uniform gap, then a uniform target, then one uniform number below the SIGTERM share.
    rng = random.Random(7)
    expected = []
    for _ in range(12):
        gap_s, target = rng.uniform(1.0, 3.0), rng.choice(targets)
        expected.append((gap_s, target, signal.SIGTERM if rng.random() < 0.5 else signal.SIGKILL))
    assert first == expected
    assert all(1.0 <= gap_s <= 3.0 for gap_s, _, _ in first)
    # A share of 0 never sends SIGTERM (random() < 0 is never true); of 1 always (random() < 1 always is).
    assert {sig for _, _, sig in draws(soak.FaultSchedule(7, (1.0, 3.0), 0.0))} == {signal.SIGKILL}
    assert {sig for _, _, sig in draws(soak.FaultSchedule(7, (1.0, 3.0), 1.0))} == {signal.SIGTERM}


def test_fault_kind_drops_the_index():
    assert soak.fault_kind("SIGKILL", "trainer1") == "SIGKILL trainer"
    assert soak.fault_kind("SIGTERM", "input12") == "SIGTERM input"
    assert soak.fault_kind("SIGTERM", "dispatcher") == "SIGTERM dispatcher"


# -- reading the processes' output -------------------------------------------------------------------------------------
CHIEF_LINES = [
    (1.0, "training on 2 segment files; model_dir /tmp/m"),
    (2.0, "resumed from /tmp/m/checkpoints/ckpt-20 at step 20"),
    (3.0, "step 21/10000000 loss 0.5000 1.00 steps/s"),
    (3.5, "[worker] step 22/10000000 loss 0.2500 1.00 steps/s"),
    (4.0, "preempted at step 22 (signal to worker 1); every worker saved step 22"),
    (4.1, "error: something else"),
    (4.2, "a line after"),
]


def test_step_lines_since_a_time():
    assert soak.step_lines(CHIEF_LINES) == [(3.0, 21, 0.5), (3.5, 22, 0.25)]
    assert soak.step_lines(CHIEF_LINES, since_s=3.5) == [(3.5, 22, 0.25)]  # at `since_s` counts
    assert soak.step_lines(CHIEF_LINES, since_s=3.6) == []


def test_newest_step_counts_steps_and_resumes():
    # Trainer 0 logged step 22; trainer 1 only resumed, from 30 (a newer checkpoint than any step logged): 30.
    other = [(2.0, "resumed from /tmp/m/checkpoints/ckpt-30 at step 30")]
    assert soak.newest_step([CHIEF_LINES, other]) == 30
    assert soak.newest_step([CHIEF_LINES]) == 22
    assert soak.newest_step([[], [(1.0, "starting")]]) == 0


def test_messages_and_matches():
    assert soak.last_message(CHIEF_LINES) == "error: something else"  # the last of the lines that say how it ended
    assert soak.last_message(CHIEF_LINES[:5]).startswith("preempted at step 22")
    assert soak.last_message(CHIEF_LINES[:3]) == ""
    assert soak.last_message([(0.0, "error: " + "x" * 1000)]) == "error: " + "x" * (soak.MESSAGE_CHARS - 7)
    assert int(soak.first_match(CHIEF_LINES, soak.PREEMPTED_LINE)[1]) == 22
    assert int(soak.first_match(CHIEF_LINES, soak.RESUMED_LINE)[1]) == 20
    assert soak.first_match(CHIEF_LINES[:1], soak.RESUMED_LINE) is None


def test_checkpoint_state_step():
    state = 'model_checkpoint_path: "ckpt-40"\nall_model_checkpoint_paths: "ckpt-30"\n' \
            'all_model_checkpoint_paths: "ckpt-40"\n'
    assert soak.checkpoint_state_step(state) == 40
    assert soak.checkpoint_state_step("") == 0


# -- the measurements of one fault -------------------------------------------------------------------------------------
def test_expected_trainer_exits():
    assert soak.expected_trainer_exits(signal.SIGTERM, 1) == [EXIT_PREEMPTED, EXIT_PREEMPTED]
    assert soak.expected_trainer_exits(signal.SIGKILL, 1) == [EXIT_PEER_LOST, -signal.SIGKILL]
    assert soak.expected_trainer_exits(signal.SIGKILL, 0) == [-signal.SIGKILL, EXIT_PEER_LOST]


def test_trainer_fault_measurements():
    # SIGKILL to trainer1 at 10.0 s: it is gone at 10.2 s, trainer0 notices and exits 69 at 10.7 s.
    # detect_s = the last end - the fault = 10.7 - 10.0 = 0.7.
    endings = [Ending("trainer0", EXIT_PEER_LOST, True, 10.7), Ending("trainer1", -signal.SIGKILL, True, 10.2)]
    assert soak.trainer_fault_measurements(signal.SIGKILL, 1, endings, 10.0) == {
        "detect_s": 0.7, "exit_codes": [EXIT_PEER_LOST, -signal.SIGKILL], "hung": [], "as_expected": True}
    # SIGTERM to trainer0 at 5.0 s: both preempted, the last at 13.84 s: detect_s = 8.84.
    endings = [Ending("trainer0", EXIT_PREEMPTED, True, 13.0), Ending("trainer1", EXIT_PREEMPTED, True, 13.84)]
    assert soak.trainer_fault_measurements(signal.SIGTERM, 0, endings, 5.0)["as_expected"]
    # The hang rule: trainer0 did not end by itself within its bound (killed then: -9 at 160.0 s): it hung, and a
    # fault with a hang is not as expected even had its exits been.
    endings = [Ending("trainer0", -signal.SIGKILL, False, 160.0), Ending("trainer1", -signal.SIGKILL, True, 10.1)]
    got = soak.trainer_fault_measurements(signal.SIGKILL, 1, endings, 10.0)
    assert got["hung"] == ["trainer0"] and got["detect_s"] == 150.0 and not got["as_expected"]
    # SIGKILL as expected but trainer0 exited 1 (a plain error, not a lost peer): not as expected, no hang.
    endings = [Ending("trainer0", 1, True, 11.0), Ending("trainer1", -signal.SIGKILL, True, 10.1)]
    got = soak.trainer_fault_measurements(signal.SIGKILL, 1, endings, 10.0)
    assert got["hung"] == [] and not got["as_expected"]


def test_service_fault_measurements():
    # SIGTERM to input0 at 163.07 s, ended by itself at 167.81 s: detect_s = 4.74.
    assert soak.service_fault_measurements(Ending("input0", 0, True, 167.81), 163.07) == {
        "detect_s": 4.74, "exit_codes": [0], "hung": []}
    assert soak.service_fault_measurements(Ending("dispatcher", -9, False, 200.0), 170.0)["hung"] == ["dispatcher"]


def test_restart_measurements_and_the_lost_checkpoint_rule():
    # Fault at 100.0 s at step 27; the newest complete checkpoint then: 20; the restart resumed from 20 and logged
    # its first step at 131.5 s. steps_lost = 27 - 20 = 7, resume_s = 131.5 - 100.0 = 31.5, no checkpoint lost.
    assert soak.restart_measurements(27, 20, 20, 100.0, 131.5, []) == {
        "newest_complete_checkpoint": 20, "resumed_from_step": 20, "steps_lost": 7, "lost_checkpoint": False,
        "resume_s": 31.5}
    # Resumed from 10 though 20 was complete: a lost checkpoint; steps_lost = 27 - 10 = 17.
    got = soak.restart_measurements(27, 20, 10, 100.0, 131.5, [])
    assert got["lost_checkpoint"] and got["steps_lost"] == 17
    # Resumed from a checkpoint newer than the step seen at the fault (it was written after): nothing lost, 0 not -3.
    got = soak.restart_measurements(27, 30, 30, 100.0, 131.5, [])
    assert got["steps_lost"] == 0 and not got["lost_checkpoint"]


def test_restart_without_a_step_is_a_hang():
    got = soak.restart_measurements(27, 20, 20, 100.0, None, ["trainer0"])
    assert got["hung"] == ["trainer0", "restart"] and "resume_s" not in got


def test_longest_stall():
    # Fault at 50.0 s; the chief's steps at 49.0 (before: not counted), 50.4, 53.9, 54.2 s.
    # Gaps: 50.4 - 50.0 = 0.4, 53.9 - 50.4 = 3.5, 54.2 - 53.9 = 0.3: the longest is 3.5.
    assert soak.longest_stall_s(50.0, [49.0, 50.4, 53.9, 54.2]) == 3.5
    # The first step alone: the gap from the fault, 57.25 - 50.0 = 7.25.
    assert soak.longest_stall_s(50.0, [57.25]) == 7.25
    assert soak.longest_stall_s(50.0, []) == 0.0


# -- the summary -------------------------------------------------------------------------------------------------------
FAULTS = [
    {"kind": "SIGKILL trainer", "detect_s": 0.2, "resume_s": 30.0, "steps_lost": 4, "hung": [],
     "lost_checkpoint": False, "as_expected": True},
    {"kind": "SIGKILL trainer", "detect_s": 0.6, "resume_s": 40.0, "steps_lost": 9, "hung": [],
     "lost_checkpoint": False, "as_expected": True},
    {"kind": "SIGKILL trainer", "detect_s": 6.4, "steps_lost": 2, "hung": ["restart"], "lost_checkpoint": True,
     "as_expected": True},
    {"kind": "SIGTERM input", "detect_s": 7.7, "resume_s": 36.0, "steps_lost": 0, "hung": [],
     "lost_checkpoint": False, "as_expected": False},
    {"kind": "unprovoked", "hung": [], "as_expected": False},
]


def test_summary_by_kind():
    got = soak.summarize(FAULTS)
    # SIGKILL trainer: 3 faults, all as expected, one hang (the restart). detect_s 0.2, 0.6, 6.4: median 0.6, max 6.4;
    # resume_s only of the two that resumed, 30 and 40: median (30 + 40) / 2 = 35.0, max 40; steps_lost 4, 9, 2:
    # median 4, max 9.
    assert got["by_kind"]["SIGKILL trainer"] == {
        "count": 3, "as_expected": 3, "hangs": 1, "detect_s_median": 0.6, "detect_s_max": 6.4,
        "resume_s_median": 35.0, "resume_s_max": 40.0, "steps_lost_median": 4, "steps_lost_max": 9}
    assert got["by_kind"]["SIGTERM input"]["detect_s_median"] == 7.7
    # A kind without a measurement has None, not 0.
    assert got["by_kind"]["unprovoked"]["detect_s_median"] is None
    assert got["by_kind"]["unprovoked"]["steps_lost_max"] is None
    assert list(got["by_kind"]) == ["SIGKILL trainer", "SIGTERM input", "unprovoked"]  # sorted
    # Over all: 1 hang, 1 lost checkpoint, 2 not as expected (the input fault, the unprovoked one).
    assert (got["hangs"], got["lost_checkpoints"], got["not_as_expected"]) == (1, 1, 2)
    assert soak.summarize([]) == {"by_kind": {}, "hangs": 0, "lost_checkpoints": 0, "not_as_expected": 0}


# -- the end comparisons, the verdict, the report ----------------------------------------------------------------------
def test_compare_losses():
    # final_step 10: window max(5, 10 // 5 = 2) = 5 steps. The first incarnation logged steps 1..7, the second
    # resumed from 5 and logged 6..10: its losses of 6 and 7 win.
    first = [(float(s), s, 1.0) for s in range(1, 8)]
    second = [(100.0 + s, s, loss) for s, loss in zip(range(6, 11), (0.2, 0.4, 0.3, 0.1, 0.5))]
    reference = [(float(s), s, loss) for s, loss in zip(range(1, 11),
                                                          (0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.2, 0.4))]
    got = soak.compare_losses([first, second], reference, final_step=10)
    # Soak, steps 6..10: (0.2 + 0.4 + 0.3 + 0.1 + 0.5) / 5 = 0.3. Reference 6..10: (0.4 + 0.3 + 0.2 + 0.2 + 0.4) / 5
    # = 0.3; its first 5: (0.9 + 0.8 + 0.7 + 0.6 + 0.5) / 5 = 0.7. Ratio 0.3 / 0.3 = 1.0: in range.
    assert got == {"final_loss_mean": 0.3, "uninterrupted_loss_mean": 0.3, "first_steps_loss_mean": 0.7,
                   "loss_window_steps": 5, "loss_ratio": 1.0, "loss_in_same_range": True}
    # The soak's tail three times the reference's: ratio 3.0, out of [0.5, 2].
    tripled = [(t, s, 3 * loss) for t, s, loss in second]
    got = soak.compare_losses([first, tripled], reference, final_step=10)
    assert got["loss_ratio"] == 3.0 and not got["loss_in_same_range"]
    assert soak.loss_window_steps(1312) == 262  # 1312 // 5


def _write_checkpoint(prefix, values):
    variables = {name: tf.Variable(value) for name, value in values.items()}
    return tf.train.Checkpoint(**variables).write(prefix)


def test_compare_checkpoints(tmp_path):
    a = _write_checkpoint(str(tmp_path / "a" / "ckpt-3"), {"w": np.arange(4.0), "b": np.float32(1.0)})
    same = _write_checkpoint(str(tmp_path / "same" / "ckpt-3"), {"w": np.arange(4.0), "b": np.float32(1.0)})
    other = _write_checkpoint(str(tmp_path / "other" / "ckpt-3"), {"w": np.arange(4.0) + 1e-12, "b": np.float32(1.0)})
    got = soak.compare_checkpoints(a, same)
    assert got == {"final_weights_equal_uninterrupted": True, "variables_compared": 2, "variables_differing": []}
    got = soak.compare_checkpoints(other, a)  # one bit off in one variable is a difference
    assert not got["final_weights_equal_uninterrupted"]
    assert [k.split("/")[0] for k in got["variables_differing"]] == ["w"]


def _report(mode, **end):
    return {"generated_by": soak.GENERATED_BY, "mode": mode, "faults_injected": 2, **end,
            "summary": {"by_kind": {}, "hangs": 0, "lost_checkpoints": 0, "not_as_expected": 1}}


def test_passed_and_verdict():
    plain = _report("plain", final_weights_equal_uninterrupted=True)
    assert soak.passed(plain)
    assert soak.verdict(plain) == ("2 faults, 0 hangs, 0 lost checkpoints, 1 not as expected; final weights equal "
                                   "the uninterrupted run: True")
    assert not soak.passed(_report("plain", final_weights_equal_uninterrupted=False))
    service = _report("service", loss_in_same_range=True, loss_ratio=1.2)
    assert soak.passed(service) and soak.verdict(service).endswith("range: True (ratio 1.2)")
    hung = _report("plain", final_weights_equal_uninterrupted=True)
    hung["summary"]["hangs"] = 1
    assert not soak.passed(hung)
    lost = _report("service", loss_in_same_range=True, loss_ratio=1.0)
    lost["summary"]["lost_checkpoints"] = 1
    assert not soak.passed(lost)


def test_save_report_keeps_the_other_mode(tmp_path):
    path = str(tmp_path / "out" / "soak.json")
    soak.save_report(_report("service", loss_in_same_range=True, loss_ratio=1.0), path)
    soak.save_report(_report("plain", final_weights_equal_uninterrupted=False), path)
    soak.save_report(_report("plain", final_weights_equal_uninterrupted=True), path)
    with open(path) as f:
        saved = json.load(f)
    assert sorted(saved) == ["plain", "service"]
    assert saved["plain"]["final_weights_equal_uninterrupted"] is True  # the newest of a mode wins
    assert saved["plain"]["cpu"] == saved["service"]["cpu"] == cpu.describe()  # each mode names the CPU it ran on


# -- settings and the work dir -----------------------------------------------------------------------------------------
def test_bad_settings_fail_before_any_work(tmp_path):
    work_dir = str(tmp_path / "soak")
    with pytest.raises(soak.SoakError, match="no target"):
        soak.Soak(soak.SoakSettings(target_kinds=("dispatcher",), work_dir=work_dir))
    with pytest.raises(ConfigError):
        soak.Soak(soak.SoakSettings(overrides=("train.no_such_key=1",), work_dir=work_dir))
    assert not os.path.exists(work_dir)


def test_prepare_work_dir_clears_runs_and_keeps_data(tmp_path):
    for name in ("data", "model", "logs", "reference", "elsewhere"):
        os.makedirs(tmp_path / name)
        (tmp_path / name / "file").write_text("x")
    assert soak.prepare_work_dir(str(tmp_path)) == str(tmp_path / "data")
    assert sorted(os.listdir(tmp_path)) == ["data", "elsewhere"]
    assert os.listdir(tmp_path / "data") == ["file"]  # data there already: not written again


# -- end to end --------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_one_trainer_fault_end_to_end(tmp_path):
    """Two trainers, one fault (seed 0: SIGTERM to trainer1), the final checkpoint against an uninterrupted run."""
    settings = soak.SoakSettings(faults=1, target_kinds=("trainer",), gap_s=(0.5, 1.0), work_dir=str(tmp_path),
                                 resume_timeout_s=240.0)
    out = str(tmp_path / "report.json")
    lines = []
    report = soak.run_soak(settings, out, log_fn=lines.append)
    assert report["mode"] == "plain" and report["faults_injected"] == 1, lines
    (fault,) = report["faults"]
    assert fault["kind"] == "SIGTERM trainer" and fault["exit_codes"] == [EXIT_PREEMPTED, EXIT_PREEMPTED], fault
    assert fault["steps_lost"] == 0 and not fault["lost_checkpoint"] and fault["resume_s"] > fault["detect_s"] > 0
    assert report["final_weights_equal_uninterrupted"], report
    assert soak.passed(report) and lines[-1] == soak.verdict(report) + f"; report {out}"
    with open(out) as f:
        assert json.load(f)["plain"]["final_step"] == report["final_step"]
