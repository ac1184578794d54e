"""Self-supervision's preparation (SeFlow, Zhang et al., ECCV 2024; TeFlow, arXiv 2602.19053): for every log of a
directory of pair records, DUFOMap (Duberg et al., RA-L 2024; the `dufomap` package) over the whole log, then HDBSCAN
clusters of each sweep's dynamic points, written into the records as `schema.DYNAMIC_CLUSTER_KEY_FORMAT` of every
sweep each record holds (-2 ground, -1 static, 0 dynamic in no cluster, k >= 1 dynamic in cluster k of its sweep),
for `train.loss=seflow` / `teflow` with `data.labels=self`. Any source's records: WOD segments, Argoverse 2 logs, a
user's own sequences, the synthetic generators' data (`tools/write_pair_records.py`, labelled or `--no_labels`).

Per log (one records file is one sequence; `prepare_log`), as the authors' KTH-RPL/OpenSceneFlow process.py does
(docs/label_free.md cites the lines; `ff3d_tf.config.SelfSupConfig` holds their values):

1. Its sweeps (`log_sweeps`): every cloud of every record, one sweep per timestamp (t0 and its partner; an older
   cloud is the sweep of the same pose and point count). A sweep's points in its own vehicle frame: the t0 cloud as
   stored, else its cloud moved back by inv(pose_k) pose_t0.
2. Checks, each an error naming the file, record and field (`wod_errors.FrameDecodeError`): at least 2 sweeps,
   every pose rigid (`geometry.pose_problem_np`), consecutive t0 sweeps at most the records' `max_frame_gap_s` apart.
3. Ground of each sweep by `selfsup.ground`: the records' own masks (Argoverse 2's map), or the height rule
   (`ff3d_tf.labels.ground.height_ground_mask`).
4. DUFOMap: every sweep's points between `selfsup.min_range_m` and `max_range_m` from the vehicle origin are cast
   from the sensor (pose @ `selfsup.sensor_origin_m`, poses relative to the log's first sweep), then the map's
   clustering and propagation once, then every point of every sweep is classified; a ground point is never dynamic.
5. HDBSCAN (the `hdbscan` package, as the authors; `cluster_min_points`, `cluster_epsilon_m`) of each sweep's
   dynamic points.

The job is the per-file shape of `ff3d_tf.labels.enrich_records` (records in, fields added, records out): one Beam
element per log, its output written atomically when the whole log is done, an existing output skipped; a bad log
stops the job naming it, or with `skip_bad_records` is left out and named under `bad_logs` (every finished log's
records stay as written). A whole log's records are held in memory while it is prepared.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import os
import time

import numpy as np

from ff3d_tf import geometry, schema
from ff3d_tf.config import ExperimentConfig, SelfSupConfig
from ff3d_tf.data import pair_records, wod_errors
from ff3d_tf.labels import enrich_records
from ff3d_tf.labels.ground import height_ground_mask

_LOG = logging.getLogger(__name__)
JOB_NAME = "self_supervision"
# DUFOMap's clustering of the void map, as the authors set it (process.py: setCluster(depth 0, min_points 20,
# max_dist 0.2 m)).
DUFOMAP_CLUSTER_DEPTH, DUFOMAP_CLUSTER_MIN_POINTS, DUFOMAP_CLUSTER_MAX_DIST_M = 0, 20, 0.2
_PROGRESS_EVERY_SWEEPS = 20


def fields_of(num_frames: int) -> tuple[str, ...]:
    """The fields the job adds to records of `num_frames` sweeps: one per cloud."""
    return tuple(schema.DYNAMIC_CLUSTER_KEY_FORMAT.format(cloud=c) for c in schema.sweep_clouds(num_frames))


@dataclasses.dataclass
class Sweep:
    """One sweep of a log: its points in its own vehicle frame (m), pose (vehicle -> world), ground (None: not
    known from the records), and, once prepared, each point's value of `schema.DYNAMIC_CLUSTER_KEY_FORMAT`."""
    timestamp_ns: int
    points_xyz: np.ndarray
    pose: np.ndarray
    ground: np.ndarray | None = None
    dynamic_cluster: np.ndarray | None = None


