"""Sequences of a user's sweeps: the directories that `tools/write_pair_records.py --source files` reads and that
`tools/predict.py --sweeps_dir` predicts, with their poses, timestamps and (optionally) tracked boxes.

A sequence is one sweeps directory (`point_files.list_sweeps`: point files sorted by name; poses as `poses.txt` or
per-sweep pose files, `point_files.sweep_poses`) plus, optionally:
- `timestamps.txt`: one time per sweep in sweep order, in seconds (any decimal number, read exactly to the
  nanosecond; blank lines and `#` comments skipped), strictly increasing; without it, sweep k is at k x the sweep
  period (`DEFAULT_SWEEP_PERIOD_S` unless the caller gives another);
- a box table (`box_table`: `boxes.csv` or `boxes.feather`).

`list_sequences(DIR_OR_GLOB)`: a directory holding point files is one sequence; a directory of such directories is
one sequence per subdirectory (sorted); a glob names sequence directories. `write_sequence` writes one (the synthetic
default and tests).

Errors are `PointFileError` naming the file and the line or field.
"""
from __future__ import annotations

import dataclasses
import decimal
import glob
import os

import numpy as np

from ff3d_tf.data.files import box_table, point_files
from ff3d_tf.data.files.point_file_errors import PointFileError

TIMESTAMPS_FILE = "timestamps.txt"
DEFAULT_SWEEP_PERIOD_S = 0.1  # 10 Hz, the rate of WOD, Argoverse 2 and the model's training pairs
MAX_TIMESTAMPS_BYTES = 1 << 26  # a timestamps file of one short line per sweep is far smaller


@dataclasses.dataclass(frozen=True)
class SweepSequence:
    """One sequence: its sweeps in order, their poses (None: the directory has none), their times (ns) and where
    those came from, and its box table (None: no boxes)."""
    directory: str
    sweeps: tuple[str, ...]
    poses: tuple[np.ndarray, ...] | None
    timestamps_ns: tuple[int, ...]
    timestamps_from: str  # "timestamps.txt" or "a sweep every <period> s"
    box_table: str | None

    @property
    def name(self) -> str:
        """The sequence's id: its directory's name."""
        return os.path.basename(os.path.normpath(self.directory))

    @property
    def stems(self) -> list[str]:
        """Each sweep's name without its suffix: the `sweep` of its boxes and the name of its outputs."""
        return [os.path.splitext(os.path.basename(s))[0] for s in self.sweeps]


def _seconds_to_ns(path: str, line: int, token: str) -> int:
    try:
        value = decimal.Decimal(token)
    except decimal.InvalidOperation:
        raise PointFileError(path, f"line {line}", f"{token!r} is not a number of seconds") from None
    if not value.is_finite():
        raise PointFileError(path, f"line {line}", f"{token!r}: not a finite time")
    if abs(value) > decimal.Decimal(10) ** 12:
        raise PointFileError(path, f"line {line}", f"{token!r} s: not a time (over 10^12 s)")
    return int((value * 1_000_000_000).to_integral_value(decimal.ROUND_HALF_EVEN))


def read_timestamps(path: str, num_sweeps: int) -> list[int]:
    """The sweeps' times (ns) of a `timestamps.txt` (module docstring): as many as sweeps, strictly increasing."""
    if os.path.getsize(path) > MAX_TIMESTAMPS_BYTES:
        raise PointFileError(path, "file", f"over {MAX_TIMESTAMPS_BYTES} bytes: not a list of sweep times")
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = f.read().splitlines()
    stamps, lines_of = [], []
    for i, line in enumerate(lines, start=1):
        tokens = line.split("#", 1)[0].split()
        if not tokens:
            continue
        if len(tokens) != 1:
            raise PointFileError(path, f"line {i}", f"{len(tokens)} values; one time (s) per line")
        stamps.append(_seconds_to_ns(path, i, tokens[0]))
        lines_of.append(i)
        if len(stamps) > 1 and stamps[-1] <= stamps[-2]:
            raise PointFileError(path, f"line {i}", f"{tokens[0]} s is not after the time before it (line "
                                                    f"{lines_of[-2]}): times increase strictly, in sweep order")
    if len(stamps) != num_sweeps:
        raise PointFileError(path, "file", f"{len(stamps)} times for {num_sweeps} sweeps (one line per sweep, in the "
                                           "sweeps' name order)")
    return stamps


def check_sweep_period(period_s: float) -> float:
    period_s = float(period_s)
    if not (np.isfinite(period_s) and period_s > 0):
        raise ValueError(f"sweep period {period_s!r} s: must be a finite number > 0")
    return period_s


