"""NSFP (`ff3d_tf.labels.nsfp`) at traffic speeds: its end-point error on synthetic pairs whose moving vehicles drive
at a chosen speed band, per candidate fit, and on the real Argoverse 2 sample pair (lab/tools/benchmark_nsfp_speed.py,
docs/label_free.md "NSFP at highway speeds").

The pairs (`speed_pair`): the street world of `ff3d_tf.data.synthetic.scene` (`make_scene`: curved road, four traffic
lanes, parked vehicles, cyclists, pedestrians, poles, signs, buildings; flat ground), seen by the synthetic
Argoverse 2 generator's two stacked 32-beam lidars (`ff3d_tf.data.synthetic.av2.LIDARS`) at t-1 and t0, 0.1 s
apart, every point where its surface was when the ray reached it, in the vehicle frame of its sweep's time
(Argoverse 2 sweeps are ego-motion compensated; `SENSORS`: "timed" fires each ray at its own time, so a moving
object is smeared by its motion over the sweep, "ideal" casts the whole sweep at one instant). The
generators draw lane speeds from 2-10 m/s; here every traffic lane's speed (the ego's lane and so the ego's speed
too) is drawn uniformly from the pair's band instead, by a stream of its own, so the pairs of one seed share the
road, the objects and their placement along it and differ in the lane speeds only. Cyclists and pedestrians keep the
world's speeds (at most 6 m/s). The truth is the simulator's rigid motion of each surface hit (t-1 -> t0, t0 vehicle
frame, metres); ground points are flagged (the truth, as a map's ground mask) and left out of the fit and the score,
as the pseudo-label job does with Argoverse 2's map.

The scores (`score`): the Argoverse 2 challenge's arithmetic (`ff3d_tf.metrics_av2`: three-way EPE over the points
of the 35 m box; vehicles are REGULAR_VEHICLE, cyclists BICYCLIST, pedestrians PEDESTRIAN, signs SIGN, the rest
background) plus the error of the band's own objects: `moving_vehicle_epe_m`, the mean EPE of the points on moving
traffic-lane vehicles (the objects whose speed the band sets), with their mean true speed. A point without a fitted
flow (outside the fitted region) is scored as zero flow.

The benchmark (`run`): the candidate fits (changes to the pseudo-label job's fit, `nsfp.MEASURED_FIT_OPTIONS`) on
the tuning seeds' pairs of each band, the chosen ones on the held-out seeds' pairs and on the real pair (`fit_real`:
the job's own `pseudo_records.fit_pair`), and per pair the objective along the true motion (`chamfer_profile`):
where NSFP's Chamfer is lowest when the band's vehicles are moved by a multiple of their truth.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Callable, Sequence

import numpy as np

from ff3d_tf import cpu, geometry, metrics_av2
from ff3d_tf.data.synthetic import av2 as synthetic_av2
from ff3d_tf.data.synthetic import av2_sweeps
from ff3d_tf.data.synthetic import realism as realism_lib
from ff3d_tf.data.synthetic import scene as sim
from ff3d_tf.labels import nsfp
from lab import bench

DT_S = sim.DT_S  # 0.1 s between the pair's sweeps
TRAFFIC_LANES = (-1.75, -5.25, 1.75, 5.25)  # `scene.make_scene`'s traffic lanes (lateral offset, m); -1.75: the ego's
BANDS_MPS = {"0-5": (0.5, 5.0), "5-10": (5.0, 10.0), "10-20": (10.0, 20.0)}  # lane speeds, uniform in [lo, hi)
DEFAULT_POINTS = 32768  # points per sweep (the real sample pair: ~90K; the job fits every 4th)
# The lidar models (`synthetic.realism`): "ideal" every ray at the sweep time, exact; "timed" the realistic profile's
# sensor (each ray at its own firing time, the down lidar half a turn after the up one; range noise, dropped returns).
SENSORS = {"ideal": realism_lib.IDEAL, "timed": realism_lib.REALISTIC}
DEFAULT_SENSOR = "timed"
_LABEL = {1: metrics_av2.LABEL_NAMES.index("REGULAR_VEHICLE"), 2: metrics_av2.LABEL_NAMES.index("PEDESTRIAN"),
          3: metrics_av2.LABEL_NAMES.index("SIGN"), 4: metrics_av2.LABEL_NAMES.index("BICYCLIST")}


@dataclasses.dataclass(frozen=True)
class SpeedPair:
    points_xyz_t0: np.ndarray  # [N,3] float32, t0 vehicle frame
    points_xyz_tm1_in_t0: np.ndarray  # [M,3] float32, the t-1 sweep in the t0 vehicle frame (ego motion removed)
    motion_m: np.ndarray  # [N,3] float32 true motion t-1 -> t0 of each t0 point (t0 frame, ego motion removed)
    label_t0: np.ndarray  # [N] int64 challenge label index (metrics_av2), 0 background
    ground_t0: np.ndarray  # [N] bool
    ground_tm1: np.ndarray  # [M] bool
    band_vehicle_t0: np.ndarray  # [N] bool: on a traffic-lane vehicle (the band's objects)
    lane_speeds_mps: dict  # lateral offset -> speed (m/s); the ego drives lane -1.75
    t0_s: float


def _band_stream(seed: int, band: tuple[float, float]) -> np.random.Generator:
    return np.random.default_rng([int(seed), 7919, int(round(band[0] * 100)), int(round(band[1] * 100))])


def _sensor(name: str) -> realism_lib.Realism:
    """The lidar model of `SENSORS[name]` on the street world (`Realism.city` off)."""
    if name not in SENSORS:
        raise ValueError(f"unknown sensor {name!r}; the sensors are {sorted(SENSORS)}")
    return dataclasses.replace(SENSORS[name], city=False)


def _rotation_z(heading: np.ndarray) -> np.ndarray:
    c, s = np.cos(heading), np.sin(heading)
    out = np.zeros(np.shape(heading) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1], out[..., 2, 2] = c, -s, s, c, 1.0
    return out


def _true_motion(road: sim.Road, agent, points_w: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """[K,3] world motion over the DT_S before each point's time of the rigid agent surface point `points_w` [K,3]
    seen at `times_s` [K]."""
    centre_0, heading_0 = agent.poses(road, times_s)
    centre_1, heading_1 = agent.poses(road, times_s - DT_S)
    local = np.einsum("kji,kj->ki", _rotation_z(heading_0), points_w - centre_0)  # R0^T (p - c0)
    return points_w - (np.einsum("kij,kj->ki", _rotation_z(heading_1), local) + centre_1)


def speed_pair(seed: int, band_mps: tuple[float, float], points: int = DEFAULT_POINTS,
               sensor: str = DEFAULT_SENSOR) -> SpeedPair:
    """The synthetic pair of `seed` with every traffic lane at a speed drawn from `band_mps` (module docstring), seen
    by `sensor` (`SENSORS`); each sweep `points` points (drawn from all the returns), deterministic for (seed, band,
    points, sensor)."""
    lo, hi = band_mps
    if not 0 <= lo < hi:
        raise ValueError(f"band_mps must be (lo, hi) with 0 <= lo < hi, got {band_mps!r}")
    profile = _sensor(sensor)
    rng = np.random.default_rng(seed)
    road, agents = sim.make_scene(rng, 0.0)  # the ego lane's speed is set below (make_scene draws none for it)
    stream = _band_stream(seed, band_mps)
    lane_speeds = {d: float(stream.uniform(lo, hi)) for d in TRAFFIC_LANES}
    in_lane = [a.class_id == 1 and a.d in lane_speeds for a in agents]
    agents = [dataclasses.replace(a, speed=(1.0 if a.d < 0 else -1.0) * lane_speeds[a.d]) if lane else a
              for a, lane in zip(agents, in_lane)]
    band_ids = {a.track_id for a, lane in zip(agents, in_lane) if lane}
    ego_speed = lane_speeds[TRAFFIC_LANES[0]]
    t0 = float(np.random.default_rng([int(seed), 104729]).uniform(0.0, 10.0))

    def world_from_ego_at(times):
        m = sim.ego_poses(road, times, ego_speed)
        m[:, 2, 3] += synthetic_av2.EGO_ORIGIN_HEIGHT_M
        return m

    width = max(64, int(np.ceil(points / (2 * len(synthetic_av2.BEAM_INCLINATIONS_RAD) * 0.5))))
    sweeps = []
    for t in (t0 - DT_S, t0):
        scene = sim.frame_scene(0, t, road, agents, ego_speed, world_from_ego_at([t])[0])
        w = width
        for _ in range(4):  # widen the scan until it has enough returns
            points_w, hits, _, offset_ns = av2_sweeps.scan_sweep(
                synthetic_av2.LIDARS, synthetic_av2.BEAM_INCLINATIONS_RAD, w, scene, world_from_ego_at, road, rng,
                profile, synthetic_av2.SWEEP_PERIOD_NS, synthetic_av2.LIDAR_MAX_RANGE_M, synthetic_av2.MIN_RANGE_M)
            if len(points_w) >= points:
                break
            w = int(np.ceil(w * 1.2 * points / max(len(points_w), 1)))
        keep = np.sort(rng.choice(len(points_w), min(points, len(points_w)), replace=False))
        times = t + offset_ns[keep] * 1e-9 if profile.motion_distortion else np.full(len(keep), t)
        sweeps.append((scene, points_w[keep], hits[keep], times))
    (_, world_tm1, hits_tm1, _), (scene_t0, world_t0, hits_t0, times_t0) = sweeps
    t0_from_world = np.linalg.inv(world_from_ego_at([t0])[0])
    motion_w = np.zeros_like(world_t0)
    label = np.zeros(len(world_t0), np.int64)
    band_vehicle = np.zeros(len(world_t0), bool)
    for j, a in enumerate(scene_t0.near):
        sel = hits_t0 == j
        if not sel.any():
            continue
        if a.class_id > 0 and a.labelled:
            label[sel] = _LABEL[a.class_id]
        band_vehicle[sel] = a.track_id in band_ids
        if a.moves():
            motion_w[sel] = _true_motion(road, a, world_t0[sel], times_t0[sel])
    return SpeedPair(geometry.transform_points_np(world_t0, t0_from_world).astype(np.float32),
                     geometry.transform_points_np(world_tm1, t0_from_world).astype(np.float32),
                     (motion_w @ t0_from_world[:3, :3].T).astype(np.float32), label, hits_t0 == -1, hits_tm1 == -1,
                     band_vehicle, lane_speeds, t0)


def score(pair: SpeedPair, motion_pred_m: np.ndarray) -> dict:
    """The challenge's three-way EPE (metres over the pair, the 35 m box, ground left out) and the band's own error
    (module docstring) of a predicted motion [N,3] (m, t-1 -> t0, t0 frame) of the pair's t0 points."""
    mask = metrics_av2.eval_mask(pair.points_xyz_t0, pair.ground_t0)
    acc = metrics_av2.AV2FlowAccumulator()
    acc.update(pair.motion_m.astype(np.float64), np.asarray(motion_pred_m, np.float64), pair.label_t0, mask)
    result = acc.result()
    speed = np.linalg.norm(pair.motion_m, axis=1) / DT_S
    error = np.linalg.norm(np.asarray(motion_pred_m, np.float64) - pair.motion_m, axis=1)
    band = mask & pair.band_vehicle_t0 & (speed * DT_S >= metrics_av2.DYNAMIC_THRESHOLD_M)
    out = {k: result[f"three_way/{k}"] for k in ("mean_epe_m", "fg_dynamic_epe_m", "fg_static_epe_m",
                                                 "bg_static_epe_m", "fg_dynamic_count")}
    out["moving_vehicle_epe_m"] = float(error[band].mean()) if band.any() else float("nan")
    out["moving_vehicle_points"] = int(band.sum())
    out["moving_vehicle_mean_speed_mps"] = float(speed[band].mean()) if band.any() else float("nan")
    out["moving_vehicle_zero_flow_epe_m"] = float(np.linalg.norm(pair.motion_m[band], axis=1).mean()) \
        if band.any() else float("nan")
    return out


