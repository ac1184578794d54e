"""The one shape of the project's data jobs: an Apache Beam pipeline with one element per input (a WOD segment, an
Argoverse 2 log), each writing its output file atomically and skipping outputs that exist, so that a rerun resumes.

`run_per_input(inputs, process, ...)` runs `process(input) -> counts` for every input (Beam's in-process FnApiRunner
unless the standard Beam options say otherwise; `--direct_num_workers=N --direct_running_mode=multi_processing` runs N
at once), logs progress with rate and ETA as inputs finish, and returns the summed counts, also written as JSON into
`out_dir`.
`process` must be picklable (a module-level function or a `functools.partial` of one).

An input whose data the project's own checks reject (`input_errors`: a bad record, point file or Argoverse 2 log, a
missing sweep, each error naming file, record and field) fails alone: the job goes on with the other inputs (their
outputs are written, so a rerun after the input is fixed resumes), its summary counts the failed inputs
(`FAILED_KEY`, with their messages), and `run_per_input` then raises `DataJobError` with one line per failed input,
which the tools print as such (`tools/_common.run`), instead of Beam's tracebacks around each copy of the message.
Any other exception (a bug) still stops the job with its traceback.
"""
from __future__ import annotations

import json
import logging
import os
import time
from typing import Callable

_LOG = logging.getLogger(__name__)
FAILED_KEY = "failed_inputs"  # the summary's list of "<input>: <error>" lines


class DataJobError(RuntimeError):
    """Inputs of a data job that failed the project's checks; `failures`: one line per input, naming it and the
    error; `counts`: the job's summary (the other inputs' counts included)."""

    def __init__(self, job_name: str, failures: list[str], total: int, counts: dict):
        self.failures, self.counts = list(failures), counts
        super().__init__(f"{job_name}: {len(failures)} of {total} inputs failed (each named above); the others are "
                         "written, and a rerun after the fix resumes")


def input_errors() -> tuple[type, ...]:
    """The errors of the project's checks of input data, each naming file, record and field (imported when called:
    the job's workers import them in their own process)."""
    from ff3d_tf.config import ConfigError
    from ff3d_tf.data.av2.argoverse2 import Argoverse2FormatError
    from ff3d_tf.data.files.point_file_errors import PointFileError
    from ff3d_tf.data.wod.wod_format import WireFormatError
    from ff3d_tf.data.wod_errors import FrameDecodeError
    return FrameDecodeError, PointFileError, Argoverse2FormatError, WireFormatError, ConfigError


def merge_counts(all_counts) -> dict:
    """Per key: numbers summed, lists (e.g. the names of failed items) concatenated."""
    out: dict = {}
    for counts in all_counts:
        for k, v in counts.items():
            out[k] = out[k] + v if k in out else v
    return out


class Progress:
    """Inputs done out of a total, with the rate and the time left, for a job's log."""

    def __init__(self, total: int, unit: str = "inputs", clock=time.monotonic):
        self.total, self.unit, self.clock = total, unit, clock
        self.start, self.done = clock(), 0

    def step(self, n: int = 1) -> str:
        self.done += n
        elapsed = max(self.clock() - self.start, 1e-9)
        rate = self.done / elapsed
        left = (self.total - self.done) / rate if rate > 0 else float("inf")
        return (f"{self.done}/{self.total} {self.unit}, {rate * 60:.2f}/min, "
                f"ETA {time.strftime('%H:%M:%S', time.gmtime(left)) if left != float('inf') else '?'}")


def write_json(obj, path: str) -> str:
    import tensorflow as tf
    with tf.io.gfile.GFile(path + ".partial", "w") as f:
        json.dump(obj, f, indent=1, sort_keys=True)
    tf.io.gfile.rename(path + ".partial", path, overwrite=True)
    return path


def run_per_input(inputs: list[str], process: Callable[[str], dict], out_dir: str, job_name: str,
                  beam_args: list[str] | None = None, result_name: str | None = None) -> dict:
    """Runs `process` on every input in a Beam pipeline; returns the summed counts (also `<out_dir>/<result_name>`,
    default `<job_name>_counts.json`); raises `DataJobError` after the job when inputs failed (module docstring)."""
    import apache_beam as beam
    import tensorflow as tf
    from apache_beam.options.pipeline_options import PipelineOptions

    result_path = os.path.join(out_dir, result_name or f"{job_name}_counts.json")
    tf.io.gfile.makedirs(out_dir)
    total = len(inputs)

    class Process(beam.DoFn):
        def setup(self):
            self.progress = Progress(total)

        def process(self, path):
            try:
                counts = process(path)
            except input_errors() as err:  # the input fails alone, named once, after the job (module docstring)
                _LOG.warning("%s: failed: %s (the job goes on with the other inputs)", job_name, path)
                yield {FAILED_KEY: [f"{path}: {err}"]}
                return
            for k, v in counts.items():
                if isinstance(v, (int, float)):
                    beam.metrics.Metrics.counter(job_name, k).inc(int(v))
            # One worker's view of the job: with several workers each reports the inputs it did.
            _LOG.info("%s: done %s (%s): %s", job_name, path, self.progress.step(), counts)
            yield counts

    beam_args = list(beam_args or [])
    if not any(a.startswith("--runner") for a in beam_args):
        # Beam's in-process runner. Not "DirectRunner": since Beam 2.6x it first tries the Prism runner, which
        # downloads a binary from GitHub (offline: a failed download, logged, then the fallback to this runner).
        beam_args.append("--runner=FnApiRunner")
    with beam.Pipeline(options=PipelineOptions(beam_args)) as p:
        (p | "Inputs" >> beam.Create(list(inputs))
           | "Reshuffle" >> beam.Reshuffle()
           | "Process" >> beam.ParDo(Process())
           | "Collect" >> beam.combiners.ToList()
           | "Merge" >> beam.Map(merge_counts)
           | "Write" >> beam.Map(write_json, result_path))
    with tf.io.gfile.GFile(result_path) as f:
        counts = json.load(f)
    if counts.get(FAILED_KEY):
        raise DataJobError(job_name, counts[FAILED_KEY], total, counts)
    return counts
