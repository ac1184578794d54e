"""Pseudo-labels at scale (ZeroFlow's recipe): NSFP flow (`ff3d_tf.labels.nsfp`) of every pair of a directory of pair
records, written as pair records again with `flow_mps_pseudo_t0` and `pseudo_valid_t0` beside whatever the input
held (human labels, ground masks, categories), so that `data.labels=pseudo` trains on them and evaluation still
scores the human labels.

One pair (`fit_pair`, also what `ff3d_tf.labels.nsfp_av2_check` scores): the fit sees the points of both clouds in the
fitted region (`NsfpOptions`' crop: by default the Argoverse 2 challenge's box in x and y and ZeroFlow's z range) that
are not ground, by the same rule for both clouds (`JobOptions.ground`: the records' own masks where they carry one
for each cloud, Argoverse 2's map raster; else the local height rule of `ff3d_tf.labels.ground`). A t0 point the fit
did not see gets no pseudo-label (`pseudo_valid_t0` False, flow 0), never a zero label. A fit whose loss or flow is
not finite, or whose share of fitted points faster than `JobOptions.max_speed_mps` is above
`max_implausible_fraction`, is fitted again with the next seed (`retries` times); if it stays so, the pair is named
in the job's report (`bad_fits`) and written without pseudo-labels, or the job stops (`on_bad_fit="stop"`). Points
faster than `max_speed_mps` in a fit that passes get no pseudo-label either.

Input: records of any source (`tools/write_pair_records.py`, WOD or Argoverse 2, labelled or raw with `--no_labels`).
One Beam element per records file (`ff3d_tf.data.beam_job`). NSFP takes seconds to minutes per pair, so each pair's
flow is kept as soon as it is fitted (`<out>.parts/<index>.npy`, float32, written atomically) and a rerun after a kill
fits only the pairs not yet done; the output file is assembled from the parts and written atomically, then the parts
are removed. The fit is deterministic for a seed, so a resumed run writes the same bytes as an uninterrupted one.
Convention: the project's (`ff3d_tf.schema`): motion of each t0 point from its partner cloud to t0, divided by the
gap, in m/s in the t0 vehicle frame.
"""
from __future__ import annotations

import dataclasses
import functools
import io
import logging
import math
import os
import time

import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.data import beam_job, pair_records, wod_errors
from ff3d_tf.labels import nsfp_av2_check
from ff3d_tf.labels.ground import height_ground_mask
from ff3d_tf.labels.nsfp import MEASURED_FIT_OPTIONS, NsfpOptions, NsfpResult, nsfp_flow

_LOG = logging.getLogger(__name__)
PSEUDO_KEY, PSEUDO_VALID_KEY = schema.PSEUDO_FLOW_KEY, schema.PSEUDO_VALID_KEY
PSEUDO_EXTRAS = (PSEUDO_KEY, PSEUDO_VALID_KEY)
GROUND_RULES = ("auto", "records", "height", "none")  # JobOptions.ground
BAD_FIT_ACTIONS = ("skip", "stop")  # JobOptions.on_bad_fit


