"""Soak test of fault-tolerant training (`lab/tools/soak_train.py`): a two-worker job on 127.0.0.1 under random faults,
measured per fault, then compared with an uninterrupted run.

`run_soak(settings)` runs two `tools/train.py` workers (TF_CONFIG on loopback ports, MultiWorkerMirroredStrategy,
`SOAK_OVERRIDES`: the tests' tiny model on small synthetic segments made in the work dir), with `settings.service` a
dispatcher in fault-tolerant mode (`tools/data_service.py --dispatcher --work_dir`) and `settings.input_workers` input
workers. Once training runs, it waits a random time, then sends SIGKILL or SIGTERM to a random target
(`FaultSchedule`): a trainer, or with the service also the dispatcher or an input worker. It restarts what died (both
trainers once the survivors have ended by themselves; a service process at once, the dispatcher on its port and work
dir) and waits until training runs again before the next fault. After `settings.faults` faults (or
`settings.max_minutes`) it preempts the job with SIGTERM at step S and compares: without the service, every variable
of the chief's checkpoint S with an uninterrupted run of S steps, bit for bit (`compare_checkpoints`); with it, the
mean loss of the last steps with the uninterrupted run's (`compare_losses`).

One record per fault (`summarize` tabulates them by kind): target, signal, detect_s (fault -> the last trainer ended,
for a trainer fault; -> the process ended, for a service fault), resume_s (fault -> the first step after the restart),
stall_s (the longest gap between the chief's steps in that time), steps_lost (the newest step reached minus the step
resumed from), the exit statuses and the chief's message. A hang is a trainer that does not end by itself within
train.peer_timeout_s + hang_slack_s of a fault (a service process: hang_slack_s; it is then killed), or a job that does
not run again within resume_timeout_s of a restart. A lost checkpoint is a restart that resumes before the newest
checkpoint the chief had completed (its `checkpoint` state file) when the fault came.
"""
from __future__ import annotations

import dataclasses
import json
import os
import random
import re
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time

from ff3d_tf import cpu
from ff3d_tf.checkpoints import CHECKPOINTS_DIR
from ff3d_tf.config import TINY_OVERRIDES, load_config
from ff3d_tf.training.cluster import EXIT_PEER_LOST, EXIT_PREEMPTED, free_loopback_ports
from lab import children

GENERATED_BY = "lab/tools/soak_train.py"
# The tools the soak runs as child processes, relative to the repository root (children.ROOT, their working folder).
TRAIN_TOOL = "tools/train.py"
DATA_SERVICE_TOOL = "tools/data_service.py"
# The tiny model (config.TINY_OVERRIDES), no XLA (the fastest start), a checkpoint every 10 steps.
SOAK_OVERRIDES = TINY_OVERRIDES + ("train.learning_rate=1e-2", "train.log_every_steps=1", "train.eval_every_steps=0",
                                   "train.checkpoint_every_steps=10", "model.compile=none")
SOAK_SEGMENT_SEEDS = (5, 6)  # two small synthetic segments of 5 frames (8 pairs)
SOAK_SEGMENT_FRAMES = 5
SOAK_LIDAR_SCALE = 0.12
TARGET_KINDS = ("trainer", "dispatcher", "input")
NUM_TRAINERS = 2
ENDLESS_STEPS = 10 ** 7  # train.num_steps of the soaked job: it runs until the soak stops it
CLEARED_SUBDIRS = ("model", "model_service", "reference", "dispatcher", "logs")  # of the work dir; data/ is kept
LOSS_RATIO_RANGE = (0.5, 2.0)  # soak / uninterrupted mean loss of the last steps that counts as the same range
MIN_LOSS_WINDOW_STEPS = 5
SERVICE_START_TIMEOUT_S = 300.0
SERVICE_STOP_TIMEOUT_S = 30.0
REFERENCE_TIMEOUT_S = 3600.0
POLL_S = 0.05
MESSAGE_PREFIXES = ("error:", "preempted", "interrupted")  # the lines of tools/train.py that say how it ended
MESSAGE_CHARS = 400
STEP_LINE = re.compile(r"^(?:\[worker\] )?step (\d+)/\d+ loss (\S+)")
RESUMED_LINE = re.compile(r"resumed from \S+ at step (\d+)")
PREEMPTED_LINE = re.compile(r"preempted at step (\d+)")
SERVING_LINE = re.compile(r"serving on port")
CHECKPOINT_STATE_LINE = re.compile(r'^model_checkpoint_path: "ckpt-(\d+)"', re.M)

