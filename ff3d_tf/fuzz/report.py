"""What a fuzz run records and how one input is judged: the outcomes, `Result`, `Report`, the frame check, the watchdog.

Each mutant damages a valid input one way (a `kind`) and must end as either
  - `decoded`: a decode whose arrays are finite and consistent (a config that validates and round-trips), or
  - `named_error`: the reader's own error naming file, record and field (`FrameDecodeError`; `Argoverse2FormatError`
    naming file and column; `ConfigError` naming the key and what is allowed).
Anything else is a defect: `unnamed_error` (our error without file/record/field), `raw_error` (a TensorFlow or
library error escaping), `crash` (any other exception), `nonfinite` (a decode with NaN/Inf or inconsistent arrays),
`slow` (over the per-input time bound), `huge_allocation` (a reader that allocated what a header claims, where the
fuzzer measures it: `ff3d_tf.fuzz.files`). A hang is not waited for: with `hang_s` the watchdog aborts the process with
every thread's traceback.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import faulthandler
import resource
import time
from typing import Callable

import numpy as np

from ff3d_tf import schema

DEFECTS = ("unnamed_error", "raw_error", "crash", "nonfinite", "slow", "huge_allocation")
OUTCOMES = ("decoded", "named_error") + DEFECTS
SECONDS_PER_INPUT = 10.0  # bound on one decode, far above what a decode of any valid record takes
NONFINITE = (np.nan, np.inf, -np.inf)  # values the mutators write into float fields


@dataclasses.dataclass
class Result:
    kind: str
    outcome: str
    seconds: float
    detail: str


@dataclasses.dataclass
class Report:
    """Outcomes of a fuzz run: counts by kind x outcome, the slowest input, peak memory."""

    results: list = dataclasses.field(default_factory=list)

    def add(self, result: Result) -> None:
        self.results.append(result)

    @property
    def defects(self) -> list[Result]:
        return [r for r in self.results if r.outcome in DEFECTS]

    def table(self) -> dict[str, collections.Counter]:
        by_kind: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        for r in self.results:
            by_kind[r.kind][r.outcome] += 1
        return dict(by_kind)

    def slowest(self) -> Result | None:
        return max(self.results, key=lambda r: r.seconds, default=None)

    def format(self, title: str) -> str:
        width = max(len(o) for o in OUTCOMES) + 1
        lines = [f"{title}: {len(self.results)} inputs",
                 f"  {'kind':24s}" + "".join(f"{o:>{width}s}" for o in OUTCOMES)]
        for kind, counts in sorted(self.table().items()):
            lines.append(f"  {kind:24s}" + "".join(f"{counts.get(o, 0):{width}d}" for o in OUTCOMES))
        slow = self.slowest()
        if slow is not None:
            lines.append(f"  slowest: {slow.seconds * 1e3:.1f} ms ({slow.kind}: {slow.detail[:120]})")
        lines.append(f"  peak memory (max RSS of this process): {peak_rss_mib():.0f} MiB")
        for r in self.defects[:20]:
            lines.append(f"  DEFECT {r.kind} -> {r.outcome}: {r.detail[:300]}")
        return "\n".join(lines)


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


@contextlib.contextmanager
def watchdog(seconds: float | None):
    """Aborts the process with every thread's traceback if the block runs longer than `seconds` (a hang is a defect
    to see, not to wait for); None: no watchdog."""
    if seconds is None:
        yield
        return
    faulthandler.dump_traceback_later(seconds, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


def judge(report: Report, kind: str, what: str, classify: Callable[[], tuple[str, str]], hang_s: float | None,
          bound_s: float | None = SECONDS_PER_INPUT) -> Result:
    """Runs `classify()` -> (outcome, detail) of one input under the watchdog (`hang_s`) and adds its `Result` to
    `report`: `slow` if it took over `bound_s` (None: no bound), the detail prefixed by `what` was damaged."""
    start = time.perf_counter()
    with watchdog(hang_s):
        outcome, detail = classify()
    seconds = time.perf_counter() - start
    result = Result(kind, "slow" if bound_s is not None and seconds > bound_s else outcome, seconds,
                    f"{what} -> {detail}")
    report.add(result)
    return result


def check_frame(frame: dict) -> str | None:
    """None if a decoded frame (`ff3d_tf.schema` keys) is finite and consistent, else what is wrong."""
    n = len(frame["points_xyz"])
    for key in ("points_xyz", "intensity", "elongation", "flow_mps", "pose"):
        if not np.all(np.isfinite(frame[key])):
            return f"{key} has non-finite values"
    for key in ("intensity", "elongation", "flow_mps", "class_id", "laser_name"):
        if len(frame[key]) != n:
            return f"{key} has {len(frame[key])} rows for {n} points"
    classes = frame["class_id"]
    if classes.size and (classes.min() < schema.CLASS_NO_LABEL or classes.max() > max(schema.CLASS_NAMES)):
        return "class_id out of range"
    return None


def pick(rng: np.random.Generator, items):
    """One of `items`, drawn by `rng` (the mutators' one way to choose)."""
    return items[int(rng.integers(len(items)))]
