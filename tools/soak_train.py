"""Soak test of fault-tolerant training: a two-worker job on 127.0.0.1 under random faults. JSON into benchmarks/.

python tools/soak_train.py --faults 20 --service --out benchmarks/soak_train.json   # with a tf.data service
python tools/soak_train.py --faults 6 --out benchmarks/soak_train.json              # the trainers alone

Runs two `tools/train.py` workers (TF_CONFIG on loopback ports, MultiWorkerMirroredStrategy, the tiny model of the
tests on small synthetic segments made in --work_dir), with --service a dispatcher in fault-tolerant mode
(`tools/data_service.py --dispatcher --work_dir`) and --input_workers input workers. Once training runs, it waits a
random time (uniform in --gap_s), then sends SIGKILL or SIGTERM (--sigterm_share) to a random target: a trainer,
or with --service also the dispatcher or an input worker. It restarts what died (both trainers once the survivors
have ended by themselves; a service process at once, the dispatcher on its port and work dir) and waits until
training runs again before the next fault. After --faults faults (or --max_minutes) it preempts the job with SIGTERM
at step S and compares: without the service, every variable of the chief's checkpoint S with an uninterrupted run
of S steps (bit for bit); with it, the mean loss of the last steps with the uninterrupted run's.

Per fault: target, signal, detect_s (fault -> the last trainer ended, for a trainer fault; -> the process ended,
for a service fault), resume_s (fault -> the first step after the restart), stall_s (the longest gap between the
chief's steps in that time), steps_lost (the newest step reached minus the step resumed from), the trainers' exit
statuses and the chief's message. A hang is a trainer that does not end by itself within train.peer_timeout_s +
--hang_slack_s of a fault (it is then killed), or a job that does not run again within --resume_timeout_s of a
restart. A lost checkpoint is a restart that resumes before the newest checkpoint the chief had completed (its
`checkpoint` state file) when the fault came.
"""
import json
import os
import random
import re
import signal
import statistics
import subprocess
import sys
import threading
import time

import _common

from ff3d_tf.training import cluster
from ff3d_tf.training.cluster import EXIT_PEER_LOST, EXIT_PREEMPTED

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The tests' tiny model (tests/conftest.py TINY_OVERRIDES), no XLA (the fastest start), a checkpoint every 10 steps.
SOAK_OVERRIDES = ("grid.num_pillars_x=32", "grid.num_pillars_y=32", "grid.x_range_m=[-40, 40]",
                  "grid.y_range_m=[-40, 40]", "model.point_feature_dim=16", "model.encoder_widths=[16, 24, 32]",
                  "model.encoder_depths=[2, 2, 2]", "model.decoder_dims=[[24, 24], [24, 16], [16, 16]]",
                  "model.head_hidden_dim=8", "data.point_bucket_base=1024", "data.shuffle_buffer=4",
                  "train.global_batch_size=2", "train.learning_rate=1e-2", "train.log_every_steps=1",
                  "train.eval_every_steps=0", "train.checkpoint_every_steps=10", "model.compile=none")
_STEP_RE = re.compile(r"^(?:\[worker\] )?step (\d+)/\d+ loss (\S+)")
_RESUMED_RE = re.compile(r"resumed from \S+ at step (\d+)")


def _args(argv=None):
    p = _common.parser(__doc__, None)
    p.add_argument("--faults", type=int, default=20, help="faults to inject")
    p.add_argument("--service", action="store_true", help="feed the trainers from a tf.data service")
    p.add_argument("--input_workers", type=int, default=2, help="tf.data service workers (with --service)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault schedule")
    p.add_argument("--gap_s", type=float, nargs=2, default=(0.5, 8.0), metavar=("MIN", "MAX"),
                   help="seconds of running training before each fault (uniform)")
    p.add_argument("--targets", default="trainer,dispatcher,input",
                   help="kinds of target to choose from (comma-separated; dispatcher and input need --service)")
    p.add_argument("--sigterm_share", type=float, default=0.5, help="share of faults that are SIGTERM (else SIGKILL)")
    p.add_argument("--max_minutes", type=float, default=15.0, help="no new fault after this; the job is then stopped")
    p.add_argument("--hang_slack_s", type=float, default=30.0)
    p.add_argument("--resume_timeout_s", type=float, default=300.0, help="restart -> first step (start-up included)")
    p.add_argument("--work_dir", default="/tmp/ff3d_soak", help="data, model dirs and every process's log")
    p.add_argument("--out", default="benchmarks/soak_train.json", help="report (merged: one entry per mode)")
    return p.parse_args(argv)