def _sweep_key(pose: np.ndarray, count: int) -> tuple:
    return np.asarray(pose, np.float64).tobytes(), int(count)


def _in_own_frame(points_xyz_in_t0: np.ndarray, pose_t0: np.ndarray, pose_k: np.ndarray) -> np.ndarray:
    own_from_t0 = np.linalg.inv(np.asarray(pose_k, np.float64)) @ np.asarray(pose_t0, np.float64)
    return (points_xyz_in_t0.astype(np.float64) @ own_from_t0[:3, :3].T + own_from_t0[:3, 3]).astype(np.float32)


def log_sweeps(path: str, examples: list[tuple[int, dict]], manifest: pair_records.Manifest
               ) -> tuple[list[Sweep], list[list[int]]]:
    """(the log's sweeps in time order, for each record the index of the sweep each of its clouds holds), with the
    checks of the module docstring (step 2)."""
    if not examples:
        raise wod_errors.FrameDecodeError(path, -1, "file", "no records: a log needs at least 2 sweeps")
    by_time: dict[int, Sweep] = {}
    by_key: dict[tuple, int] = {}
    clouds = schema.sweep_clouds(manifest.num_frames)
    previous = None
    for index, ex in examples:
        for cloud in clouds:
            pose_key = schema.cloud_keys(cloud)["pose"]
            problem = geometry.pose_problem_np(ex[pose_key], pose_key)
            if problem:
                raise wod_errors.FrameDecodeError(path, index, pose_key, problem)
        t0_ns = int(ex[pair_records.TIMESTAMP_KEY])
        if previous is not None and not 0 < (t0_ns - previous[1]) * 1e-9 <= manifest.max_frame_gap_s:
            raise wod_errors.FrameDecodeError(path, index, pair_records.TIMESTAMP_KEY, pair_records.missing_sweep(
                t0_ns, previous[1], f"the t0 sweep of record {previous[0]}", manifest.max_frame_gap_s))
        previous = (index, t0_ns)
        ground = ex.get("is_ground_t0")
        by_time.setdefault(t0_ns, Sweep(t0_ns, ex["points_xyz_t0"], ex["pose_t0"], ground))
        if ground is not None and by_time[t0_ns].ground is None:
            by_time[t0_ns].ground = ground
    for index, ex in examples:  # partners that are never a t0 (a log's first or last sweep)
        ts = int(ex[pair_records.PARTNER_TIMESTAMP_KEY])
        if ts not in by_time:
            by_time[ts] = Sweep(ts, _in_own_frame(ex["points_xyz_tm1_in_t0"], ex["pose_t0"], ex["pose_tm1"]),
                                ex["pose_tm1"], ex.get("is_ground_tm1"))
        elif by_time[ts].ground is None and "is_ground_tm1" in ex:
            by_time[ts].ground = ex["is_ground_tm1"]
    sweeps = [by_time[t] for t in sorted(by_time)]
    if len(sweeps) < 2:
        raise wod_errors.FrameDecodeError(path, -1, "file", f"a log of {len(sweeps)} sweep: DUFOMap needs at least "
                                          "2 sweeps of a log")
    for i, sweep in enumerate(sweeps):
        by_key.setdefault(_sweep_key(sweep.pose, len(sweep.points_xyz)), i)
    slots = []
    for index, ex in examples:
        held = []
        for cloud in clouds:
            keys = schema.cloud_keys(cloud)
            found = by_key.get(_sweep_key(ex[keys["pose"]], len(ex[keys["xyz"]])))
            if found is None:
                raise wod_errors.FrameDecodeError(path, index, keys["xyz"], "this cloud is no sweep of the log (no "
                                                  "t0 or partner cloud of its records has its pose and point count)")
            held.append(found)
        slots.append(held)
    return sweeps, slots


def _no_record_ground(where: str) -> str:
    return (f"{where}: selfsup.ground=records, but these records carry no ground mask of every sweep (is_ground_t0 "
            "and is_ground_tm1: Argoverse 2 records do); use selfsup.ground=height or auto")