Line = tuple[float, str]  # (seconds since the soak began, one line of a process's output)
StepLine = tuple[float, int, float]  # (seconds since the soak began, step, loss)


class SoakError(RuntimeError):
    """The soak itself could not go on (bad settings, a job that did not start or stop); the message says why."""


def print_flushed(line: str) -> None:
    print(line, flush=True)


@dataclasses.dataclass(frozen=True)
class SoakSettings:
    """What one soak runs (module docstring). `config`: a YAML file of overrides ("": the built-in defaults), with
    `SOAK_OVERRIDES` then `overrides` applied; `gap_s`: (min, max) seconds of running training before each fault."""
    faults: int = 20
    service: bool = False
    input_workers: int = 2
    seed: int = 0
    gap_s: tuple[float, float] = (0.5, 8.0)
    target_kinds: tuple[str, ...] = TARGET_KINDS
    sigterm_share: float = 0.5
    max_minutes: float = 15.0
    hang_slack_s: float = 30.0
    resume_timeout_s: float = 300.0
    work_dir: str = "/tmp/ff3d_soak"
    config: str = ""
    overrides: tuple[str, ...] = ()

    @property
    def mode(self) -> str:
        return "service" if self.service else "plain"

    @property
    def config_overrides(self) -> list[str]:
        return list(SOAK_OVERRIDES) + list(self.overrides)


# -- the fault schedule ------------------------------------------------------------------------------------------------
def fault_targets(target_kinds, service: bool, input_workers: int) -> list[str]:
    """The processes a fault may hit: trainer0 and trainer1 (kind "trainer"); with the service also "dispatcher" and
    input0 .. input{input_workers - 1} (kind "input"). SoakError for an unknown kind or when none is left."""
    unknown = sorted(set(target_kinds) - set(TARGET_KINDS))
    if unknown:
        raise SoakError(f"unknown target kinds {unknown}; choose from {', '.join(TARGET_KINDS)}")
    names = [f"trainer{i}" for i in range(NUM_TRAINERS)] if "trainer" in target_kinds else []
    if service:
        names += ["dispatcher"] if "dispatcher" in target_kinds else []
        names += [f"input{i}" for i in range(input_workers)] if "input" in target_kinds else []
    if not names:
        raise SoakError(f"targets {','.join(target_kinds)}: no target to fault (dispatcher and input need the service)")
    return names


class FaultSchedule:
    """The random part of a soak, from one generator seeded with `seed`, drawn in a fixed order: before each fault the
    seconds of running training to wait (uniform in `gap_s`), then its target (uniform) and its signal (SIGTERM with
    probability `sigterm_share`, else SIGKILL)."""

    def __init__(self, seed: int, gap_s: tuple[float, float], sigterm_share: float):
        self.rng = random.Random(seed)
        self.gap_s, self.sigterm_share = tuple(gap_s), sigterm_share

    def next_gap_s(self) -> float:
        return self.rng.uniform(*self.gap_s)

    def next_fault(self, targets: list[str]) -> tuple[str, signal.Signals]:
        target = self.rng.choice(targets)
        return target, signal.SIGTERM if self.rng.random() < self.sigterm_share else signal.SIGKILL


def fault_kind(signal_name: str, target: str) -> str:
    """"SIGKILL trainer" for SIGKILL to trainer1: the row of the summary a fault counts in."""
    return f"{signal_name} {target.rstrip('0123456789')}"


# -- reading the processes' output -------------------------------------------------------------------------------------
def step_lines(lines: list[Line], since_s: float = 0.0) -> list[StepLine]:
    """(time, step, loss) of the step lines of tools/train.py logged at or after `since_s`."""
    out = []
    for t, line in lines:
        m = STEP_LINE.match(line)
        if m and t >= since_s:
            out.append((t, int(m[1]), float(m[2])))
    return out


def first_match(lines: list[Line], pattern: re.Pattern) -> re.Match | None:
    for _, line in lines:
        m = pattern.search(line)
        if m:
            return m
    return None