# --- the objective along the truth --------------------------------------------------------------------------------

PROFILE_SCALES = tuple(round(0.05 * k, 2) for k in range(27))  # 0, 0.05, ..., 1.3 times the true motion
PROFILE_REACH_M = 3.0  # the reverse term's t-1 points: those this close to a t0 point of a band vehicle


def _nearest_distance(points: np.ndarray, cloud: np.ndarray, chunk: int = 256) -> np.ndarray:
    """[K] distance of each of `points` [K,3] to its nearest point of `cloud` [M,3] (brute force, in chunks)."""
    out = np.empty(len(points))
    for begin in range(0, len(points), chunk):
        d2 = ((points[begin: begin + chunk, None, :] - cloud[None, :, :]) ** 2).sum(-1)
        out[begin: begin + chunk] = np.sqrt(d2.min(axis=1))
    return out


def chamfer_profile(pair: SpeedPair, scales: Sequence[float] = PROFILE_SCALES) -> dict:
    """NSFP's two-sided mean squared Chamfer (m^2; ground left out of both clouds) of the pair when the band's
    vehicles are moved back by `scale` times their true motion and every other point by its truth: the forward term
    over the vehicles' t0 points (to the t-1 cloud), the reverse term over the t-1 points within PROFILE_REACH_M of
    them (to the moved t0 cloud). {"scales", "chamfer_m2", "argmin_scale", "at_truth_over_at_zero"}: where along
    the true motion the objective is lowest."""
    keep = ~pair.ground_t0
    xyz, motion, vehicle = pair.points_xyz_t0[keep], pair.motion_m[keep], pair.band_vehicle_t0[keep]
    tm1 = pair.points_xyz_tm1_in_t0[~pair.ground_tm1]
    near = _nearest_distance(tm1, xyz[vehicle]) < PROFILE_REACH_M
    values = []
    for scale in scales:
        moved = xyz - np.where(vehicle[:, None], scale * motion, motion)
        values.append(float(np.mean(_nearest_distance(moved[vehicle], tm1) ** 2) +
                            np.mean(_nearest_distance(tm1[near], moved) ** 2)))
    scales = [float(s) for s in scales]
    return {"scales": scales, "chamfer_m2": values, "argmin_scale": scales[int(np.argmin(values))],
            "at_truth_over_at_zero": values[scales.index(1.0)] / values[0] if 1.0 in scales and 0.0 in scales
            else float("nan")}