class Proc:
    """One child process: its output, time-stamped (seconds since the soak began), in memory and in a log file."""

    def __init__(self, name: str, cmd: list[str], log_path: str, t0: float, env: dict | None = None):
        self.name, self.t0 = name, t0
        self.lines: list[tuple[float, str]] = []
        self.log = open(log_path, "a")
        self.log.write(f"=== {' '.join(cmd)}\n")
        self.popen = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
        self.started = time.monotonic() - t0
        self.ended: float | None = None
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.popen.stdout:
            t = time.monotonic() - self.t0
            self.lines.append((t, line.rstrip("\n")))
            self.log.write(f"{t:8.2f} {line}")
        self.popen.wait()
        self.ended = time.monotonic() - self.t0  # the end itself, not when someone asked (EOF: the process is gone)
        self.log.flush()

    def poll(self) -> int | None:
        code = self.popen.poll()
        if code is not None and self.ended is None:
            self._reader.join(5)
            if self.ended is None:
                self.ended = time.monotonic() - self.t0
        return code

    def finish(self, timeout_s: float) -> tuple[int, bool]:
        """(exit status, whether it ended by itself within `timeout_s`); killed otherwise."""
        deadline = time.monotonic() + timeout_s
        while self.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        by_itself = self.poll() is not None
        if not by_itself:
            self.popen.kill()
            self.popen.wait()
            self.poll()
        self._reader.join(10)
        self.log.close()
        return self.popen.returncode, by_itself

    def steps(self, since: float = 0.0) -> list[tuple[float, int, float]]:
        """(time, step, loss) of the step lines logged after `since`."""
        out = []
        for t, line in list(self.lines):
            m = _STEP_RE.match(line)
            if m and t >= since:
                out.append((t, int(m[1]), float(m[2])))
        return out

    def find(self, pattern: str) -> re.Match | None:
        for _, line in list(self.lines):
            m = re.search(pattern, line)
            if m:
                return m
        return None

    def last_message(self) -> str:
        for _, line in reversed(list(self.lines)):
            if line.startswith(("error:", "preempted", "interrupted")):
                return line[:400]
        return ""


