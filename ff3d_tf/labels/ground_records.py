"""Every sweep's ground mask in pair records: for each record of a directory, `schema.ground_keys(num_frames)`
(`is_ground_t0`, `is_ground_tm1`, `is_ground_tm2`, ...), one boolean per point of each sweep, written as pair records
again beside everything the input held, for `data.drop_ground` (every sweep's ground left out of the model's input, as
DeltaFlow's authors do).

Per sweep (cloud) of a record (`ground_of_record`): the record's own mask where the input's manifest lists that key
among its extras (Argoverse 2 records: the map raster's, kept bit for bit), else the local height rule of
`ff3d_tf.labels.ground.height_ground_mask` on that sweep's points alone. Every sweep of a record is in the t0 vehicle
frame; the rule is local per column of the x-y plane (a low percentile of z, interpolated between columns), so it
needs no sweep's own frame. An empty sweep gets an empty mask. A sweep with non-finite coordinates stops its file,
naming file, record and field.

Which keys are added: those of `ground_keys` the input's manifest does not list (`missing_ground_keys`); the output
manifest lists them all (`output_manifest`). Records that already hold some sweeps' masks (Argoverse 2 records of
more sweeps written before every sweep got the raster's mask) keep those and get the rule for the others: two rules
in one record, said once in the log. Records that hold every sweep's mask are copied unchanged (the job adds
nothing, says so, and counts `masks_computed` 0), so that the job's output directory holds every mask whatever the
source, and running it on its own output is a copy.

The job is the per-pair shape of `ff3d_tf.labels.enrich_records` (records in, fields added, records out; one Beam
element per records file): each pair's masks are kept as soon as they are computed (`<out>.parts/<index>.npz`) and a
rerun after a kill computes only the pairs not yet done; an output file that exists is skipped; a record that does
not parse stops its file naming file, record and field, or with `skip_bad_records` is left out and counted
(`skipped_records`). The rule is deterministic, so a resumed run writes the same bytes as an uninterrupted one.
"""
from __future__ import annotations

import functools
import logging
import os

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data import pair_records, wod_errors
from ff3d_tf.labels import enrich_records
from ff3d_tf.labels.ground import height_ground_mask

_LOG = logging.getLogger(__name__)
JOB_NAME = "ground_masks"
_LOG_EVERY_PAIRS = 50  # a progress line for a file's first pair and every this many (the rule takes milliseconds a
# pair); Beam's line when the file is done


def missing_ground_keys(manifest: pair_records.Manifest) -> tuple[str, ...]:
    """The ground keys of the records' sweeps (`schema.ground_keys`, slot order) that their manifest does not list:
    the fields the job adds."""
    return tuple(k for k in schema.ground_keys(manifest.num_frames) if k not in manifest.extras)


def output_manifest(manifest: pair_records.Manifest, written_by: str = "") -> pair_records.Manifest:
    """The input's manifest with every sweep's ground key among its extras (the added ones after those it held)."""
    return enrich_records.output_manifest(manifest, missing_ground_keys(manifest), written_by)


def sweep_ground_mask(points_xyz) -> np.ndarray:
    """[N] bool: the height rule's ground of one sweep's points (t0 vehicle frame, m); [0] for an empty sweep."""
    points = np.asarray(points_xyz)
    if len(points) == 0:
        return np.zeros(0, bool)
    return np.asarray(height_ground_mask(points), bool)


def ground_of_record(ex: dict, fields: tuple[str, ...], path: str = "<record>", index: int = -1) -> dict:
    """{key: [N_k] bool} the height rule's mask of each sweep whose ground key is in `fields` (the keys the job adds),
    from the sweep's points in `ex` (a record's fields as NumPy). A sweep with non-finite coordinates raises a
    FrameDecodeError naming `path`, record `index` and the points' field."""
    out = {}
    for key in fields:
        xyz_key = schema.cloud_keys(schema.POINT_KEYS[key].cloud)["xyz"]
        try:
            out[key] = sweep_ground_mask(ex[xyz_key])
        except ValueError as err:
            raise wod_errors.FrameDecodeError(path, index, xyz_key, f"{err} (no ground mask for {key})") from None
    return out


def ground_file(in_path: str, out_dir: str, manifest: pair_records.Manifest, out_manifest: pair_records.Manifest,
                skip_bad_records: bool = False) -> dict:
    """Every sweep's ground mask of one records file into `out_dir` (same file name), resumable per pair
    (`enrich_records.enrich_pairs`). Returns counts: `pairs` written, `masks_kept` (sweeps whose mask the records
    held), `masks_computed` (sweeps whose mask is the height rule's, by this run or by a stopped one whose parts it
    kept), `points_computed` and `ground_points_computed` (their points, and those of them that are ground),
    `skipped_records`, `seconds`; or {"already_done": 1}."""
    fields = missing_ground_keys(manifest)
    kept = tuple(k for k in schema.ground_keys(manifest.num_frames) if k not in fields)
    counts = {"pairs": 0, "masks_kept": 0, "masks_computed": 0, "points_computed": 0, "ground_points_computed": 0,
              "skipped_records": 0}
    name = os.path.basename(in_path)

    def compute(index, ex, where):
        return ground_of_record(ex, fields, in_path, index)

    def on_pair(index, ex, part, fresh, progress_line):
        counts["pairs"] += 1
        counts["masks_kept"] += len(kept)
        counts["masks_computed"] += len(fields)
        counts["points_computed"] += sum(len(part[k]) for k in fields)
        counts["ground_points_computed"] += sum(int(np.count_nonzero(part[k])) for k in fields)
        if counts["pairs"] == 1 or counts["pairs"] % _LOG_EVERY_PAIRS == 0:
            _LOG.info("%s pair %d%s; %s", name, index, "" if fresh else " (kept from an earlier run)", progress_line)

    return enrich_records.enrich_pairs(in_path, out_dir, enrich_records.PairJob(fields, compute, on_pair),
                                       manifest, out_manifest, counts, skip_bad_records)


def run_ground_job(files: list[str], out_dir: str, beam_args: list[str] | None = None, written_by: str = "",
                   skip_bad_records: bool = False) -> dict:
    """Every sweep's ground mask of every records file in `files` into `out_dir` (module docstring; a Beam job, one
    element per file, progress per pair and per file; an input that fails the checks fails alone and the job then
    raises `beam_job.DataJobError` naming it). The output manifest (`output_manifest`, naming `written_by`) is
    written before any work. Returns the summed counts, with the keys kept from the records (`ground_keys_kept`) and
    those added by the rule (`ground_keys_added`)."""
    manifest = pair_records.manifest_of_files(list(files))
    added = missing_ground_keys(manifest)
    kept = [k for k in schema.ground_keys(manifest.num_frames) if k not in added]
    if not added:
        _LOG.warning("the records already hold every sweep's ground mask (%s): nothing to add; %s will be a copy of "
                     "them (train on the input directly)", ", ".join(kept), out_dir)
    elif kept:
        _LOG.warning("the records hold %s (kept as they are) but not %s: those get the height rule "
                     "(ff3d_tf.labels.ground), another rule than the records' own", ", ".join(kept), ", ".join(added))
    out_manifest = output_manifest(manifest, written_by)
    process = functools.partial(ground_file, out_dir=out_dir, manifest=manifest, out_manifest=out_manifest,
                                skip_bad_records=skip_bad_records)
    counts = enrich_records.run_job(list(files), out_dir, out_manifest, process, JOB_NAME, beam_args)
    counts["ground_keys_kept"], counts["ground_keys_added"] = kept, list(added)
    return counts