# --- the candidate fits ----------------------------------------------------------------------------------------------

def candidate_options(changes: dict, base: nsfp.NsfpOptions = nsfp.MEASURED_FIT_OPTIONS) -> nsfp.NsfpOptions:
    """`base` (the pseudo-label job's fit) with the fields `changes` names set; lists become tuples (JSON)."""
    return dataclasses.replace(base, **{k: tuple(v) if isinstance(v, list) else v for k, v in changes.items()})


def fit_synthetic(pair: SpeedPair, options: nsfp.NsfpOptions) -> dict:
    """One fit of a synthetic pair (ground left out of both clouds, as the job does with a map's ground): its
    scores (`score`), Adam steps and seconds."""
    result = nsfp.nsfp_flow(pair.points_xyz_t0, pair.points_xyz_tm1_in_t0, DT_S, options, keep_t0=~pair.ground_t0,
                            keep_tm1=~pair.ground_tm1)
    return {**score(pair, result.flow_mps_t0 * np.float32(DT_S)), "iterations": result.num_iterations,
            "fit_s": result.fit_s, "grid_s": result.grid_s}


def fit_real(log_dir: str, options: nsfp.NsfpOptions, index: int = 0) -> dict:
    """The pseudo-label job's fit (`pseudo_records.fit_pair`, its ground rule, guard and retries) with `options` on
    the real Argoverse 2 pair `index` of the log at `log_dir`, scored by the challenge's arithmetic as the job scores
    itself (`nsfp_av2_check`: the 35 m box, ground left out, a point without a pseudo-label as zero flow)."""
    from ff3d_tf.config import ExperimentConfig
    from ff3d_tf.data import pair_records
    from ff3d_tf.labels import av2 as av2_labels
    from ff3d_tf.labels import pseudo_records
    ex = av2_labels.challenge_pair(log_dir, index, ExperimentConfig())
    fit = pseudo_records.fit_pair(ex, pseudo_records.JobOptions(nsfp=options))
    gap_s = pair_records.pair_gap_s(ex)
    mask = metrics_av2.eval_mask(ex["points_xyz_t0"], ex["is_ground_t0"])
    acc = metrics_av2.AV2FlowAccumulator()
    acc.update(-ex["flow_mps_t0"].astype(np.float64) * gap_s, -fit.flow_mps.astype(np.float64) * gap_s,
               ex["category_t0"], mask)
    result = acc.result()
    return {"mean_epe_m": result["three_way/mean_epe_m"], "fg_dynamic_epe_m": result["three_way/fg_dynamic_epe_m"],
            "fg_static_epe_m": result["three_way/fg_static_epe_m"],
            "bg_static_epe_m": result["three_way/bg_static_epe_m"],
            "bucketed_mean_dynamic_norm_epe": result["bucketed/mean_dynamic_norm_epe"],
            "iterations": fit.result.num_iterations, "fit_s": fit.result.fit_s, "grid_s": fit.result.grid_s,
            "attempts": fit.attempts, "problem": fit.problem, "evaluated_points": int(mask.sum())}