def last_message(lines: list[Line]) -> str:
    """The last line that says how tools/train.py ended (an error, a preemption, an interruption), or ""."""
    for _, line in reversed(lines):
        if line.startswith(MESSAGE_PREFIXES):
            return line[:MESSAGE_CHARS]
    return ""


def newest_step(trainers_lines: list[list[Line]]) -> int:
    """The newest step the trainers logged or resumed from (0: none yet)."""
    steps = [step for lines in trainers_lines for _, step, _ in step_lines(lines)]
    resumed = [int(m[1]) for lines in trainers_lines for m in [first_match(lines, RESUMED_LINE)] if m]
    return max(steps + resumed + [0])


def checkpoint_state_step(state_text: str) -> int:
    """The step of the newest checkpoint named by a CheckpointManager state file's text (0: none)."""
    m = CHECKPOINT_STATE_LINE.search(state_text)
    return int(m[1]) if m else 0


# -- the measurements of one fault -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Ending:
    """How a process ended: its exit status, whether it ended by itself within its bound (else it was killed then),
    and when (seconds since the soak began)."""
    name: str
    exit_code: int
    by_itself: bool
    at_s: float


def expected_trainer_exits(sig: signal.Signals, victim: int) -> list[int]:
    """The trainers' exit statuses a fault should give: SIGTERM to any one preempts both (EXIT_PREEMPTED); SIGKILL
    kills the victim (-SIGKILL) and its peer notices the loss (EXIT_PEER_LOST)."""
    if sig == signal.SIGTERM:
        return [EXIT_PREEMPTED] * NUM_TRAINERS
    return [-signal.SIGKILL if i == victim else EXIT_PEER_LOST for i in range(NUM_TRAINERS)]


def trainer_fault_measurements(sig: signal.Signals, victim: int, endings: list[Ending], t_fault_s: float) -> dict:
    """detect_s (fault -> the last trainer's end), exit_codes, hung (the trainers killed at their bound) and
    as_expected (the expected exits and no hang) of a fault of trainer `victim`."""
    codes = [e.exit_code for e in endings]
    hung = [e.name for e in endings if not e.by_itself]
    return {"detect_s": round(max(e.at_s for e in endings) - t_fault_s, 2), "exit_codes": codes, "hung": hung,
            "as_expected": codes == expected_trainer_exits(sig, victim) and not hung}


def service_fault_measurements(ending: Ending, t_fault_s: float) -> dict:
    """detect_s (fault -> the process's end), exit_codes and hung of a fault of a service process."""
    return {"detect_s": round(ending.at_s - t_fault_s, 2), "exit_codes": [ending.exit_code],
            "hung": [] if ending.by_itself else [ending.name]}


def restart_measurements(step_at_fault: int, newest_complete_step: int, resumed_step: int, t_fault_s: float,
                         t_first_step_s: float | None, hung: list[str]) -> dict:
    """The record of a restart of the trainers: the step resumed from, steps_lost (the step at the fault minus it),
    lost_checkpoint (it resumed before the newest checkpoint complete at the fault), and resume_s (fault -> the first
    step after the restart) or, when no step came (`t_first_step_s` None), "restart" added to `hung`."""
    out = {"newest_complete_checkpoint": newest_complete_step, "resumed_from_step": resumed_step,
           "steps_lost": max(0, step_at_fault - resumed_step), "lost_checkpoint": resumed_step < newest_complete_step}
    if t_first_step_s is None:
        out["hung"] = list(hung) + ["restart"]
    else:
        out["resume_s"] = round(t_first_step_s - t_fault_s, 2)
    return out


def longest_stall_s(t_fault_s: float, step_times_s: list[float]) -> float:
    """The longest gap between the fault and the chief's first step after it or between two of its steps after it
    (0.0: no step)."""
    times = [t_fault_s] + sorted(t for t in step_times_s if t >= t_fault_s)
    return round(max([b - a for a, b in zip(times, times[1:])] or [0.0]), 2)


SUMMARIZED_KEYS = ("detect_s", "resume_s", "steps_lost")