def sweep_times_ns(directory: str, num_sweeps: int, sweep_period_s: float = DEFAULT_SWEEP_PERIOD_S
                   ) -> tuple[list[int], str]:
    """(each sweep's time in ns, where they came from): `timestamps.txt` if the directory has one, else a sweep every
    `sweep_period_s`."""
    path = os.path.join(directory, TIMESTAMPS_FILE)
    if os.path.isfile(path):
        return read_timestamps(path, num_sweeps), TIMESTAMPS_FILE
    period_s = check_sweep_period(sweep_period_s)
    return [int(round(k * period_s * 1e9)) for k in range(num_sweeps)], f"a sweep every {period_s:g} s"


def read_sequence(directory: str, sweep_period_s: float = DEFAULT_SWEEP_PERIOD_S) -> SweepSequence:
    """A sequence's sweeps, poses, times and box table path (the table itself is read by `read_boxes`)."""
    sweeps = point_files.list_sweeps(directory)
    poses = point_files.sweep_poses(directory, sweeps)
    stamps, origin = sweep_times_ns(directory, len(sweeps), sweep_period_s)
    return SweepSequence(directory, tuple(sweeps), None if poses is None else tuple(poses), tuple(stamps), origin,
                         box_table.find_box_table(directory))


def read_boxes(sequence: SweepSequence, class_map: dict | None = None) -> dict[str, dict] | None:
    """The sequence's boxes by sweep stem (`box_table.read_box_table`), None without a box table."""
    if sequence.box_table is None:
        return None
    return box_table.read_box_table(sequence.box_table, sequence.stems, class_map)


def _has_sweeps(directory: str) -> bool:
    return os.path.isdir(directory) and any(
        point_files._is_sweep_name(n) and os.path.isfile(os.path.join(directory, n)) for n in os.listdir(directory))


def list_sequences(dir_or_glob: str) -> list[str]:
    """Sequence directories (module docstring), sorted; FileNotFoundError naming the input when there are none."""
    if any(ch in dir_or_glob for ch in "*?["):
        found = sorted(d for d in glob.glob(dir_or_glob) if _has_sweeps(d))
    elif _has_sweeps(dir_or_glob):
        found = [dir_or_glob]
    elif os.path.isdir(dir_or_glob):
        found = sorted(os.path.join(dir_or_glob, n) for n in os.listdir(dir_or_glob)
                       if _has_sweeps(os.path.join(dir_or_glob, n)))
    else:
        raise FileNotFoundError(f"{dir_or_glob}: no such directory")
    if not found:
        raise FileNotFoundError(f"{dir_or_glob}: no sweeps directories (a directory of point files "
                                f"{'/'.join(point_files.POINT_SUFFIXES)}, or a directory of such directories)")
    names = {}
    for d in found:
        name = os.path.basename(os.path.normpath(d))
        if name in names:
            raise ValueError(f"{d} and {names[name]}: two sequences named {name!r} (a sequence's records file is "
                             "named after its directory): rename one")
        names[name] = d
    return found


def write_sequence(directory: str, clouds: list[tuple[str, np.ndarray, np.ndarray]], poses: list[np.ndarray],
                   timestamps_ns: list[int] | None = None, boxes_by_sweep: dict[str, dict] | None = None) -> str:
    """Writes a sequence: per sweep (stem, points_xyz [N,3], intensity [N]) a KITTI-style `<stem>.bin` (float32 x, y,
    z, intensity), `poses.txt` (3x4 rows, every digit of their float64), `timestamps.txt` (s, exact to the ns) when
    given, and `boxes.csv` (`box_table.write_box_table`) when given. Returns the directory."""
    os.makedirs(directory, exist_ok=True)
    for stem, xyz, intensity in clouds:
        rows = np.concatenate([np.asarray(xyz, np.float32), np.asarray(intensity, np.float32)[:, None]], 1)
        with open(os.path.join(directory, stem + ".bin.partial"), "wb") as f:
            f.write(rows.astype("<f4").tobytes())
        os.replace(os.path.join(directory, stem + ".bin.partial"), os.path.join(directory, stem + ".bin"))
    with open(os.path.join(directory, point_files.POSES_FILE), "w") as f:
        f.write("".join(" ".join(repr(float(v)) for v in np.asarray(p)[:3].reshape(-1)) + "\n" for p in poses))
    if timestamps_ns is not None:
        with open(os.path.join(directory, TIMESTAMPS_FILE), "w") as f:
            f.write("".join(f"{t // 1_000_000_000}.{t % 1_000_000_000:09d}\n" for t in timestamps_ns))
    if boxes_by_sweep is not None:
        box_table.write_box_table(os.path.join(directory, box_table.BOX_TABLE_NAMES[0]), boxes_by_sweep)
    return directory