# --- the benchmark ---------------------------------------------------------------------------------------------------

def _mean(values) -> float:
    values = [v for v in values if v == v]
    return float(np.mean(values)) if values else float("nan")


SUMMARY_FIELDS = ("moving_vehicle_epe_m", "fg_dynamic_epe_m", "fg_static_epe_m", "bg_static_epe_m", "mean_epe_m",
                  "iterations", "fit_s")


def summarize(fits: dict, candidate: str, bands: Sequence[str], seeds: Sequence[int]) -> dict:
    """Per band the mean over `seeds` of each `SUMMARY_FIELDS` entry of the candidate's fits (those done), the seeds
    they are over, and `fast_over_slow`: the moving-vehicle error of the last band over the first's."""
    out = {}
    for band in bands:
        done = [fits[f"{candidate}/{band}/{seed}"] for seed in seeds if f"{candidate}/{band}/{seed}" in fits]
        out[band] = {"seeds": [s for s in seeds if f"{candidate}/{band}/{s}" in fits],
                     **{k: _mean([d[k] for d in done]) for k in SUMMARY_FIELDS}}
    first, last = out[bands[0]]["moving_vehicle_epe_m"], out[bands[-1]]["moving_vehicle_epe_m"]
    out["fast_over_slow"] = last / first if first == first and first > 0 else float("nan")
    return out