def ground_of(sweeps: list[Sweep], rule: str, path: str) -> None:
    """Sets every sweep's ground by `rule` (`config.SELFSUP_GROUND_RULES`; "auto": the records' masks where every
    sweep has one)."""
    from_records = all(s.ground is not None for s in sweeps)
    if rule == "records" and not from_records:
        raise ValueError(_no_record_ground(path))
    for sweep in sweeps:
        if rule == "height" or not from_records:
            sweep.ground = height_ground_mask(sweep.points_xyz) if len(sweep.points_xyz) else np.zeros(0, bool)
        sweep.ground = np.asarray(sweep.ground, bool)


def _sensor_poses(sweeps: list[Sweep], origin_m) -> list[np.ndarray]:
    """Each sweep's sensor pose relative to the log's first vehicle pose (smaller coordinates in DUFOMap's float32
    map, as the authors normalise): inv(pose_first) pose_k translate(origin)."""
    first_inv = np.linalg.inv(np.asarray(sweeps[0].pose, np.float64))
    sensor = np.eye(4)
    sensor[:3, 3] = origin_m
    return [first_inv @ np.asarray(s.pose, np.float64) @ sensor for s in sweeps]


def dufomap_dynamic(sweeps: list[Sweep], selfsup: SelfSupConfig, where: str = "") -> list[np.ndarray]:
    """[N_k] bool per sweep: DUFOMap's dynamic points of the whole log (module docstring, step 4)."""
    from dufomap import dufomap  # the `selfsup` extra (setup.py)
    origin = np.asarray(selfsup.sensor_origin_m, np.float64)
    poses = _sensor_poses(sweeps, origin)
    mapper = dufomap(selfsup.dufomap_resolution_m, selfsup.dufomap_hit_inflation_m,
                     selfsup.dufomap_unknown_inflation, num_threads=selfsup.num_threads)
    mapper.setCluster(DUFOMAP_CLUSTER_DEPTH, DUFOMAP_CLUSTER_MIN_POINTS, DUFOMAP_CLUSTER_MAX_DIST_M)
    for i, (sweep, pose) in enumerate(zip(sweeps, poses)):
        distance = np.linalg.norm(sweep.points_xyz, axis=1)
        near = (distance > selfsup.min_range_m) & (distance < selfsup.max_range_m)
        if near.any():
            mapper.run(sweep.points_xyz[near] - origin, pose, cloud_transform=True)
        if (i + 1) % _PROGRESS_EVERY_SWEEPS == 0 or i + 1 == len(sweeps):
            _LOG.info("%s: DUFOMap integrated %d of %d sweeps", where, i + 1, len(sweeps))
    mapper.oncePropagateCluster(if_propagate=True, if_cluster=True)
    return [mapper.segment(s.points_xyz - origin, pose, cloud_transform=True).astype(bool) if len(s.points_xyz)
            else np.zeros(0, bool) for s, pose in zip(sweeps, poses)]


def cluster_ids(points_xyz: np.ndarray, dynamic: np.ndarray, selfsup: SelfSupConfig) -> np.ndarray:
    """[N] int32: 0 for a dynamic point in no cluster (and for every dynamic point of a sweep with fewer than
    `cluster_min_points`), k >= 1 for HDBSCAN's cluster k of the sweep's dynamic points, -1 for the others."""
    # The authors' `hdbscan` package (the `selfsup` extra, setup.py). scikit-learn 1.9.1's HDBSCAN fails in its
    # epsilon search (TypeError in _tree.traverse_upwards) on some sweeps with cluster_selection_epsilon > 0.
    from hdbscan import HDBSCAN
    out = np.full(len(points_xyz), schema.DYNAMIC_CLUSTER_STATIC, np.int32)
    out[dynamic] = schema.DYNAMIC_CLUSTER_NOISE
    if int(dynamic.sum()) >= selfsup.cluster_min_points:
        labels = HDBSCAN(min_cluster_size=selfsup.cluster_min_points,
                         cluster_selection_epsilon=selfsup.cluster_epsilon_m).fit_predict(
                             points_xyz[dynamic].astype(np.float64))
        out[dynamic] = labels + 1  # HDBSCAN's -1 (noise) -> 0
    return out