class BadFitError(RuntimeError):
    """A pair whose fit stayed implausible with `on_bad_fit="stop"`: names the file, record and why."""


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """The pseudo-label job's options: the fit, and what the job does around it (module docstring)."""
    nsfp: NsfpOptions = MEASURED_FIT_OPTIONS
    ground: str = "auto"  # records: the records' masks of both clouds; height: ff3d_tf.labels.ground; auto: records
    # where they carry both masks, else height; none: no ground removal (besides nsfp.remove_ground_below_z_m)
    max_speed_mps: float = 50.0  # a fitted point faster than this is implausible (no pseudo-label)
    max_implausible_fraction: float = 0.01  # a fit with more implausible fitted points than this share is bad
    retries: int = 1  # fits of a bad pair with the next seeds before it is given up
    on_bad_fit: str = "skip"  # skip: the pair is written without pseudo-labels and named; stop: the job stops

    def __post_init__(self):
        if not isinstance(self.nsfp, NsfpOptions):
            raise ValueError(f"JobOptions.nsfp: an NsfpOptions, got {type(self.nsfp).__name__}")
        if self.ground not in GROUND_RULES:
            raise ValueError(f"JobOptions.ground: one of {', '.join(GROUND_RULES)}, got {self.ground!r}")
        if self.on_bad_fit not in BAD_FIT_ACTIONS:
            raise ValueError(f"JobOptions.on_bad_fit: one of {', '.join(BAD_FIT_ACTIONS)}, got {self.on_bad_fit!r}")
        for name, low in (("max_speed_mps", 0.0), ("max_implausible_fraction", 0.0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value <= low:
                raise ValueError(f"JobOptions.{name}: must be a finite number > {low}, got {value!r}")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or self.retries < 0:
            raise ValueError(f"JobOptions.retries: must be an integer >= 0, got {self.retries!r}")


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
    extras = tuple(k for k in manifest.extras if k not in PSEUDO_EXTRAS) + PSEUDO_EXTRAS
    return dataclasses.replace(manifest, extras=extras, written_by=written_by)


def _records(path: str, manifest: pair_records.Manifest) -> tf.data.TFRecordDataset:
    """The serialized records of one records file."""
    return tf.data.TFRecordDataset(path, compression_type="ZLIB" if manifest.compression == "zlib" else "")


def _raw_examples(path: str, manifest: pair_records.Manifest, skip_bad_records: bool, counts: dict):
    """(record index, every stored field of the record as NumPy) of each record of `path`, in file order. A record
    that does not parse raises a FrameDecodeError naming file, record and field (`ff3d_tf.data.wod_errors`), or with
    `skip_bad_records` is logged, counted (`skipped_records`) and left out; a corrupt TFRecord framing ends the file
    there (nothing after it can be read) in the same two ways."""
    extras = tuple(k for k in manifest.extras if k not in PSEUDO_EXTRAS)
    parse = pair_records.record_parser(manifest, extras)
    iterator, index = iter(_records(path, manifest)), -1
    while True:
        index += 1
        try:
            record = next(iterator)
        except StopIteration:
            return
        except tf.errors.DataLossError:
            error = wod_errors.FrameDecodeError(path, index, "file", "corrupt or truncated TFRecord (records after "
                                                "it cannot be read)")
            if not skip_bad_records:
                raise error from None
            _LOG.warning("skipped the rest of the file: %s", error)
            counts["skipped_records"] += 1
            return
        try:
            example = parse(record, tf.constant(wod_errors.record_source(path, index)))
        except tf.errors.InvalidArgumentError as err:
            tagged = wod_errors.parse_tagged_error(err.message)
            error = tagged.error() if tagged is not None else wod_errors.FrameDecodeError(
                path, index, "record", f"not a pair record ({err.message.splitlines()[0][:200]})")
            if not skip_bad_records:
                raise error from None
            _LOG.warning("skipped: %s", error)
            counts["skipped_records"] += 1
            continue
        yield index, {k: v.numpy() for k, v in example.items()}


def _save_part(path: str, fit: PairFit) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, flow_mps=fit.flow_mps.astype(np.float32), valid=fit.valid, problem=np.array(fit.problem))
    with tf.io.gfile.GFile(path + ".partial", "wb") as f:
        f.write(buffer.getvalue())
    tf.io.gfile.rename(path + ".partial", path, overwrite=True)


def _load_part(path: str, n: int) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(flow, valid, problem) of a pair done before, or None if missing or not of `n` points (then fitted again)."""
    if not tf.io.gfile.exists(path):
        return None
    try:
        with tf.io.gfile.GFile(path, "rb") as f:
            with np.load(io.BytesIO(f.read()), allow_pickle=False) as part:
                flow, valid, problem = part["flow_mps"], part["valid"], str(part["problem"])
    except (ValueError, KeyError, OSError):
        return None
    if flow.shape != (n, 3) or flow.dtype != np.float32 or valid.shape != (n,) or valid.dtype != bool:
        return None
    return flow, valid, problem


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
        return height_ground_mask(ex["points_xyz_t0"]), height_ground_mask(ex["points_xyz_tm1_in_t0"]), "height"
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


def fit_pair(ex: dict, job: JobOptions = JobOptions()) -> PairFit:
    """The pseudo-labels of one record's pair (module docstring): ground by `job.ground` on both clouds, the fit,
    its guard and retries. `ex`: the record's fields as NumPy (`pair_records`)."""
    ground_t0, ground_tm1, rule = ground_masks(ex, job.ground)
    keep_t0, keep_tm1 = (None if g is None else ~g for g in (ground_t0, ground_tm1))
    for attempt in range(job.retries + 1):
        options = dataclasses.replace(job.nsfp, seed=(job.nsfp.seed + attempt) % 2 ** 31)
        result = nsfp_flow(ex["points_xyz_t0"], ex["points_xyz_tm1_in_t0"], pair_records.pair_gap_s(ex), options,
                           keep_t0=keep_t0, keep_tm1=keep_tm1)
        problem = _implausible(result, job)
        if not problem:
            break
    speed = np.linalg.norm(result.flow_mps_t0, axis=1)
    valid = result.valid_t0 & (speed <= job.max_speed_mps) & (not problem)
    flow = np.where(valid[:, None], result.flow_mps_t0, 0.0).astype(np.float32)
    return PairFit(flow, valid, result, rule, attempt + 1, problem)


def _count_records(path: str, manifest: pair_records.Manifest) -> int:
    """Records in the file (for the progress line); the readable ones when its framing is corrupt."""
    count = 0
    try:
        for _ in _records(path, manifest):
            count += 1
    except tf.errors.DataLossError:
        return count  # the framing breaks here: the records before it are those the job reads
    return count


def pseudo_label_file(in_path: str, out_dir: str, job: JobOptions, manifest: pair_records.Manifest,
                      out_manifest: pair_records.Manifest, skip_bad_records: bool = False) -> dict:
    """Pseudo-labels of one records file into `out_dir` (same file name); resumable per pair. Returns counts, with
    the pairs written without pseudo-labels named under `bad_fits`."""
    out_path = os.path.join(out_dir, os.path.basename(in_path))
    if tf.io.gfile.exists(out_path):
        _LOG.info("exists, skipped: %s", out_path)
        return {"already_done": 1}
    parts = out_path + ".parts"
    tf.io.gfile.makedirs(parts)
    counts = {"pairs": 0, "fitted_pairs": 0, "skipped_records": 0, "points_t0": 0, "pseudo_labelled_points": 0,
              "implausible_points": 0, "retried_pairs": 0, "nsfp_iterations": 0, "nsfp_seconds": 0.0,
              "bad_fits": []}
    progress = beam_job.Progress(_count_records(in_path, manifest), "pairs")
    t0 = time.time()

    def records():
        for index, ex in _raw_examples(in_path, manifest, skip_bad_records, counts):
            part = os.path.join(parts, f"{index:06d}.npz")
            done = _load_part(part, len(ex["points_xyz_t0"]))
            where = f"{in_path}: record {index} (t0 {int(ex[pair_records.TIMESTAMP_KEY])} ns)"
            if done is None:
                fit = fit_pair(ex, job)
                if fit.problem and job.on_bad_fit == "stop":
                    raise BadFitError(f"{where}: {fit.problem} after {fit.attempts} fits (on_bad_fit=stop; "
                                      "on_bad_fit=skip writes the pair without pseudo-labels)")
                _save_part(part, fit)
                flow, valid, problem = fit.flow_mps, fit.valid, fit.problem
                r = fit.result
                counts["fitted_pairs"] += 1
                counts["retried_pairs"] += int(fit.attempts > 1)
                counts["implausible_points"] += int((r.valid_t0 & ~valid).sum()) if not problem else 0
                counts["nsfp_iterations"] += r.num_iterations
                counts["nsfp_seconds"] += r.grid_s + r.fit_s
                _LOG.info("%s pair %d: %d iterations, loss %.5f, %.1f s, ground %s, %d of %d points labelled%s; %s",
                          os.path.basename(in_path), index, r.num_iterations, r.loss, r.grid_s + r.fit_s,
                          fit.ground_rule, int(valid.sum()), len(valid), f", NOT LABELLED: {problem}" if problem
                          else "", progress.step())
            else:
                flow, valid, problem = done
                progress.step()
            if problem:
                _LOG.warning("%s: written without pseudo-labels: %s", where, problem)
                counts["bad_fits"].append(f"{where}: {problem}")
            counts["pairs"] += 1
            counts["points_t0"] += len(flow)
            counts["pseudo_labelled_points"] += int(valid.sum())
            ex[PSEUDO_KEY], ex[PSEUDO_VALID_KEY] = flow, valid
            yield pair_records.serialize_pair(ex, out_manifest.precision, out_manifest.extras)

    pair_records.write_records_atomically(out_path, records(), out_manifest.compression)
    tf.io.gfile.rmtree(parts)
    counts["seconds"] = time.time() - t0
    return counts


SCORES_NAME = "pseudo_label_scores.json"


def run_pseudo_label_job(files: list[str], out_dir: str, job: JobOptions, beam_args: list[str] | None = None,
                         written_by: str = "", skip_bad_records: bool = False, cfg=None) -> dict:
    """Pseudo-labels of every records file in `files` into `out_dir` (a Beam job, one element per file; progress
    with rate and ETA per pair and per file; bad records named, or skipped and counted with `skip_bad_records`; bad
    fits named in `bad_fits`, or the job stopped with `job.on_bad_fit="stop"`). Where the records carry human labels
    the scores can be computed from (`nsfp_av2_check.scorable`), the pseudo-labels' scores against them and zero
    flow's are added (`scores`) and written to `<out_dir>/pseudo_label_scores.json`."""
    manifest = pair_records.manifest_of_files(list(files))
    if job.ground == "records" and not {"is_ground_t0", "is_ground_tm1"} <= set(manifest.extras):
        ground_masks({}, "records")  # raises, naming what is missing: before any work
    out_manifest = output_manifest(manifest, written_by)
    pair_records.write_manifest(out_dir, out_manifest)  # before any work: a directory of other records fails here
    counts = beam_job.run_per_input(list(files), functools.partial(
        pseudo_label_file, out_dir=out_dir, job=job, manifest=manifest, out_manifest=out_manifest,
        skip_bad_records=skip_bad_records),
        out_dir, "pseudo_label", beam_args)
    if not nsfp_av2_check.scorable(out_manifest):
        from ff3d_tf.config import load_config
        out_files = [os.path.join(out_dir, os.path.basename(f)) for f in files]
        counts["scores"] = nsfp_av2_check.score_pseudo_records(out_files, cfg or load_config(None))
        beam_job.write_json({**counts["scores"], "job_options": dataclasses.asdict(job), "written_by": written_by},
                            os.path.join(out_dir, SCORES_NAME))
    return counts