def run(out: str, candidates: dict, tune_seeds: Sequence[int], held_out_seeds: Sequence[int],
        held_out_candidates: Sequence[str], bands: Sequence[str], points: int, sensor: str, real_log: str | None,
        real_candidates: Sequence[str], log: Callable[[str], None] = print) -> dict:
    """The benchmark, resumable: every fit of `candidates` ({name: NsfpOptions changes}) on the `tune_seeds` pairs of
    each band, of `held_out_candidates` on the `held_out_seeds` pairs, and of `real_candidates` on the real pair of
    `real_log` (skipped when None), each written to `out` as it completes; a rerun fits only what the file lacks (a
    candidate whose options changed is fitted again)."""
    result = {}
    if os.path.exists(out):
        with open(out) as f:
            result = json.load(f)
    options = {name: candidate_options(changes) for name, changes in candidates.items()}
    old = result.get("candidates", {})
    stale = {name for name in candidates if name in old and old[name]["options"] != _jsonable(options[name])}
    if {k: result.get("pairs", {}).get(k) for k in ("points_per_sweep", "sensor")} != \
            {"points_per_sweep": points, "sensor": sensor}:  # other pairs: every synthetic figure is redone
        stale |= set(candidates) | set(old)
        result.pop("chamfer_profile", None)
        real_kept = result.get("real_pair", {})
    else:
        real_kept = None
    result["machine"] = {**cpu.describe(), "load_average_at_start": bench.load_average()}  # of this (re)run
    result.setdefault("load_average_at_each_run", []).append(bench.load_average())
    result["pairs"] = {"generator": "lab.labels.nsfp_speed.speed_pair", "points_per_sweep": points,
                       "sensor": sensor, "bands_mps": {b: list(BANDS_MPS[b]) for b in bands},
                       "tune_seeds": list(tune_seeds), "held_out_seeds": list(held_out_seeds)}
    result["candidates"] = {name: {"changes": candidates[name], "options": _jsonable(options[name])}
                            for name in candidates}
    fits = {k: v for k, v in result.get("fits", {}).items() if k.split("/")[0] not in stale}
    real = real_kept if real_kept is not None else \
        {k: v for k, v in result.get("real_pair", {}).items() if k not in stale}
    result["fits"], result["real_pair"] = fits, real
    jobs = [(name, band, seed) for seed in tune_seeds for band in bands for name in candidates]
    jobs += [(name, band, seed) for seed in held_out_seeds for band in bands for name in held_out_candidates]
    todo = [job for job in jobs if "/".join(map(str, job)) not in fits]
    pairs = {}
    start = time.perf_counter()
    for done, (name, band, seed) in enumerate(todo):
        if (band, seed) not in pairs:
            pairs = {(band, seed): speed_pair(seed, BANDS_MPS[band], points, sensor)}
        fit = fit_synthetic(pairs[(band, seed)], options[name])
        fits[f"{name}/{band}/{seed}"] = fit
        _summaries(result, bands)
        bench.write_json(out, result)
        elapsed = time.perf_counter() - start
        eta_s = elapsed / (done + 1) * (len(todo) - done - 1)
        log(f"[{done + 1}/{len(todo)}] {name} {band} m/s seed {seed}: moving vehicles "
            f"{fit['moving_vehicle_epe_m']:.3f} m (zero flow {fit['moving_vehicle_zero_flow_epe_m']:.3f}), three-way "
            f"{fit['mean_epe_m']:.3f} m, {fit['iterations']} steps, {fit['fit_s']:.0f} s; ETA {eta_s:.0f} s")
    profiles = result.setdefault("chamfer_profile", {})
    for seed in list(tune_seeds) + list(held_out_seeds):
        for band in bands:
            key = f"{band}/{seed}"
            if key not in profiles:
                profiles[key] = chamfer_profile(speed_pair(seed, BANDS_MPS[band], points, sensor))
                bench.write_json(out, result)
                log(f"Chamfer along the truth, {band} m/s seed {seed}: lowest at {profiles[key]['argmin_scale']:.2f} "
                    f"x the true motion")
    if real_log:
        for name in real_candidates:
            if name in real:
                continue
            log(f"real pair {real_log}: {name} ...")
            real[name] = fit_real(real_log, options[name])
            bench.write_json(out, result)
            log(f"real pair: {name}: three-way {real[name]['mean_epe_m']:.3f} m, moving foreground "
                f"{real[name]['fg_dynamic_epe_m']:.3f} m, {real[name]['iterations']} steps, "
                f"{real[name]['fit_s']:.0f} s")
    _summaries(result, bands)
    bench.write_json(out, result)
    return result


def _summaries(result: dict, bands: Sequence[str]) -> None:
    fits, pairs = result["fits"], result["pairs"]
    result["tune"] = {name: summarize(fits, name, bands, pairs["tune_seeds"]) for name in result["candidates"]}
    result["held_out"] = {name: summarize(fits, name, bands, pairs["held_out_seeds"]) for name in result["candidates"]
                          if any(k.startswith(name + "/") and int(k.split("/")[2]) in pairs["held_out_seeds"]
                                 for k in fits)}


def _jsonable(options: nsfp.NsfpOptions) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(options)))