def prepare_log(path: str, examples: list[tuple[int, dict]], manifest: pair_records.Manifest,
                selfsup: SelfSupConfig, counts: dict) -> list[dict]:
    """The fields (`fields_of`) of every record of one log (module docstring), its counts added to `counts`."""
    sweeps, slots = log_sweeps(path, examples, manifest)
    ground_of(sweeps, selfsup.ground, path)
    started = time.time()
    dynamic = dufomap_dynamic(sweeps, selfsup, os.path.basename(path))
    counts["dufomap_seconds"] += time.time() - started
    started = time.time()
    for sweep, moving in zip(sweeps, dynamic):
        moving &= ~sweep.ground
        sweep.dynamic_cluster = cluster_ids(sweep.points_xyz, moving, selfsup)
        sweep.dynamic_cluster[sweep.ground] = schema.DYNAMIC_CLUSTER_GROUND
        counts["points"] += len(moving)
        counts["dynamic_points"] += int(moving.sum())
        counts["clusters"] += int(sweep.dynamic_cluster.max(initial=0))
    counts["cluster_seconds"] += time.time() - started
    counts["sweeps"] += len(sweeps)
    counts["records"] += len(examples)
    if not any(s.dynamic_cluster.max(initial=0) > 0 for s in sweeps):
        _LOG.warning("%s: no cluster of dynamic points in any sweep (a log without movers trains the Chamfer and "
                     "static terms only)", path)
        counts["logs_without_clusters"].append(path)
    fields = fields_of(manifest.num_frames)
    return [{key: sweeps[s].dynamic_cluster for key, s in zip(fields, held)} for held in slots]


def prepare_file(in_path: str, out_dir: str, manifest: pair_records.Manifest, out_manifest: pair_records.Manifest,
                 selfsup: SelfSupConfig, skip_bad_records: bool = False) -> dict:
    """One log's records file into `out_dir` (`enrich_records.enrich_whole_file`); a bad log raises, or with
    `skip_bad_records` is left out and named under `bad_logs`."""
    counts = {"logs": 1, "records": 0, "sweeps": 0, "points": 0, "dynamic_points": 0, "clusters": 0,
              "skipped_records": 0, "dufomap_seconds": 0.0, "cluster_seconds": 0.0, "bad_logs": [],
              "logs_without_clusters": []}
    started = time.time()
    try:
        result = enrich_records.enrich_whole_file(
            in_path, out_dir, fields_of(manifest.num_frames),
            lambda path, examples: prepare_log(path, examples, manifest, selfsup, counts), manifest, out_manifest,
            counts, skip_bad_records)
    except wod_errors.FrameDecodeError as err:
        if not skip_bad_records:
            raise
        _LOG.warning("log left out: %s", err)
        return {"logs": 0, "bad_logs": [str(err)]}
    if "already_done" not in result:
        result["seconds"] = time.time() - started
        _LOG.info("%s: %d sweeps, %d records, %d dynamic points in %d clusters, %.1f s", os.path.basename(in_path),
                  counts["sweeps"], counts["records"], counts["dynamic_points"], counts["clusters"],
                  result["seconds"])
    return result


def run_preparation_job(files: list[str], out_dir: str, cfg: ExperimentConfig, beam_args: list[str] | None = None,
                        written_by: str = "", skip_bad_records: bool = False) -> dict:
    """The fields of every log of `files` (pair records) into `out_dir` by `cfg.selfsup` (a Beam job, one element per
    log; the resolved config written to `<out_dir>/config.yaml`). Returns the summed counts."""
    manifest = pair_records.manifest_of_files(list(files))
    if cfg.selfsup.ground == "records" and not {"is_ground_t0", "is_ground_tm1"} <= set(manifest.extras):
        raise ValueError(_no_record_ground(os.path.dirname(files[0])))  # before any work
    out_manifest = enrich_records.output_manifest(manifest, fields_of(manifest.num_frames), written_by)
    pair_records.write_manifest(out_dir, out_manifest)
    cfg.save(os.path.join(out_dir, "config.yaml"))
    process = functools.partial(prepare_file, out_dir=out_dir, manifest=manifest, out_manifest=out_manifest,
                                selfsup=cfg.selfsup, skip_bad_records=skip_bad_records)
    return enrich_records.run_job(list(files), out_dir, out_manifest, process, JOB_NAME, beam_args)
