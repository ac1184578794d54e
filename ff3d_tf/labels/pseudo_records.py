"""Pseudo-labels at scale (ZeroFlow's recipe): NSFP flow (`ff3d_tf.labels.nsfp`) of every pair of a directory of pair
records, written as pair records again with `flow_mps_pseudo_t0` and `pseudo_valid_t0` beside whatever the input
held (human labels, ground masks, categories), so that `data.labels=pseudo` trains on them and evaluation still
scores the human labels.

One pair (`fit_pair`, also what `ff3d_tf.labels.nsfp_av2_check` scores): the fit sees the points of both clouds in the
fitted region (the crop: by default the Argoverse 2 challenge's box in x and y and ZeroFlow's z range) that are not
ground, by the same rule for both clouds (`ground`: the records' own masks where they carry one for each cloud,
Argoverse 2's map raster; else the local height rule of `ff3d_tf.labels.ground`). A t0 point the fit did not see gets
no pseudo-label (`pseudo_valid_t0` False, flow 0), never a zero label. A fit whose loss or flow is not finite, or
whose share of fitted points faster than `max_speed_mps` is above `max_implausible_fraction`, is fitted again with
the next seed (`retries` times); if it stays so, the pair is named in the job's report (`bad_fits`) and written
without pseudo-labels, or the job stops (`on_bad_fit="stop"`). Points faster than `max_speed_mps` in a fit that passes
get no pseudo-label either. These options are `JobOptions` (and its `NsfpOptions`), built from the config's `nsfp`
section (`job_from_config`; `ff3d_tf.config.NsfpConfig` documents each key); the job writes the resolved config
beside its output (`<out_dir>/config.yaml`).

Input: records of any source (`tools/write_pair_records.py`, WOD or Argoverse 2, labelled or raw with `--no_labels`).
The job is the per-pair shape of `ff3d_tf.labels.enrich_records` (records in, fields added, records out; one Beam
element per records file). NSFP takes seconds to minutes per pair, so each pair's flow is kept as soon as it is fitted
(`<out>.parts/<index>.npz`, written atomically) and a rerun after a kill fits only the pairs not yet done; the output
file is assembled from the parts and written atomically, then the parts are removed. The fit is deterministic for a
seed, so a resumed run writes the same bytes as an uninterrupted one.
Convention: the project's (`ff3d_tf.schema`): motion of each t0 point from its partner cloud to t0, divided by the
gap, in m/s in the t0 vehicle frame.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
import time
from typing import Callable

import numpy as np
import tensorflow as tf
import yaml

from ff3d_tf import schema
from ff3d_tf.config import ConfigError, ExperimentConfig, NsfpConfig, nsfp_option_problem
from ff3d_tf.data import beam_job, pair_records
from ff3d_tf.data.pairs import list_segment_files
from ff3d_tf.labels import enrich_records, nsfp_av2_check
from ff3d_tf.labels.ground import pair_ground_masks
from ff3d_tf.labels.nsfp import MEASURED_FIT_OPTIONS, NsfpOptions, NsfpResult, nsfp_flow, options_from_config

_LOG = logging.getLogger(__name__)
PSEUDO_KEY, PSEUDO_VALID_KEY = schema.PSEUDO_FLOW_KEY, schema.PSEUDO_VALID_KEY
PSEUDO_EXTRAS = (PSEUDO_KEY, PSEUDO_VALID_KEY)
_JOB_DEFAULTS = NsfpConfig()  # JobOptions' defaults: the config's nsfp section's


class BadFitError(RuntimeError):
    """A pair whose fit stayed implausible with `on_bad_fit="stop"`: names the file, record and why."""


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """The pseudo-label job's options: the fit, and what the job does around it (module docstring). Defaults and
    rules: the config's `nsfp` section (`ff3d_tf.config.NsfpConfig`, which documents each; `job_from_config`)."""
    nsfp: NsfpOptions = MEASURED_FIT_OPTIONS
    ground: str = _JOB_DEFAULTS.ground  # one of config.NSFP_GROUND_RULES
    max_speed_mps: float = _JOB_DEFAULTS.max_speed_mps
    max_implausible_fraction: float = _JOB_DEFAULTS.max_implausible_fraction
    retries: int = _JOB_DEFAULTS.retries
    on_bad_fit: str = _JOB_DEFAULTS.on_bad_fit  # one of config.NSFP_BAD_FIT_ACTIONS

    def __post_init__(self):
        if not isinstance(self.nsfp, NsfpOptions):
            raise ValueError(f"JobOptions.nsfp: an NsfpOptions, got {type(self.nsfp).__name__}")
        for field in (f for f in dataclasses.fields(self) if f.name != "nsfp"):
            problem = nsfp_option_problem(field.name, getattr(self, field.name))
            if problem:
                raise ValueError(f"JobOptions.{field.name}: {problem}, got {getattr(self, field.name)!r}")


