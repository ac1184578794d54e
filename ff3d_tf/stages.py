"""Resumable jobs of several tools: each stage a subprocess that leaves a record when it finishes, so that the same
command run again continues where the job stopped. The standard library only (a job's runner imports no TensorFlow).

A stage's record `RECORD_DIR/<stage>.json`, written atomically once its tool exits with status 0, holds
- `command`: the tool and its arguments (the interpreter left out);
- `code`: `code_fingerprint()`, a SHA-256 of the project's Python files and configs (a tool's defaults live there);
- `outputs`: {path: {relative file: size}} of the files and folders the stage wrote (`listing`);
- `seconds`: how long it ran.

The rule. A stage is skipped when its record holds the same command and the same code, every output is still there
with the same files and sizes, and no earlier stage ran in this job (a stage that ran may have changed a later one's
inputs). Otherwise it runs. When its last start (`RECORD_DIR/<stage>.started.json`, written before the tool starts) was
of another command or code, its outputs are removed first: the tools skip or resume from what exists (segments already
written, a model_dir's checkpoints), which would mix outputs of another command or code into this run. When it was of
the same command and code, the interrupted stage resumes its own way.

Progress: one line when a stage is skipped, starts and ends, `=== [k/N] <stage> ...`, with the job's elapsed time and
an estimate of the time left: each stage still to run counts the seconds of its last record (of any command or code),
or, without one, the mean seconds of the stages this job ran.

Ctrl-C reaches the whole process group: the runner ignores SIGINT while a stage runs, so the stage handles it
(training writes a checkpoint) and exits, and the runner then raises `StageError` instead of killing it mid-write.
"""
from __future__ import annotations

import glob
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from typing import Callable, Sequence

from ff3d_tf.json_io import write_json

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CODE_PATTERNS = ("ff3d_tf/**/*.py", "tools/*.py", "configs/*.yaml")


class StageError(RuntimeError):
    """A stage that stopped (non-zero exit status) or did not write its outputs; the message says how to go on."""


def code_fingerprint(root: str = ROOT, patterns: Sequence[str] = CODE_PATTERNS) -> str:
    """SHA-256 of the files of `patterns` under `root` (names and contents): what a stage's outputs depend on besides
    its command line."""
    digest = hashlib.sha256()
    for path in sorted({p for pattern in patterns for p in glob.glob(os.path.join(root, pattern), recursive=True)}):
        digest.update(os.path.relpath(path, root).encode() + b"\0")
        with open(path, "rb") as f:
            digest.update(f.read() + b"\0")
    return digest.hexdigest()


def listing(path: str) -> dict[str, int]:
    """{relative file: size} of every file under a folder, or {"": size} of a file: what a record keeps of an
    output."""
    if os.path.isfile(path):
        return {"": os.path.getsize(path)}
    found = {}
    for folder, _, names in os.walk(path):
        for name in names:
            full = os.path.join(folder, name)
            found[os.path.relpath(full, path)] = os.path.getsize(full)
    return found


def _read_json(path: str) -> dict:
    try:
        with open(path) as f:
            found = json.load(f)
    except (OSError, ValueError):  # absent, or cut short: nothing is known of it
        return {}
    return found if isinstance(found, dict) else {}


def _remove(path: str) -> None:
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path)
    elif os.path.lexists(path):
        os.remove(path)