def summarize(faults: list[dict]) -> dict:
    """Per fault kind: count, as_expected, hangs, and the median and max of detect_s, resume_s and steps_lost over the
    faults that have them (None when none has); over all faults: hangs, lost_checkpoints, not_as_expected."""
    by_kind: dict[str, dict] = {}
    for f in faults:
        k = by_kind.setdefault(f["kind"], {"count": 0, "as_expected": 0, "hangs": 0,
                                           **{key: [] for key in SUMMARIZED_KEYS}})
        k["count"] += 1
        k["as_expected"] += bool(f.get("as_expected"))
        k["hangs"] += bool(f.get("hung"))
        for key in SUMMARIZED_KEYS:
            if f.get(key) is not None:
                k[key].append(f[key])
    table = {}
    for kind, k in sorted(by_kind.items()):
        row = {"count": k["count"], "as_expected": k["as_expected"], "hangs": k["hangs"]}
        for key in SUMMARIZED_KEYS:
            values = k[key]
            row[f"{key}_median"] = round(statistics.median(values), 2) if values else None
            row[f"{key}_max"] = round(max(values), 2) if values else None
        table[kind] = row
    return {"by_kind": table, "hangs": sum(bool(f.get("hung")) for f in faults),
            "lost_checkpoints": sum(bool(f.get("lost_checkpoint")) for f in faults),
            "not_as_expected": sum(not f.get("as_expected") for f in faults)}