def job_from_config(cfg: ExperimentConfig) -> JobOptions:
    """The pseudo-label job that `cfg` (an ExperimentConfig) configures: its fit (`nsfp.options_from_config`) and
    every other JobOptions field from the field of the same name in `cfg.nsfp`."""
    return JobOptions(options_from_config(cfg), **{f.name: getattr(cfg.nsfp, f.name)
                                                   for f in dataclasses.fields(JobOptions) if f.name != "nsfp"})


@dataclasses.dataclass(frozen=True)
class PairFit:
    flow_mps: np.ndarray  # [N,3] float32 pseudo-labels (t0 vehicle frame), 0 where not valid
    valid: np.ndarray  # [N] bool: the point has a pseudo-label
    result: NsfpResult  # the last fit's
    ground_rule: str  # the ground rule applied: records, height or none
    attempts: int  # fits made (1 + retries used)
    problem: str  # "" for a good fit; else why the pair has no pseudo-labels


def output_manifest(manifest: pair_records.Manifest, written_by: str = "") -> pair_records.Manifest:
    """The input's manifest with the pseudo-labels and their validity among its extras."""
    return enrich_records.output_manifest(manifest, PSEUDO_EXTRAS, written_by)


def ground_masks(ex: dict, rule: str) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(ground of the t0 cloud, ground of the partner cloud, the rule applied): one rule for both clouds."""
    both = "is_ground_t0" in ex and "is_ground_tm1" in ex
    if rule == "records" and not both:
        raise ValueError("ground=records: these records carry no ground mask of both clouds (is_ground_t0 and "
                         "is_ground_tm1; Argoverse 2 records written by tools/write_pair_records.py --source av2 "
                         "do); use ground=height")
    if rule == "records" or (rule == "auto" and both):
        return np.asarray(ex["is_ground_t0"], bool), np.asarray(ex["is_ground_tm1"], bool), "records"
    if rule in ("auto", "height"):
        return (*pair_ground_masks(ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"]), "height")
    return None, None, "none"


def _implausible(result: NsfpResult, job: JobOptions) -> str:
    """Why a fit is not to be written ("" if it may be)."""
    if not math.isfinite(result.loss) and result.valid_t0.any():
        return f"the fit's loss is {result.loss}"
    fitted = result.flow_mps_t0[result.valid_t0]
    if not np.isfinite(fitted).all():
        return "the fit's flow is not finite"
    speed = np.linalg.norm(fitted, axis=1)
    fast = float((speed > job.max_speed_mps).mean()) if len(speed) else 0.0
    if fast > job.max_implausible_fraction:
        return (f"{fast:.1%} of the fitted points are faster than {job.max_speed_mps:g} m/s (fastest "
                f"{speed.max():.0f} m/s; JobOptions.max_implausible_fraction={job.max_implausible_fraction:g})")
    return ""


def fit_pair(ex: dict, job: JobOptions = JobOptions(), progress: Callable[[int, float], None] | None = None) -> PairFit:
    """The pseudo-labels of one record's pair (module docstring): ground by `job.ground` on both clouds, the fit,
    its guard and retries. `ex`: the record's fields as NumPy (`pair_records`); `progress(steps, best_loss)` is
    called between the fit's compiled segments."""
    ground_t0, ground_tm1, rule = ground_masks(ex, job.ground)
    keep_t0, keep_tm1 = (None if g is None else ~g for g in (ground_t0, ground_tm1))
    for attempt in range(job.retries + 1):
        options = dataclasses.replace(job.nsfp, seed=(job.nsfp.seed + attempt) % 2 ** 31)
        result = nsfp_flow(ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"], pair_records.pair_gap_s(ex), options,
                           keep_t0=keep_t0, keep_tm1=keep_tm1, progress=progress)
        problem = _implausible(result, job)
        if not problem:
            break
    speed = np.linalg.norm(result.flow_mps_t0, axis=1)
    valid = result.valid_t0 & (speed <= job.max_speed_mps) & (not problem)
    flow = np.where(valid[:, None], result.flow_mps_t0, 0.0).astype(np.float32)
    return PairFit(flow, valid, result, rule, attempt + 1, problem)