class Stages:
    """Runs the stages of `plan` (their names, in order) as subprocesses by the rule of the module docstring.

    After the job: `seconds` {stage: seconds, from its record when skipped}, `skipped` [stages skipped this run].
    `code` defaults to `code_fingerprint()`; `cwd` is the stages' working directory (default: this process's).
    """

    def __init__(self, record_dir: str, plan: Sequence[str], code: str | None = None, cwd: str | None = None,
                 log: Callable[[str], None] | None = None):
        if len(set(plan)) != len(plan):
            raise ValueError(f"stage names repeat in {list(plan)}")
        self.record_dir, self.plan, self.cwd = record_dir, list(plan), cwd
        self.code = code_fingerprint() if code is None else code
        self.log = log or (lambda line: print(line, flush=True))
        self.seconds: dict[str, float] = {}
        self.skipped: list[str] = []
        self.ran_this_job: list[str] = []
        # Seconds of each stage's last record, read before this job overwrites any: the estimate of the time left.
        self._last_seconds = {name: _read_json(self._path(name)).get("seconds") for name in self.plan}
        self._t0 = time.time()

    def _path(self, name: str, kind: str = "") -> str:
        return os.path.join(self.record_dir, name.replace(" ", "_") + kind + ".json")

    def _key(self, args: Sequence[str]) -> dict:
        return {"command": list(args), "code": self.code}

    def complete(self, name: str, args: Sequence[str]) -> dict | None:
        """The record of `name` when it holds this command and code and its outputs are all unchanged, else None."""
        record = _read_json(self._path(name))
        key = self._key(args)
        if {k: record.get(k) for k in key} != key or not isinstance(record.get("outputs"), dict):
            return None
        if all(os.path.exists(p) and listing(p) == files for p, files in record["outputs"].items()):
            return record
        return None

    def _progress(self, name: str, include_this: bool) -> str:
        """"elapsed X s[, about Y s left]" after (or, with `include_this`, before) stage `name`."""
        text = f"elapsed {time.time() - self._t0:.0f} s"
        left = self.plan[self.plan.index(name) + (0 if include_this else 1):]
        ran = [self.seconds[n] for n in self.ran_this_job]
        guesses = [self._last_seconds.get(n) if self._last_seconds.get(n) is not None else
                   (sum(ran) / len(ran) if ran else None) for n in left]
        if left and None not in guesses:
            text += f", about {sum(guesses):.0f} s left"
        return text

    def run(self, name: str, args: Sequence[str], outputs: Sequence[str], after: Callable[[], None] | None = None
            ) -> bool:
        """Runs `args` (a tool and its flags, with this interpreter) unless the rule skips it; `after()` finishes its
        outputs (e.g. renames a folder written under a temporary name). True when it ran."""
        if name not in self.plan:
            raise ValueError(f"stage {name!r} is not in the plan {self.plan}")
        head = f"[{self.plan.index(name) + 1}/{len(self.plan)}] {name}"
        record = None if self.ran_this_job else self.complete(name, args)
        if record is not None:
            self.seconds[name] = float(record.get("seconds", 0.0))
            self.skipped.append(name)
            self.log(f"=== {head}: complete ({self.seconds[name]:.0f} s when run), skipped")
            return False
        os.makedirs(self.record_dir, exist_ok=True)
        key = self._key(args)
        started = _read_json(self._path(name, ".started"))
        if {k: started.get(k) for k in key} != key:
            for path in outputs:
                if os.path.lexists(path):
                    self.log(f"=== {head}: removing {path} (written by another command or code)")
                    _remove(path)
        write_json(self._path(name, ".started"), key)
        self.log(f"\n=== {head} ({self._progress(name, include_this=True)}): {' '.join(args)}")
        t = time.time()
        returncode = self._call([sys.executable, *args])
        self.ran_this_job.append(name)
        self.seconds[name] = time.time() - t
        if returncode != 0:
            raise StageError(f"stage {name} stopped (exit status {returncode}); run the same command again to "
                             f"resume")
        if after is not None:
            after()
        missing = [p for p in outputs if not os.path.exists(p)]
        if missing:
            raise StageError(f"stage {name} finished without writing {missing}")
        write_json(self._path(name), {**key, "outputs": {p: listing(p) for p in outputs},
                                       "seconds": self.seconds[name]})
        self.log(f"=== {head} done in {self.seconds[name]:.0f} s ({self._progress(name, include_this=False)})")
        return True

    def _call(self, command: list[str]) -> int:
        proc = subprocess.Popen(command, cwd=self.cwd)
        # Ctrl-C reaches the whole process group: the stage handles it and this process waits for it to finish.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            return proc.wait()
        finally:
            signal.signal(signal.SIGINT, previous)