# -- the end: the soaked job against an uninterrupted one --------------------------------------------------------------
def loss_window_steps(final_step: int) -> int:
    """How many of the last steps `compare_losses` averages: a fifth of the run, at least MIN_LOSS_WINDOW_STEPS."""
    return max(MIN_LOSS_WINDOW_STEPS, final_step // 5)


def compare_losses(chief_runs: list[list[StepLine]], reference: list[StepLine], final_step: int) -> dict:
    """The mean loss of the soaked job's last steps (`chief_runs`: each incarnation's chief's step lines, in start
    order: the last incarnation's loss of a step wins) against the uninterrupted run's, over the same number of last
    steps; their ratio in LOSS_RATIO_RANGE is the same range. first_steps_loss_mean: the uninterrupted run's start."""
    losses = {step: loss for run in chief_runs for _, step, loss in run}
    reference_losses = {step: loss for _, step, loss in reference}
    window = loss_window_steps(final_step)
    tail = statistics.mean(losses[s] for s in sorted(losses)[-window:])
    reference_tail = statistics.mean(reference_losses[s] for s in sorted(reference_losses)[-window:])
    head = statistics.mean(reference_losses[s] for s in sorted(reference_losses)[:window])
    ratio = tail / reference_tail
    return {"final_loss_mean": round(tail, 4), "uninterrupted_loss_mean": round(reference_tail, 4),
            "first_steps_loss_mean": round(head, 4), "loss_window_steps": window, "loss_ratio": round(ratio, 3),
            "loss_in_same_range": LOSS_RATIO_RANGE[0] <= ratio <= LOSS_RATIO_RANGE[1]}


def checkpoint_tensors(prefix: str) -> dict:
    """Every variable of the checkpoint `prefix` by its key (the save counter left out)."""
    import tensorflow as tf
    reader = tf.train.load_checkpoint(prefix)
    return {k: reader.get_tensor(k) for k in reader.get_variable_to_shape_map()
            if not k.startswith(("save_counter", "_CHECKPOINTABLE"))}


def compare_checkpoints(got_prefix: str, want_prefix: str) -> dict:
    """Whether the checkpoints hold the same variables, bit for bit; the first 10 keys that differ or are missing."""
    import numpy as np
    got, want = checkpoint_tensors(got_prefix), checkpoint_tensors(want_prefix)
    differing = sorted(k for k in want if k not in got or not np.array_equal(got[k], want[k]))
    return {"final_weights_equal_uninterrupted": not differing and sorted(got) == sorted(want),
            "variables_compared": len(want), "variables_differing": differing[:10]}


def passed(report: dict) -> bool:
    """No hang, no lost checkpoint, and the end as the uninterrupted run's (weights, or with the service the loss)."""
    s = report["summary"]
    return bool(s["hangs"] == 0 and s["lost_checkpoints"] == 0 and report.get(
        "final_weights_equal_uninterrupted", report.get("loss_in_same_range")))


def verdict(report: dict) -> str:
    """One line: faults, hangs, lost checkpoints, faults not as expected, and the comparison's outcome."""
    s = report["summary"]
    end = (f"final weights equal the uninterrupted run: {report['final_weights_equal_uninterrupted']}"
           if "final_weights_equal_uninterrupted" in report else
           f"final loss in the uninterrupted run's range: {report['loss_in_same_range']} "
           f"(ratio {report['loss_ratio']})")
    return (f"{report['faults_injected']} faults, {s['hangs']} hangs, {s['lost_checkpoints']} lost checkpoints, "
            f"{s['not_as_expected']} not as expected; {end}")


def save_report(report: dict, path: str) -> None:
    """Writes `report` into the JSON file `path` under its mode ("plain" or "service"), keeping the other mode's."""
    merged = {}
    if os.path.exists(path):
        with open(path) as f:
            merged = json.load(f)
    merged[report["mode"]] = {**report, "cpu": cpu.describe()}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(merged, f, indent=1)


def prepare_work_dir(work_dir: str) -> str:
    """Clears the work dir's model, dispatcher and log folders and writes the soak's synthetic segments into its data
    folder unless it holds them already; returns the data folder."""
    from ff3d_tf.data.synthetic import wod as synthetic
    os.makedirs(work_dir, exist_ok=True)
    for name in CLEARED_SUBDIRS:
        shutil.rmtree(os.path.join(work_dir, name), ignore_errors=True)
    data_dir = os.path.join(work_dir, "data")
    if not os.path.isdir(data_dir):
        for seed in SOAK_SEGMENT_SEEDS:
            synthetic.write_segment(os.path.join(data_dir, f"segment-soak{seed}.tfrecord"), synthetic.SegmentSpec(
                seed=seed, num_frames=SOAK_SEGMENT_FRAMES, lidar_scale=SOAK_LIDAR_SCALE))
    return data_dir


# -- the processes -----------------------------------------------------------------------------------------------------
class LoggedProcess:
    """One child process run from the repository root: its output lines, time-stamped (seconds since the soak began,
    `t0`: time.monotonic() then), in memory (`lines`) and appended to the file `log_path`."""

    def __init__(self, name: str, cmd: list[str], log_path: str, t0: float, env: dict | None = None):
        self.name, self.t0 = name, t0
        self.lines: list[Line] = []
        self.log = open(log_path, "a")
        self.log.write(f"=== {' '.join(cmd)}\n")
        self.popen = subprocess.Popen(cmd, cwd=children.ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True,
                                      env=children.child_environment(env={"PYTHONUNBUFFERED": "1", **(env or {})}))
        self.started_s = time.monotonic() - t0
        self.ended_s: float | None = None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.popen.stdout:
            t = time.monotonic() - self.t0
            self.lines.append((t, line.rstrip("\n")))
            self.log.write(f"{t:8.2f} {line}")
        self.popen.wait()
        self.ended_s = time.monotonic() - self.t0  # the end itself, not when someone asked (EOF: the process is gone)
        self.log.flush()

    def poll(self) -> int | None:
        code = self.popen.poll()
        if code is not None and self.ended_s is None:
            self._reader.join(5)
            if self.ended_s is None:
                self.ended_s = time.monotonic() - self.t0
        return code

    def finish(self, timeout_s: float) -> Ending:
        """Waits up to `timeout_s` for the process to end by itself, kills it otherwise; closes its log."""
        deadline = time.monotonic() + timeout_s
        while self.poll() is None and time.monotonic() < deadline:
            time.sleep(POLL_S)
        by_itself = self.poll() is not None
        if not by_itself:
            self.popen.kill()
            self.popen.wait()
            self.poll()
        self._reader.join(10)
        self.log.close()
        return Ending(self.name, self.popen.returncode, by_itself, self.ended_s)

    def kill(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait()

    def snapshot(self) -> list[Line]:
        return list(self.lines)

    def steps(self, since_s: float = 0.0) -> list[StepLine]:
        return step_lines(self.snapshot(), since_s)


class Soak:
    """One soak (module docstring) with `settings`; progress lines go to `log_fn`. The settings and the config are
    checked here, before any work; `run` does it."""

    def __init__(self, settings: SoakSettings, log_fn=print_flushed):
        self.settings, self.log_fn = settings, log_fn
        self.overrides = settings.config_overrides
        self.peer_timeout_s = load_config(settings.config or None, self.overrides).train.peer_timeout_s
        self.targets = fault_targets(settings.target_kinds, settings.service, settings.input_workers)
        self.schedule = FaultSchedule(settings.seed, settings.gap_s, settings.sigterm_share)
        work_dir = settings.work_dir
        self.logs_dir = os.path.join(work_dir, "logs")
        self.data_dir = os.path.join(work_dir, "data")
        self.model_dir = os.path.join(work_dir, "model_service" if settings.service else "model")
        self.reference_dir = os.path.join(work_dir, "reference")
        self.dispatcher_dir = os.path.join(work_dir, "dispatcher")
        self.t0 = time.monotonic()
        self.trainer_ports: list[int] = []
        self.dispatcher_port = 0
        self.trainers: list[LoggedProcess] = []
        self.dispatcher: LoggedProcess | None = None
        self.inputs: list[LoggedProcess] = []
        self.chiefs: list[LoggedProcess] = []  # every incarnation's chief of the soaked job
        self.started: list[LoggedProcess] = []  # every process, killed at the end if still running

    def now(self) -> float:
        return time.monotonic() - self.t0

    def run(self) -> dict:
        """The report: the soak's settings, the comparison with the uninterrupted run, `summarize` of the faults and
        every fault's record. Every process it started has ended when it returns or raises."""
        prepare_work_dir(self.settings.work_dir)
        os.makedirs(self.logs_dir, exist_ok=True)
        self.t0 = time.monotonic()
        self.trainer_ports = free_loopback_ports(NUM_TRAINERS)
        self.dispatcher_port = free_loopback_ports(1)[0]
        try:
            return self._run()
        finally:
            for p in self.started:
                p.kill()

    # -- processes -----------------------------------------------------------------------------------------------------
    def _start(self, name: str, cmd: list[str], env: dict | None = None) -> LoggedProcess:
        proc = LoggedProcess(name, cmd, os.path.join(self.logs_dir, f"{name}.log"), self.t0, env)
        self.started.append(proc)
        return proc

    def start_trainers(self, model_dir: str, num_steps: int, ports: list[int] | None = None,
                       tag: str = "") -> list[LoggedProcess]:
        """The two workers of a job on `ports` (default: the soaked job's); the soaked job (no `tag`) reads from the
        service when there is one, and its chief joins `chiefs`."""
        ports = ports or self.trainer_ports
        service = self.settings.service and not tag
        procs = []
        for index in range(NUM_TRAINERS):
            tf_config = {"cluster": {"worker": [f"127.0.0.1:{p}" for p in ports]},
                         "task": {"type": "worker", "index": index}}
            cmd = [sys.executable, TRAIN_TOOL, "--config", self.settings.config, "--data_dir", self.data_dir,
                   "--model_dir", model_dir]
            if service:
                cmd += ["--data_service_address", f"grpc://127.0.0.1:{self.dispatcher_port}"]
            cmd += [a for kv in self.overrides + [f"train.num_steps={num_steps}"] for a in ("--set", kv)]
            procs.append(self._start(f"trainer{index}{tag}", cmd, env={"TF_CONFIG": json.dumps(tf_config)}))
        if not tag:
            self.chiefs.append(procs[0])
        return procs

    def start_dispatcher(self) -> LoggedProcess:
        return self._start("dispatcher", [sys.executable, DATA_SERVICE_TOOL, "--dispatcher", "--port",
                                          str(self.dispatcher_port), "--work_dir", self.dispatcher_dir])

    def start_input(self, index: int) -> LoggedProcess:
        return self._start(f"input{index}", [sys.executable, DATA_SERVICE_TOOL, "--worker", "--dispatcher_address",
                                             f"127.0.0.1:{self.dispatcher_port}"])

    def wait_serving(self, proc: LoggedProcess, timeout_s: float = SERVICE_START_TIMEOUT_S) -> float | None:
        """When a service process said it serves (None: it ended, or not within `timeout_s`)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            for t, line in proc.snapshot():
                if SERVING_LINE.search(line):
                    return t
            time.sleep(POLL_S)
        return None

    def wait_training(self, since_s: float, timeout_s: float) -> float | None:
        """Time of the chief's first step line after `since_s` (None: none within `timeout_s`, or a trainer ended)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            steps = self.trainers[0].steps(since_s)
            if steps:
                return steps[0][0]
            if any(p.poll() is not None for p in self.trainers):
                return None
            time.sleep(POLL_S)
        return None

    def newest_complete_checkpoint(self) -> int:
        """The step of the newest checkpoint the chief finished writing (its CheckpointManager state file)."""
        try:
            with open(os.path.join(self.model_dir, CHECKPOINTS_DIR, "checkpoint")) as f:
                return checkpoint_state_step(f.read())
        except OSError:
            return 0

    def current_step(self) -> int:
        return newest_step([p.snapshot() for p in self.trainers])

    # -- faults --------------------------------------------------------------------------------------------------------
    def inject(self, number: int) -> dict:
        """Sends the next scheduled fault, waits until training runs again; the fault's record."""
        target, sig = self.schedule.next_fault(self.targets)
        record = {"fault": number, "target": target, "signal": sig.name, "kind": fault_kind(sig.name, target),
                  "step_at_fault": self.current_step()}
        t_fault = self.now()
        record["at_s"] = round(t_fault, 2)
        if target.startswith("trainer"):
            self.trainer_fault(record, int(target[len("trainer"):]), sig, t_fault)
            record["stall_s"] = record.get("resume_s")  # no step between the fault and the restarted job's first
        else:
            self.service_fault(record, target, sig, t_fault)
        self.log_fn(f"[{self.now():7.1f} s] fault {number}: {record['kind']} at step {record['step_at_fault']}: "
                    f"detect {record.get('detect_s')} s, resume {record.get('resume_s')} s, steps lost "
                    f"{record.get('steps_lost')}, exits {record['exit_codes']}, hung {record['hung']}"
                    + ("" if record.get("as_expected") else "  (NOT AS EXPECTED)"))
        return record

    def unprovoked(self, number: int) -> dict:
        """The record of a trainer that ended by itself (a fault of its own), after restarting the job."""
        record = {"fault": number, "target": "none", "signal": "none", "kind": "unprovoked",
                  "step_at_fault": self.current_step(), "at_s": round(self.now(), 2),
                  "exit_codes": [p.finish(self.peer_timeout_s).exit_code for p in self.trainers],
                  "message": last_message(self.trainers[0].snapshot()), "hung": [], "as_expected": False}
        self.restart_trainers(record, self.now())
        return record

    def trainer_fault(self, record: dict, victim: int, sig: signal.Signals, t_fault: float) -> None:
        bound_s = self.peer_timeout_s + self.settings.hang_slack_s
        self.trainers[victim].popen.send_signal(sig)
        endings = [p.finish(bound_s - (self.now() - t_fault)) for p in self.trainers]
        record.update(trainer_fault_measurements(sig, victim, endings, t_fault))
        record["message"] = last_message(self.trainers[0].snapshot()) or last_message(self.trainers[1].snapshot())
        self.restart_trainers(record, t_fault)

    def restart_trainers(self, record: dict, t_fault: float) -> None:
        complete = self.newest_complete_checkpoint()
        self.trainers = self.start_trainers(self.model_dir, ENDLESS_STEPS)
        t_resume = self.wait_training(self.trainers[0].started_s, self.settings.resume_timeout_s)
        resumed = first_match(self.trainers[0].snapshot(), RESUMED_LINE)
        record.update(restart_measurements(record["step_at_fault"], complete, int(resumed[1]) if resumed else 0,
                                           t_fault, t_resume, record.get("hung", [])))

    def service_fault(self, record: dict, target: str, sig: signal.Signals, t_fault: float) -> None:
        input_index = None if target == "dispatcher" else int(target[len("input"):])
        proc = self.dispatcher if input_index is None else self.inputs[input_index]
        proc.popen.send_signal(sig)
        ending = proc.finish(self.settings.hang_slack_s)
        record.update(service_fault_measurements(ending, t_fault))
        if input_index is None:
            self.dispatcher = replacement = self.start_dispatcher()
        else:
            self.inputs[input_index] = replacement = self.start_input(input_index)
        t_serving = self.wait_serving(replacement)
        record["replacement_serving_s"] = None if t_serving is None else round(t_serving - t_fault, 2)
        t_resume = self.wait_training(t_serving or self.now(), self.settings.resume_timeout_s)
        record["trainers_ended"] = trainers_ended = [p.name for p in self.trainers if p.poll() is not None]
        if trainers_ended or t_resume is None:  # the trainers did not survive it: restart them as after their fault
            for p in self.trainers:
                p.finish(self.peer_timeout_s + self.settings.hang_slack_s)
            record["exit_codes"] += [p.popen.returncode for p in self.trainers]
            record["as_expected"] = False
            self.restart_trainers(record, t_fault)
        else:
            record.update({"resume_s": round(t_resume - t_fault, 2), "steps_lost": 0, "lost_checkpoint": False,
                           "as_expected": ending.by_itself})
        record["stall_s"] = longest_stall_s(t_fault, [t for t, _, _ in self.trainers[0].steps(t_fault)])

    # -- run -----------------------------------------------------------------------------------------------------------
    def _run(self) -> dict:
        s = self.settings
        if s.service:
            self.dispatcher = self.start_dispatcher()
            self.inputs = [self.start_input(i) for i in range(s.input_workers)]
        self.trainers = self.start_trainers(self.model_dir, ENDLESS_STEPS)
        if self.wait_training(0.0, s.resume_timeout_s) is None:
            raise SoakError(f"the job did not start; logs in {self.logs_dir}")
        faults = []
        while len(faults) < s.faults and self.now() < 60 * s.max_minutes:
            deadline = time.monotonic() + self.schedule.next_gap_s()
            while time.monotonic() < deadline and all(p.poll() is None for p in self.trainers):
                time.sleep(POLL_S / 2)
            if any(p.poll() is not None for p in self.trainers):
                faults.append(self.unprovoked(len(faults) + 1))
            else:
                faults.append(self.inject(len(faults) + 1))
        return self.stop_and_compare(faults)

    def stop_job(self) -> int:
        """SIGTERM to the chief: every trainer saves the same step and ends; returns that step."""
        self.trainers[0].popen.send_signal(signal.SIGTERM)
        codes = [p.finish(self.peer_timeout_s + self.settings.hang_slack_s).exit_code for p in self.trainers]
        m = first_match(self.trainers[0].snapshot(), PREEMPTED_LINE)
        if codes != [EXIT_PREEMPTED] * NUM_TRAINERS or m is None:
            raise SoakError(f"the final stop failed: exits {codes}; logs in {self.logs_dir}")
        return int(m[1])

    def stop_and_compare(self, faults: list[dict]) -> dict:
        """Stops the job and the service, runs the uninterrupted job to the same step, compares; the report."""
        s = self.settings
        final_step = self.stop_job()
        for p in ([self.dispatcher] if self.dispatcher else []) + self.inputs:
            p.popen.terminate()
            p.finish(SERVICE_STOP_TIMEOUT_S)
        self.log_fn(f"[{self.now():7.1f} s] job stopped at step {final_step}; uninterrupted run of {final_step} steps")
        reference = self.start_trainers(self.reference_dir, final_step, ports=free_loopback_ports(NUM_TRAINERS),
                                        tag="_reference")
        reference_codes = [p.finish(REFERENCE_TIMEOUT_S).exit_code for p in reference]
        if reference_codes != [0] * NUM_TRAINERS:
            raise SoakError(f"the uninterrupted run failed: exits {reference_codes}; logs in {self.logs_dir}")
        report = {"mode": s.mode, "faults_injected": len(faults), "final_step": final_step,
                  "wall_s": round(self.now(), 1), "seed": s.seed, "input_workers": s.input_workers if s.service else 0,
                  "config_overrides": self.overrides}
        if s.service:
            report.update(compare_losses([p.steps() for p in self.chiefs], reference[0].steps(), final_step))
        else:
            checkpoint = os.path.join(CHECKPOINTS_DIR, f"ckpt-{final_step}")
            report.update(compare_checkpoints(os.path.join(self.model_dir, checkpoint),
                                              os.path.join(self.reference_dir, checkpoint)))
        report["summary"] = summarize(faults)
        report["faults"] = faults
        return report


def run_soak(settings: SoakSettings, out_path: str | None = None, log_fn=print_flushed) -> dict:
    """Runs one soak (module docstring); with `out_path`, saves its report there (`save_report`). Its last line to
    `log_fn` is the `verdict`. Returns the report; `passed` says whether it passed."""
    report = {"generated_by": GENERATED_BY, **Soak(settings, log_fn).run()}
    if out_path:
        save_report(report, out_path)
    log_fn(verdict(report) + (f"; report {out_path}" if out_path else ""))
    return report