def pseudo_label_file(in_path: str, out_dir: str, job: JobOptions, manifest: pair_records.Manifest,
                      out_manifest: pair_records.Manifest, skip_bad_records: bool = False) -> dict:
    """Pseudo-labels of one records file into `out_dir` (same file name); resumable per pair
    (`enrich_records.enrich_pairs`). Returns counts, with the pairs written without pseudo-labels named under
    `bad_fits`."""
    counts = {"pairs": 0, "fitted_pairs": 0, "skipped_records": 0, "points_t0": 0, "pseudo_labelled_points": 0,
              "implausible_points": 0, "retried_pairs": 0, "nsfp_iterations": 0, "nsfp_seconds": 0.0,
              "bad_fits": []}
    name = os.path.basename(in_path)
    fitted = {}  # the log line of the pair fitted last

    def compute(index, ex, where):
        started = time.time()

        def fit_progress(steps, loss):
            _LOG.info("%s pair %d: %d of at most %d steps, best loss %.5f, %.0f s", name, index, steps,
                      job.nsfp.max_iterations, loss, time.time() - started)
        fit = fit_pair(ex, job, fit_progress)
        if fit.problem and job.on_bad_fit == "stop":
            raise BadFitError(f"{where}: {fit.problem} after {fit.attempts} fits (on_bad_fit=stop; "
                              "on_bad_fit=skip writes the pair without pseudo-labels)")
        r = fit.result
        counts["fitted_pairs"] += 1
        counts["retried_pairs"] += int(fit.attempts > 1)
        counts["implausible_points"] += int((r.valid_t0 & ~fit.valid).sum()) if not fit.problem else 0
        counts["nsfp_iterations"] += r.num_iterations
        counts["nsfp_seconds"] += r.grid_s + r.fit_s
        fitted["line"] = (f"{name} pair {index}: {r.num_iterations} iterations, loss {r.loss:.5f}, "
                          f"{r.grid_s + r.fit_s:.1f} s, ground {fit.ground_rule}, {int(fit.valid.sum())} of "
                          f"{len(fit.valid)} points labelled" + (f", NOT LABELLED: {fit.problem}" if fit.problem
                                                                  else ""))
        return {PSEUDO_KEY: fit.flow_mps, PSEUDO_VALID_KEY: fit.valid, "problem": np.array(fit.problem)}

    def on_pair(index, ex, part, fresh, progress_line):
        if fresh:
            _LOG.info("%s; %s", fitted.pop("line"), progress_line)
        problem = str(part["problem"])
        if problem:
            where = enrich_records.record_where(in_path, index, ex)
            _LOG.warning("%s: written without pseudo-labels: %s", where, problem)
            counts["bad_fits"].append(f"{where}: {problem}")
        counts["pairs"] += 1
        counts["points_t0"] += len(part[PSEUDO_VALID_KEY])
        counts["pseudo_labelled_points"] += int(part[PSEUDO_VALID_KEY].sum())

    return enrich_records.enrich_pairs(in_path, out_dir, enrich_records.PairJob(PSEUDO_EXTRAS, compute, on_pair),
                                       manifest, out_manifest, counts, skip_bad_records)