class Soak:
    def __init__(self, args, cfg_sets: list[str]):
        self.args, self.sets = args, cfg_sets
        self.t0 = time.monotonic()
        self.rng = random.Random(args.seed)
        self.logs = os.path.join(args.work_dir, "logs")
        os.makedirs(self.logs, exist_ok=True)
        self.data_dir = os.path.join(args.work_dir, "data")
        self.model_dir = os.path.join(args.work_dir, "model_service" if args.service else "model")
        self.trainer_ports = cluster.free_loopback_ports(2)
        self.dispatcher_port = cluster.free_loopback_ports(1)[0]
        self.dispatcher_dir = os.path.join(args.work_dir, "dispatcher")
        self.trainers: list[Proc] = []
        self.dispatcher: Proc | None = None
        self.inputs: list[Proc] = []
        self.chiefs: list[Proc] = []  # every incarnation's chief of the soaked job
        from ff3d_tf.config import load_config
        self.peer_timeout_s = load_config(args.config or None, cfg_sets).train.peer_timeout_s  # validated here

    def now(self) -> float:
        return time.monotonic() - self.t0

    # -- processes -------------------------------------------------------------------------------------------------
    def start_trainers(self, model_dir: str, num_steps: int, service: bool, ports: list[int] | None = None,
                       tag: str = "") -> list[Proc]:
        ports = ports or self.trainer_ports
        procs = []
        for index in range(2):
            tf_config = {"cluster": {"worker": [f"127.0.0.1:{p}" for p in ports]},
                         "task": {"type": "worker", "index": index}}
            cmd = [sys.executable, "tools/train.py", "--config", self.args.config or "", "--data_dir",
                   self.data_dir, "--model_dir", model_dir]
            if service:
                cmd += ["--data_service_address", f"grpc://127.0.0.1:{self.dispatcher_port}"]
            cmd += [a for kv in self.sets + [f"train.num_steps={num_steps}"] for a in ("--set", kv)]
            procs.append(Proc(f"trainer{index}{tag}", cmd, os.path.join(self.logs, f"trainer{index}{tag}.log"),
                              self.t0, env={"TF_CONFIG": json.dumps(tf_config)}))
        if not tag:
            self.chiefs.append(procs[0])
        return procs

    def start_dispatcher(self) -> Proc:
        return Proc("dispatcher", [sys.executable, "tools/data_service.py", "--dispatcher", "--port",
                                   str(self.dispatcher_port), "--work_dir", self.dispatcher_dir],
                    os.path.join(self.logs, "dispatcher.log"), self.t0)

    def start_input(self, index: int) -> Proc:
        return Proc(f"input{index}", [sys.executable, "tools/data_service.py", "--worker", "--dispatcher_address",
                                      f"127.0.0.1:{self.dispatcher_port}"],
                    os.path.join(self.logs, f"input{index}.log"), self.t0)

    def wait_serving(self, proc: Proc, timeout_s: float = 300.0) -> float | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and proc.poll() is None:
            for t, line in list(proc.lines):
                if "serving on port" in line:
                    return t
            time.sleep(0.05)
        return None

    def wait_training(self, since: float, timeout_s: float) -> float | None:
        """Time of the chief's first step line after `since` (None: none within `timeout_s`, or a trainer ended)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            steps = self.trainers[0].steps(since)
            if steps:
                return steps[0][0]
            if any(p.poll() is not None for p in self.trainers):
                return None
            time.sleep(0.05)
        return None

    def newest_complete_checkpoint(self) -> int:
        """The step of the newest checkpoint the chief finished writing (its CheckpointManager state file)."""
        try:
            with open(os.path.join(self.model_dir, "checkpoints", "checkpoint")) as f:
                m = re.search(r'^model_checkpoint_path: "ckpt-(\d+)"', f.read(), re.M)
            return int(m[1]) if m else 0
        except OSError:
            return 0

    def current_step(self) -> int:
        steps = [s for p in self.trainers for _, s, _ in p.steps()]
        resumed = [int(m[1]) for p in self.trainers for m in [p.find(_RESUMED_RE.pattern)] if m]
        return max(steps + resumed + [0])

    # -- faults ----------------------------------------------------------------------------------------------------
    def targets(self) -> list[str]:
        kinds = self.args.targets.split(",")
        names = ["trainer0", "trainer1"] if "trainer" in kinds else []
        if self.args.service:
            names += (["dispatcher"] if "dispatcher" in kinds else []) + (
                [f"input{i}" for i in range(len(self.inputs))] if "input" in kinds else [])
        if not names:
            raise SystemExit(f"--targets {self.args.targets}: no target to fault (dispatcher and input need --service)")
        return names

    def trainer_fault(self, record: dict, victim: int, sig: int, t_fault: float) -> None:
        bound = self.peer_timeout_s + self.args.hang_slack_s
        self.trainers[victim].popen.send_signal(sig)
        codes, hung = [], []
        for p in self.trainers:
            code, by_itself = p.finish(bound - (self.now() - t_fault))
            codes.append(code)
            if not by_itself:
                hung.append(p.name)
        record["detect_s"] = round(max(p.ended for p in self.trainers) - t_fault, 2)
        record["exit_codes"] = codes
        record["message"] = self.trainers[0].last_message() or self.trainers[1].last_message()
        record["hung"] = hung
        expected = ([EXIT_PREEMPTED, EXIT_PREEMPTED] if sig == signal.SIGTERM else
                    [-signal.SIGKILL if i == victim else EXIT_PEER_LOST for i in range(2)])
        record["as_expected"] = codes == expected and not hung
        self.restart_trainers(record, t_fault)

    def restart_trainers(self, record: dict, t_fault: float) -> None:
        record["newest_complete_checkpoint"] = complete = self.newest_complete_checkpoint()
        self.trainers = self.start_trainers(self.model_dir, 10 ** 7, self.args.service)
        t_resume = self.wait_training(self.trainers[0].started, self.args.resume_timeout_s)
        resumed = self.trainers[0].find(_RESUMED_RE.pattern)
        record["resumed_from_step"] = resumed_step = int(resumed[1]) if resumed else 0
        record["steps_lost"] = max(0, record["step_at_fault"] - resumed_step)
        record["lost_checkpoint"] = resumed_step < complete
        if t_resume is None:
            record["hung"] = record.get("hung", []) + ["restart"]
            return
        record["resume_s"] = round(t_resume - t_fault, 2)

    def service_fault(self, record: dict, target: str, sig: int, t_fault: float) -> None:
        proc = self.dispatcher if target == "dispatcher" else self.inputs[int(target[len("input"):])]
        proc.popen.send_signal(sig)
        code, by_itself = proc.finish(self.args.hang_slack_s)
        record["detect_s"] = round(proc.ended - t_fault, 2)
        record["exit_codes"] = [code]
        record["hung"] = [] if by_itself else [proc.name]
        replacement = self.start_dispatcher() if target == "dispatcher" else self.start_input(
            int(target[len("input"):]))
        if target == "dispatcher":
            self.dispatcher = replacement
        else:
            self.inputs[int(target[len("input"):])] = replacement
        t_serving = self.wait_serving(replacement)
        record["replacement_serving_s"] = None if t_serving is None else round(t_serving - t_fault, 2)
        t_resume = self.wait_training(t_serving or self.now(), self.args.resume_timeout_s)
        trainers_ended = [p.name for p in self.trainers if p.poll() is not None]
        record["trainers_ended"] = trainers_ended
        if trainers_ended or t_resume is None:  # the trainers did not survive it: restart them as after their fault
            for p in self.trainers:
                p.finish(self.peer_timeout_s + self.args.hang_slack_s)
            record["exit_codes"] += [p.popen.returncode for p in self.trainers]
            record["as_expected"] = False
            self.restart_trainers(record, t_fault)
        else:
            record["resume_s"] = round(t_resume - t_fault, 2)
            record["steps_lost"] = 0
            record["lost_checkpoint"] = False
            record["as_expected"] = by_itself
        steps = [t for t, _, _ in self.trainers[0].steps(t_fault)]
        record["stall_s"] = round(max([b - a for a, b in zip([t_fault] + steps, steps)] or [0.0]), 2)

    def inject(self, number: int) -> dict:
        target = self.rng.choice(self.targets())
        sig = signal.SIGTERM if self.rng.random() < self.args.sigterm_share else signal.SIGKILL
        record = {"fault": number, "target": target, "signal": signal.Signals(sig).name,
                  "kind": f"{signal.Signals(sig).name} {target.rstrip('0123456789')}"}
        record["step_at_fault"] = self.current_step()
        t_fault = self.now()
        record["at_s"] = round(t_fault, 2)
        if target.startswith("trainer"):
            self.trainer_fault(record, int(target[-1]), sig, t_fault)
            record["stall_s"] = record.get("resume_s")  # no step between the fault and the restarted job's first
        else:
            self.service_fault(record, target, sig, t_fault)
        print(f"[{self.now():7.1f} s] fault {number}: {record['kind']} at step {record['step_at_fault']}: detect "
              f"{record.get('detect_s')} s, resume {record.get('resume_s')} s, steps lost "
              f"{record.get('steps_lost')}, exits {record['exit_codes']}, hung {record['hung']}"
              + ("" if record.get("as_expected") else "  (NOT AS EXPECTED)"), flush=True)
        return record

    # -- run -------------------------------------------------------------------------------------------------------
    def run(self) -> dict:
        args = self.args
        if args.service:
            self.dispatcher = self.start_dispatcher()
            self.inputs = [self.start_input(i) for i in range(args.input_workers)]
        self.trainers = self.start_trainers(self.model_dir, 10 ** 7, args.service)
        if self.wait_training(0.0, args.resume_timeout_s) is None:
            raise SystemExit(f"the job did not start; logs in {self.logs}")
        faults = []
        while len(faults) < args.faults and self.now() < 60 * args.max_minutes:
            gap = self.rng.uniform(*args.gap_s)
            deadline = time.monotonic() + gap
            while time.monotonic() < deadline and all(p.poll() is None for p in self.trainers):
                time.sleep(0.02)
            if any(p.poll() is not None for p in self.trainers):  # a trainer ended by itself: a fault of its own
                record = {"fault": len(faults) + 1, "target": "none", "signal": "none", "kind": "unprovoked",
                          "step_at_fault": self.current_step(), "at_s": round(self.now(), 2),
                          "exit_codes": [p.finish(self.peer_timeout_s)[0] for p in self.trainers],
                          "message": self.trainers[0].last_message(), "hung": [], "as_expected": False}
                self.restart_trainers(record, self.now())
                faults.append(record)
                continue
            faults.append(self.inject(len(faults) + 1))
        return self.finish(faults)

    def stop_job(self) -> int:
        """SIGTERM to the chief: every trainer saves the same step and ends; returns that step."""
        self.trainers[0].popen.send_signal(signal.SIGTERM)
        codes = [p.finish(self.peer_timeout_s + self.args.hang_slack_s)[0] for p in self.trainers]
        m = self.trainers[0].find(r"preempted at step (\d+)")
        if codes != [EXIT_PREEMPTED, EXIT_PREEMPTED] or m is None:
            raise SystemExit(f"the final stop failed: exits {codes}; logs in {self.logs}")
        return int(m[1])

    def finish(self, faults: list[dict]) -> dict:
        args = self.args
        final_step = self.stop_job()
        for p in ([self.dispatcher] if self.dispatcher else []) + self.inputs:
            p.popen.terminate()
            p.finish(30)
        print(f"[{self.now():7.1f} s] job stopped at step {final_step}; uninterrupted run of {final_step} steps",
              flush=True)
        ref_dir = os.path.join(args.work_dir, "reference")
        reference = self.start_trainers(ref_dir, final_step, False, ports=cluster.free_loopback_ports(2),
                                        tag="_reference")
        ref_codes = [p.finish(3600)[0] for p in reference]
        if ref_codes != [0, 0]:
            raise SystemExit(f"the uninterrupted run failed: exits {ref_codes}; logs in {self.logs}")
        report = {"mode": "service" if args.service else "plain", "faults_injected": len(faults),
                  "final_step": final_step, "wall_s": round(self.now(), 1), "seed": args.seed,
                  "input_workers": args.input_workers if args.service else 0, "config_overrides": self.sets}
        report.update(_compare(self, final_step, ref_dir, reference[0]))
        report["summary"] = _summary(faults)
        report["faults"] = faults
        return report


def _checkpoint_tensors(prefix: str) -> dict:
    import tensorflow as tf
    reader = tf.train.load_checkpoint(prefix)
    return {k: reader.get_tensor(k) for k in reader.get_variable_to_shape_map()
            if not k.startswith(("save_counter", "_CHECKPOINTABLE"))}


def _compare(soak: Soak, final_step: int, ref_dir: str, ref_chief: Proc) -> dict:
    """Without the service: every variable of both checkpoints of `final_step`, bit for bit. With it: the loss."""
    import numpy as np
    if not soak.args.service:
        got = _checkpoint_tensors(os.path.join(soak.model_dir, "checkpoints", f"ckpt-{final_step}"))
        want = _checkpoint_tensors(os.path.join(ref_dir, "checkpoints", f"ckpt-{final_step}"))
        differing = sorted(k for k in want if k not in got or not np.array_equal(got[k], want[k]))
        return {"final_weights_equal_uninterrupted": not differing and sorted(got) == sorted(want),
                "variables_compared": len(want), "variables_differing": differing[:10]}
    losses = {}
    for p in soak.chiefs:  # in start order: the last incarnation's loss of each step wins
        for _, step, loss in p.steps():
            losses[step] = loss
    ref = {step: loss for _, step, loss in ref_chief.steps()}
    window = max(5, final_step // 5)
    tail = [losses[s] for s in sorted(losses)[-window:]]
    ref_tail = [ref[s] for s in sorted(ref)[-window:]]
    head = [ref[s] for s in sorted(ref)[:window]]
    ratio = statistics.mean(tail) / statistics.mean(ref_tail)
    return {"final_loss_mean": round(statistics.mean(tail), 4), "uninterrupted_loss_mean": round(
        statistics.mean(ref_tail), 4), "first_steps_loss_mean": round(statistics.mean(head), 4),
        "loss_window_steps": window, "loss_ratio": round(ratio, 3), "loss_in_same_range": 0.5 <= ratio <= 2.0}


def _summary(faults: list[dict]) -> dict:
    by_kind: dict[str, dict] = {}
    for f in faults:
        k = by_kind.setdefault(f["kind"], {"count": 0, "as_expected": 0, "detect_s": [], "resume_s": [],
                                           "steps_lost": [], "hangs": 0})
        k["count"] += 1
        k["as_expected"] += bool(f.get("as_expected"))
        k["hangs"] += bool(f.get("hung"))
        for key in ("detect_s", "resume_s", "steps_lost"):
            if f.get(key) is not None:
                k[key].append(f[key])
    table = {}
    for kind, k in sorted(by_kind.items()):
        row = {"count": k["count"], "as_expected": k["as_expected"], "hangs": k["hangs"]}
        for key in ("detect_s", "resume_s", "steps_lost"):
            values = k[key]
            row[f"{key}_median"] = round(statistics.median(values), 2) if values else None
            row[f"{key}_max"] = round(max(values), 2) if values else None
        table[kind] = row
    return {"by_kind": table, "hangs": sum(bool(f.get("hung")) for f in faults),
            "lost_checkpoints": sum(bool(f.get("lost_checkpoint")) for f in faults),
            "not_as_expected": sum(not f.get("as_expected") for f in faults)}


def main():
    args = _args()
    from ff3d_tf.data.synthetic import wod as synthetic
    os.makedirs(args.work_dir, exist_ok=True)
    for name in ("model", "model_service", "reference", "dispatcher", "logs"):
        path = os.path.join(args.work_dir, name)
        if os.path.exists(path):
            subprocess.run(["rm", "-rf", path], check=True)
    data_dir = os.path.join(args.work_dir, "data")
    if not os.path.isdir(data_dir):
        for seed in (5, 6):  # two small segments of 5 frames (8 pairs)
            synthetic.write_segment(os.path.join(data_dir, f"segment-soak{seed}.tfrecord"),
                                    synthetic.SegmentSpec(seed=seed, num_frames=5, lidar_scale=0.12))
    soak = Soak(args, list(SOAK_OVERRIDES) + list(args.set))
    report = soak.run()
    report = {"generated_by": "tools/soak_train.py", **report}
    merged = {}
    if os.path.exists(args.out):
        with open(args.out) as f:
            merged = json.load(f)
    merged[report["mode"]] = report
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(merged, f, indent=1)
    s = report["summary"]
    verdict = (f"final weights equal the uninterrupted run: {report['final_weights_equal_uninterrupted']}"
               if "final_weights_equal_uninterrupted" in report else
               f"final loss in the uninterrupted run's range: {report['loss_in_same_range']} "
               f"(ratio {report['loss_ratio']})")
    print(f"{report['faults_injected']} faults, {s['hangs']} hangs, {s['lost_checkpoints']} lost checkpoints, "
          f"{s['not_as_expected']} not as expected; {verdict}; report {args.out}")
    ok = s["hangs"] == 0 and s["lost_checkpoints"] == 0 and report.get(
        "final_weights_equal_uninterrupted", report.get("loss_in_same_range"))
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    _common.run(main)
