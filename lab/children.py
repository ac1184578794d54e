"""One measurement in a fresh process: what every benchmark and profiler uses when a reading must not share a process
with another (thread pools cannot shrink once started, one variant's memory must not weigh on the next, an
environment variable such as `TF_ENABLE_ONEDNN_OPTS` is read only when TensorFlow starts).

`run_child("lab.x.y:function", {kwargs}, cores=2, env={...})` starts `python -c` in a new process with `env`
added to this one's environment (and, with `cores`, TensorFlow's thread pools sized to them), in the checkout with it
first on PYTHONPATH (the lab is not installed); the child restricts itself to its first `cores` CPUs before anything
else, imports `lab.x.y`, calls `function(**kwargs)` and writes its result (a JSON-serialisable dict) to a file the
parent reads back. The function is named, never pickled: only functions of the lab and of ff3d_tf run, with JSON
arguments. A child that fails, or runs past `timeout_s`, raises `ChildError` with the tail of its output;
`run_child(..., on_error="record")` returns {"error": that text} instead, for studies that report a failed variant
beside the others.

Standard library only.
"""
from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import tempfile

from lab.paths import ROOT

PACKAGES = ("lab", "ff3d_tf")  # whose functions a child may run (the child imports this module from the first)
OUTPUT_TAIL_CHARS = 4000


class ChildError(RuntimeError):
    """A measurement's process failed or ran too long; the message names it and ends with its output's tail."""


def child_environment(cores: int | None = None, env: dict | None = None, base: dict | None = None) -> dict:
    """`base` (default: this process's environment) with `env` added; with `cores`, TensorFlow's inter- and intra-op
    pools sized to them (an explicit value in `env` wins). The repository is put first on PYTHONPATH so that the child
    imports this checkout."""
    out = dict(os.environ if base is None else base)
    if cores is not None:
        out.update({"TF_NUM_INTEROP_THREADS": str(cores), "TF_NUM_INTRAOP_THREADS": str(cores)})
    out.update(env or {})
    out["PYTHONPATH"] = os.pathsep.join(p for p in (ROOT, out.get("PYTHONPATH", "")) if p)
    return out


def run_child(function: str, kwargs: dict | None = None, *, cores: int | None = None, env: dict | None = None,
              base: dict | None = None, timeout_s: float | None = None, what: str | None = None,
              on_error: str = "raise") -> dict:
    """The dict `function(**kwargs)` returns, computed in a fresh process (module docstring). `function`:
    "lab.module:name" (or "ff3d_tf.module:name"). `base`: the child's whole environment before `env` and the core
    settings (default: this process's; a study whose variants must not inherit the caller's settings passes its own).
    `what`: how errors name this measurement (default: `function`)."""
    _split(function)
    if on_error not in ("raise", "record"):
        raise ValueError(f"on_error={on_error!r}: 'raise' or 'record'")
    what = what or function
    with tempfile.TemporaryDirectory(prefix="ff3d_child_") as tmp:
        out = os.path.join(tmp, "result.json")
        spec = {"function": function, "kwargs": kwargs or {}, "cores": cores, "out": out}
        cmd = [sys.executable, "-c", "from lab import children; children.main()", json.dumps(spec)]
        try:
            proc = subprocess.run(cmd, env=child_environment(cores, env, base), cwd=ROOT, capture_output=True, text=True,
                                  timeout=timeout_s)
            failure = None if proc.returncode == 0 else \
                f"{what}: its process ended with exit {proc.returncode}:\n{_tail(proc.stdout + proc.stderr)}"
        except subprocess.TimeoutExpired as e:
            output = "".join(x.decode(errors="replace") if isinstance(x, bytes) else (x or "")
                             for x in (e.stdout, e.stderr))
            failure = f"{what}: still running after {timeout_s} s, stopped:\n{_tail(output)}"
        if failure is None and not os.path.exists(out):
            failure = f"{what}: its process ended without writing a result"
        if failure is not None:
            if on_error == "record":
                return {"error": failure}
            raise ChildError(failure)
        with open(out) as f:
            return json.load(f)


def main(argv: list[str] | None = None) -> None:
    """The child's side of `run_child` (argv[1]: the JSON spec)."""
    spec = json.loads((sys.argv if argv is None else argv)[1])
    if spec.get("cores"):
        pin_cores(int(spec["cores"]))
    module, name = _split(spec["function"])
    result = getattr(importlib.import_module(module), name)(**spec["kwargs"])
    if not isinstance(result, dict):
        raise TypeError(f"{spec['function']} returned {type(result).__name__}; a measurement returns a dict")
    tmp = spec["out"] + ".partial"
    with open(tmp, "w") as f:
        json.dump(result, f)
    os.replace(tmp, spec["out"])


def pin_cores(cores: int) -> list[int]:
    """Restricts this process to its first `cores` CPUs (call before TensorFlow starts its thread pools)."""
    available = sorted(os.sched_getaffinity(0))
    if not 1 <= cores <= len(available):
        raise ValueError(f"{cores} cores asked; this process may use {len(available)} CPUs")
    os.sched_setaffinity(0, available[:cores])
    return available[:cores]


def placement() -> dict:
    """Where this process runs: {"cpus": the CPUs it may use, "tf_threads": TensorFlow's pool sizes from the
    environment (None where unset)}; a child's record of what it was given."""
    return {"cpus": sorted(os.sched_getaffinity(0)),
            "tf_threads": {k: os.environ.get(k) for k in ("TF_NUM_INTEROP_THREADS", "TF_NUM_INTRAOP_THREADS")}}


def _split(function: str) -> tuple[str, str]:
    module, sep, name = function.partition(":")
    if not sep or not name or not any(module == p or module.startswith(p + ".") for p in PACKAGES):
        expected = " or ".join(f"'{p}.module:name'" for p in PACKAGES)
        raise ValueError(f"function={function!r}: expected {expected}")
    return module, name


def _tail(text: str) -> str:
    return text[-OUTPUT_TAIL_CHARS:]