SCORES_NAME = "pseudo_label_scores.json"
CONFIG_NAME = "config.yaml"  # the resolved config of the job, beside its pseudo-labels


def records_files(input_dir: str) -> list[str]:
    """The pair records files of `input_dir` (sorted); FileNotFoundError naming the directory when there are none."""
    files = [f for f in list_segment_files(input_dir) if f.endswith(pair_records.FILE_SUFFIX)]
    if not files:
        raise FileNotFoundError(f"{input_dir}: no pair records (*{pair_records.FILE_SUFFIX}); write them with "
                                "tools/write_pair_records.py")
    return files


def save_job_config(out_dir: str, cfg: ExperimentConfig) -> None:
    """Writes the resolved config to `<out_dir>/config.yaml`. A directory whose saved config has another `nsfp`
    section holds (part of) the pseudo-labels of another job, which a rerun would resume and mix with this one's:
    ConfigError naming the keys that differ, before any work."""
    path = os.path.join(out_dir, CONFIG_NAME)
    if tf.io.gfile.exists(path):
        with tf.io.gfile.GFile(path) as f:
            text = f.read()
        try:
            tree = yaml.safe_load(text)
        except yaml.YAMLError:
            tree = None
        saved = tree.get("nsfp") if isinstance(tree, dict) else None
        if not isinstance(saved, dict):
            raise ConfigError(f"{path}: not a saved config with an nsfp section; use another --out_dir")
        now, default = (json.loads(json.dumps(dataclasses.asdict(c))) for c in (cfg.nsfp, NsfpConfig()))  # as saved
        saved = {k: saved.get(k, default[k]) for k in now}  # a key the saved config lacks had its default
        differ = [k for k in now if saved[k] != now[k]]
        if differ:
            raise ConfigError(f"{out_dir} holds the pseudo-labels of another job: " + ", ".join(
                f"nsfp.{k} {saved[k]!r} there, {now[k]!r} here" for k in differ) + "; use another --out_dir")
    cfg.save(path)


def run_pseudo_label_job(files: list[str], out_dir: str, cfg: ExperimentConfig, beam_args: list[str] | None = None,
                         written_by: str = "", skip_bad_records: bool = False) -> dict:
    """Pseudo-labels of every records file in `files` into `out_dir` by the job that `cfg.nsfp` configures
    (`job_from_config`; a Beam job, one element per file; progress with rate and ETA per pair and per file; bad
    records named, or skipped and counted with `skip_bad_records`; bad fits named in `bad_fits`, or the job stopped
    with `nsfp.on_bad_fit=stop`). The resolved config is written to `<out_dir>/config.yaml` (`save_job_config`), the
    records' manifest names `written_by`. Where the records carry human labels the scores can be computed from
    (`nsfp_av2_check.scorable`), the pseudo-labels' scores against them and zero flow's are added (`scores`) and
    written to `<out_dir>/pseudo_label_scores.json`."""
    job = job_from_config(cfg)
    manifest = pair_records.manifest_of_files(list(files))
    if job.ground == "records" and not {"is_ground_t0", "is_ground_tm1"} <= set(manifest.extras):
        ground_masks({}, "records")  # raises, naming what is missing: before any work
    out_manifest = output_manifest(manifest, written_by)
    pair_records.write_manifest(out_dir, out_manifest)  # before any work: a directory of other records fails here
    save_job_config(out_dir, cfg)  # ... and one of another job's pseudo-labels here
    counts = enrich_records.run_job(list(files), out_dir, out_manifest, functools.partial(
        pseudo_label_file, out_dir=out_dir, job=job, manifest=manifest, out_manifest=out_manifest,
        skip_bad_records=skip_bad_records), "pseudo_label", beam_args)
    if not nsfp_av2_check.scorable(out_manifest):
        out_files = [os.path.join(out_dir, os.path.basename(f)) for f in files]
        counts["scores"] = nsfp_av2_check.score_pseudo_records(out_files, cfg)
        beam_job.write_json({**counts["scores"], "job_options": dataclasses.asdict(job), "written_by": written_by},
                            os.path.join(out_dir, SCORES_NAME))
    return counts
