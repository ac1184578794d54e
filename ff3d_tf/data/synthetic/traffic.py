"""Motion that accelerates, brakes, stops and turns, for the city world (`synthetic.city`).

A `Path` is a chain of straight and circular pieces in the road's coordinates (s along the centreline, d to the left;
`scene.Road.pose` maps them into the world), evaluated exactly at any progress u (metres along the path). The paths
that queue are a lane followed at a constant offset that may turn off it by a quarter circle (`lane_path`).

A `Queue` is a line of movers in one direction (a traffic lane, a bike lane, a sidewalk line). `simulate` steps its
movers on a time grid: each follows its free speed profile (cruise, with events: brake to a stop and go again, slow
down; and slower through its turn), and the Intelligent Driver Model's interaction term (Treiber, Hennecke & Helbing,
Phys. Rev. E 62, 2000) brakes it behind the mover ahead and before red stop lines (traffic lights, and a turning
vehicle yielding to the bike lane); a hard clamp after each step keeps every mover behind the one ahead, so boxes of a
queue never overlap. A mover leaves its queue once its turn has taken it out of the line.

A `Track` is the result: progress on the grid, read at any time by linear interpolation, mapped through the path to
the world (heading from the path's tangent, so a stopped mover keeps its heading; height from the ground).
"""
from __future__ import annotations

import dataclasses

import numpy as np

SIM_STEP_S = 0.05
# Intelligent Driver Model, city traffic (Treiber & Kesting, Traffic Flow Dynamics, 2013, the IDM's parameters for
# city traffic): time gap 1.0 s, minimum gap 2 m, acceleration 1.0 m/s^2, comfortable deceleration 1.5 m/s^2.
VEHICLE_IDM = {"time_gap_s": 1.0, "min_gap_m": 2.0, "accel_mps2": 1.0, "decel_mps2": 1.5}
# Pedestrians and cyclists in a line: modelling choices (people keep about a step's distance and react faster).
PEDESTRIAN_IDM = {"time_gap_s": 0.5, "min_gap_m": 0.4, "accel_mps2": 0.8, "decel_mps2": 1.5}
CYCLIST_IDM = {"time_gap_s": 0.8, "min_gap_m": 1.0, "accel_mps2": 1.0, "decel_mps2": 2.0}
MAX_DECEL_MPS2 = 8.0  # emergency braking bound of the step (dry road)
STOP_LINE_DECEL_MPS2 = 4.0  # a mover that cannot stop at a red line within this deceleration drives through
SPEED_TRACKING_PER_S = 2.0  # free-flow controller: the profile's slope + this * (desired - actual) speed, bounded
CLAMP_GAP_M = 0.3  # the least bumper gap the clamp keeps
STANDSTILL_MPS = 0.05  # a braking mover slower than this stops (the controller and IDM only approach zero)


class Path:
    """Straight and circular pieces chained from (s0, d0) heading h0 (radians in the (s, d) plane, 0 = +s, pi/2 = +d).

    `pieces`: [(length_m, curvature_per_m)]; the last piece goes on for ever and the first extends backwards (u < 0),
    so it must be straight."""

    def __init__(self, s0: float, d0: float, h0: float, pieces):
        if not pieces or pieces[0][1] != 0.0:
            raise ValueError("Path: the first piece extends backwards and must be straight")
        starts = [(0.0, s0, d0, h0)]
        for length, curvature in pieces[:-1]:
            u, s, d, h = starts[-1]
            ns, nd, nh = self._advance(s, d, h, curvature, length)
            starts.append((u + length, float(ns), float(nd), float(nh)))
        self.u_start, self.s, self.d, self.h = np.array(starts, np.float64).T
        self.k = np.array([curvature for _, curvature in pieces], np.float64)

    @staticmethod
    def _advance(s, d, h, k, length):
        s, d, h, k, length = (np.asarray(v, np.float64) for v in (s, d, h, k, length))
        straight = k == 0.0
        ks = np.where(straight, 1.0, k)
        s_arc = s + (np.sin(h + ks * length) - np.sin(h)) / ks
        d_arc = d - (np.cos(h + ks * length) - np.cos(h)) / ks
        return (np.where(straight, s + length * np.cos(h), s_arc), np.where(straight, d + length * np.sin(h), d_arc),
                h + k * length)

    def at(self, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, d, heading in the (s, d) plane) at progress u (any shape)."""
        u = np.asarray(u, np.float64)
        i = np.clip(np.searchsorted(self.u_start, u, "right") - 1, 0, len(self.u_start) - 1)
        return self._advance(self.s[i], self.d[i], self.h[i], self.k[i], u - self.u_start[i])


@dataclasses.dataclass(frozen=True)
class LaneGeometry:
    """A queue path's shape: the lane at offset d, direction +1 (+s) or -1, turning right or left (turn_sign -1 /
    +1 relative to its heading) by a quarter circle of radius turn_radius_m from s = turn_s (no turn: turn_s None)."""

    d: float
    direction: int
    turn_s: float | None = None
    turn_radius_m: float = 0.0
    turn_sign: int = -1


def lane_path(start_s: float, lane: LaneGeometry) -> Path:
    """The path of a mover starting at road coordinate `start_s` on `lane` (u = 0 there)."""
    h0 = 0.0 if lane.direction > 0 else np.pi
    if lane.turn_s is None:
        return Path(start_s, lane.d, h0, [(1.0, 0.0)])
    straight = (lane.turn_s - start_s) * lane.direction
    k = lane.turn_sign / lane.turn_radius_m
    return Path(start_s, lane.d, h0, [(straight, 0.0), (np.pi / 2 * lane.turn_radius_m, k), (1.0, 0.0)])


@dataclasses.dataclass
class Mover:
    """One member of a queue: its path, size along the queue, start state and free speed profile on the grid."""

    lane: LaneGeometry
    start_s: float  # road s at the grid's first time (u = 0)
    length_m: float
    width_m: float
    speed0_mps: float
    free_speed_mps: np.ndarray  # [T] desired speed on the grid
    turn_speed_mps: float = np.inf  # speed through the turn (and the braking curve before it)
    yields: bool = False  # obeys the queue's yield lines (a turning vehicle crossing the bike lane)
    # Whether the turn takes it out of the queue (a vehicle turning off its lane); False: every member of the queue
    # turns there (pedestrians turning into a side street's sidewalk), so the queue goes on along the path.
    exits_line: bool = True

    def path(self) -> Path:
        return lane_path(self.start_s, self.lane)

    def turn_u(self) -> float:
        return np.inf if self.lane.turn_s is None else (self.lane.turn_s - self.start_s) * self.lane.direction

    def exit_angle(self) -> float:
        """Turn angle from which the mover has left its line: its near side clears the line's half width."""
        if self.lane.turn_s is None or not self.exits_line:
            return np.inf
        clear = (self.width_m + self.length_m) / 2 + 0.5
        return float(np.arccos(np.clip(1.0 - clear / self.lane.turn_radius_m, -1.0, 1.0)))


@dataclasses.dataclass
class StopLine:
    """A line across the queue at road coordinate s: red where `red` [T] is True, for the movers it applies to
    (traffic lights: all; a yield line: those with `yields`)."""

    s: float
    red: np.ndarray
    yield_line: bool = False


@dataclasses.dataclass
class Queue:
    direction: int
    movers: list  # of Mover, any order (sorted by position at the first time when simulated)
    stop_lines: list  # of StopLine
    idm: dict


@dataclasses.dataclass
class Track:
    """Progress on the grid of one mover along its path; pose at any time (`poses`)."""

    times: np.ndarray  # [T] the grid
    u: np.ndarray  # [T] progress (m)
    path: Path
    z_lift_m: float  # box bottom above the highest ground under its footprint

    def max_speed_mps(self) -> float:
        """The largest progress rate on the grid (m/s)."""
        return float(np.max(np.abs(np.diff(self.u))) / (self.times[1] - self.times[0])) if len(self.u) > 1 else 0.0

    def progress(self, times) -> np.ndarray:
        return np.interp(np.asarray(times, np.float64), self.times, self.u)

    def speed_mps(self, times) -> np.ndarray:
        """Progress rate (m/s) at `times`: the slope of the grid interval holding each time."""
        i = np.clip(np.searchsorted(self.times, np.asarray(times, np.float64), "right") - 1, 0, len(self.times) - 2)
        return (self.u[i + 1] - self.u[i]) / (self.times[i + 1] - self.times[i])

    def poses(self, road, times, size) -> tuple[np.ndarray, np.ndarray]:
        """World box centres [M, 3] and headings [M] at `times`: the path at the interpolated progress, mapped by
        `road.pose`; the box bottom `z_lift_m` above the highest ground under its four footprint corners."""
        s, d, h = self.path.at(self.progress(times))
        x, y, theta = road.pose(s, d)
        heading = theta + h
        c, sn = np.cos(heading), np.sin(heading)
        corners_x = x[:, None] + np.array([1, 1, -1, -1]) * size[0] / 2 * c[:, None] - np.array(
            [1, -1, 1, -1]) * size[1] / 2 * sn[:, None]
        corners_y = y[:, None] + np.array([1, 1, -1, -1]) * size[0] / 2 * sn[:, None] + np.array(
            [1, -1, 1, -1]) * size[1] / 2 * c[:, None]
        ground = road.ground_height(corners_x, corners_y).max(axis=1)
        return np.stack([x, y, ground + self.z_lift_m + size[2] / 2], -1), heading


def free_speed_profile(rng: np.random.Generator, times: np.ndarray, cruise_mps: float, stops_per_s: float,
                       slows_per_s: float, accel_mps2: float, decel_mps2: float) -> np.ndarray:
    """Desired speed [T] on the grid: `cruise_mps` with Poisson events (rates per second) of braking at `decel_mps2`
    to a stop held 1-6 s, or slowing to 30-70 % for 2-6 s, each followed by accelerating at `accel_mps2` back.
    The number of draws depends only on the grid's span (deterministic for a seed and span)."""
    span = float(times[-1] - times[0])
    target = np.full(len(times), cruise_mps)
    for rate, low, high, hold in ((stops_per_s, 0.0, 0.0, (1.0, 6.0)), (slows_per_s, 0.3, 0.7, (2.0, 6.0))):
        count = rng.poisson(rate * span)
        starts = times[0] + rng.uniform(0.0, span, count)
        levels = cruise_mps * rng.uniform(low, high, count)
        holds = rng.uniform(*hold, count)
        for t0, level, held in zip(starts, levels, holds):
            down = (cruise_mps - level) / decel_mps2
            up = (cruise_mps - level) / accel_mps2
            dt = times - t0
            event = np.where(dt < 0, cruise_mps, np.where(dt < down, cruise_mps - decel_mps2 * dt, np.where(
                dt < down + held, level, np.minimum(cruise_mps, level + accel_mps2 * (dt - down - held)))))
            target = np.minimum(target, event)
    return np.maximum(target, 0.0)


def _lane_x(m: dict, u: np.ndarray) -> np.ndarray:
    """Position along the queue (m) at progress u: straight before a turn that leaves the queue, the projection on
    the line after it (movers that stay in the queue through their turn have turn_u = inf: arc length)."""
    phi = np.clip((u - m["turn_u"]) / m["radius"], 0.0, np.pi / 2)
    return m["x0"] + np.minimum(u, m["turn_u"]) + m["radius"] * np.sin(phi)


def _flatten(queues: list) -> tuple[list, dict]:
    """Every mover of `queues`, each queue's front mover first, and their parameters as arrays (`simulate`)."""
    movers, rows, group, first = [], [], [], []
    for q, queue in enumerate(queues):
        order = np.argsort([-queue.direction * mv.start_s for mv in queue.movers], kind="stable")
        first.append(len(movers))
        for i in order:
            movers.append(queue.movers[i])
            rows.append((q, int(i)))
            group.append(q)
    group = np.array(group, np.int64)
    direction = np.array([queues[q].direction for q in group], np.float64)
    idm = {k: np.array([queues[q].idm[k] for q in group]) for k in VEHICLE_IDM}
    arrays = {"rows": rows, "group": group, "group_first": np.array(first, np.int64)[group],
              "x0": direction * np.array([mv.start_s for mv in movers]),
              "turn_u": np.array([mv.turn_u() if mv.exits_line else np.inf for mv in movers]),
              "radius": np.array([mv.lane.turn_radius_m if mv.lane.turn_s is not None else 1.0 for mv in movers]),
              "exit_angle": np.array([mv.exit_angle() for mv in movers]),
              "length": np.array([mv.length_m for mv in movers]), "yields": np.array([mv.yields for mv in movers]),
              "turn_speed": np.array([mv.turn_speed_mps for mv in movers]), "idm": idm}
    # The mover ahead on the same path: the previous one (front first) of the same queue and lane geometry.
    last: dict = {}
    arrays["path_prev"] = np.full(len(movers), -1, np.int64)
    for k, (mv, q) in enumerate(zip(movers, group)):
        key = (int(q), mv.lane)
        arrays["path_prev"][k] = last.get(key, -1)
        last[key] = k
    lines = [(q, ln) for q, queue in enumerate(queues) for ln in queue.stop_lines]
    arrays["line_group"] = np.array([q for q, _ in lines], np.int64)
    arrays["line_x"] = np.array([queues[q].direction * ln.s for q, ln in lines])
    arrays["line_yield"] = np.array([ln.yield_line for _, ln in lines], bool)
    arrays["line_red"] = np.array([ln.red for _, ln in lines], bool) if lines else np.zeros((0, 0), bool)
    return movers, arrays


def simulate(queues: list, times: np.ndarray) -> list:
    """Progress [T] of each mover on the grid `times` (uniform step): one list per queue, in the order of its
    movers. The queues are independent (a mover only follows the movers of its own queue), stepped together."""
    movers, m = _flatten(queues)
    n = len(movers)
    out = np.zeros((n, len(times)))
    if n:
        _run(movers, m, times, out)
    result = [[None] * len(queue.movers) for queue in queues]
    for k, (q, i) in enumerate(m["rows"]):
        result[q][i] = out[k]
    return result


def _run(movers: list, m: dict, times: np.ndarray, out: np.ndarray) -> None:
    """Steps the flattened movers (`_flatten`) over the grid, writing progress into `out` [n, T].

    Each mover keeps its distance to two leaders: the nearest mover ahead still in its queue's line (by position
    along the line, until its own turn begins), and the mover ahead on the same path (same lane and turn: by arc
    length, through and after the turn). A mover leaving its queue neither stops in its turn nor after it (it drives
    off at its cruise speed), so it never blocks another queue's line."""
    n = len(movers)
    turn_u, length, idm, prev = m["turn_u"], m["length"], m["idm"], m["path_prev"]
    a_max, b_comf = idm["accel_mps2"], idm["decel_mps2"]
    free = np.stack([mv.free_speed_mps for mv in movers])  # [n, T]
    cruise = free.max(axis=1)
    turn_end = turn_u + m["radius"] * np.pi / 2 + length
    u = np.zeros(n)
    v = np.array([mv.speed0_mps for mv in movers])
    dt = float(times[1] - times[0])
    idx = np.arange(n)
    line_applies = m["line_group"][:, None] == m["group"][None, :]  # [L, n]
    line_applies &= ~m["line_yield"][:, None] | m["yields"][None, :]
    has_prev = prev >= 0
    prev_or_self = np.where(has_prev, prev, idx)
    for step in range(len(times)):
        out[:, step] = u
        if step == len(times) - 1:
            break
        x = _lane_x(m, u)
        in_line = (u - turn_u) / m["radius"] < m["exit_angle"]
        before_turn = u <= turn_u
        # Line leader: the nearest mover ahead in the same queue still in its line (no overtaking within a queue).
        ahead = np.maximum.accumulate(np.where(in_line, idx, -1))
        lead = np.concatenate([[-1], ahead[:-1]])
        lead = np.where((lead >= m["group_first"]) & before_turn, lead, -1)
        gap = np.where(lead >= 0, x[lead] - x - (length[lead] + length) / 2, np.inf)
        lead_v = np.where(lead >= 0, v[lead], v)
        # Path leader: the mover ahead on the same path, by arc length.
        arc = m["x0"] + u
        gap_path = np.where(has_prev, arc[prev_or_self] - arc - (length[prev_or_self] + length) / 2, np.inf)
        nearer = gap_path < gap
        gap, lead_v = np.where(nearer, gap_path, gap), np.where(nearer, v[prev_or_self], lead_v)
        # Red stop lines ahead that a mover can still stop at act as a standing leader.
        red = np.flatnonzero(m["line_red"][:, step]) if m["line_red"].size else np.zeros(0, np.int64)
        if red.size:
            to_line = m["line_x"][red, None] - x[None] - length[None] / 2  # [R, n]
            applies = line_applies[red] & (in_line & before_turn)[None] & (to_line > -0.1) & (
                to_line > (v * v / (2 * STOP_LINE_DECEL_MPS2))[None])
            to_line = np.where(applies, to_line, np.inf).min(axis=0)
            nearer = to_line < gap
            gap, lead_v = np.where(nearer, to_line, gap), np.where(nearer, 0.0, lead_v)
        desired, slope = free[:, step + 1], (free[:, step + 1] - free[:, step]) / dt
        approach = np.sqrt(m["turn_speed"] ** 2 + 2 * b_comf * np.maximum(turn_u - u, 0.0))
        desired = np.where(before_turn, np.minimum(desired, approach),
                           np.where(u < turn_end, np.minimum(m["turn_speed"], cruise), cruise))
        slope = np.where(before_turn, slope, 0.0)
        # Free flow: the profile's own slope (feed-forward) plus a correction towards it.
        a_top = np.maximum(a_max, slope)
        a_free = np.clip(slope + SPEED_TRACKING_PER_S * (desired - v), -MAX_DECEL_MPS2, a_top)
        s_star = idm["min_gap_m"] + np.maximum(0.0, v * idm["time_gap_s"] + v * (v - lead_v) /
                                               (2 * np.sqrt(a_max * b_comf)))
        with np.errstate(divide="ignore", invalid="ignore"):
            a_int = np.where(np.isfinite(gap), a_max * (1 - (s_star / np.maximum(gap, 1e-3)) ** 2), np.inf)
        acc = np.clip(np.minimum(a_free, a_int), -MAX_DECEL_MPS2, a_top)
        v_new = np.maximum(v + acc * dt, 0.0)
        v_new = np.where((acc < 0) & (v_new < STANDSTILL_MPS), 0.0, v_new)  # braking to a standstill ends in one
        u_new = u + (v + v_new) / 2 * dt
        _clamp(m, u, u_new, v_new, lead)
        u, v = u_new, v_new


def _clamp(m: dict, u: np.ndarray, u_new: np.ndarray, v_new: np.ndarray, lead: np.ndarray) -> None:
    """Holds each mover (in place) at least CLAMP_GAP_M behind its line leader (before its turn: position along the
    line is x0 + u) and its path leader (arc length x0 + u), front to back, so a held leader holds its follower."""
    length, prev = m["length"], m["path_prev"]
    x_new = _lane_x(m, u_new)
    arc_new = m["x0"] + u_new
    limit = np.full(len(u), np.inf)
    has_lead, has_prev = lead >= 0, prev >= 0
    limit[has_lead] = x_new[lead[has_lead]] - (length[has_lead] + length[lead[has_lead]]) / 2 - CLAMP_GAP_M
    limit_arc = np.full(len(u), np.inf)
    limit_arc[has_prev] = arc_new[prev[has_prev]] - (length[has_prev] + length[prev[has_prev]]) / 2 - CLAMP_GAP_M
    for i in np.flatnonzero((x_new > limit - 1.0) | (arc_new > limit_arc - 1.0)):
        over = -np.inf
        if lead[i] >= 0:
            j = lead[i]
            over = x_new[i] - (x_new[j] - (length[i] + length[j]) / 2 - CLAMP_GAP_M)
        if prev[i] >= 0:
            j = prev[i]
            over = max(over, arc_new[i] - (arc_new[j] - (length[i] + length[j]) / 2 - CLAMP_GAP_M))
        if over > 0:
            u_new[i] = max(u[i], u_new[i] - over)
            x_new[i] = _lane_x({k: m[k][i:i + 1] for k in ("x0", "turn_u", "radius")}, u_new[i:i + 1])[0]
            arc_new[i] = m["x0"][i] + u_new[i]
            leaders = [j for j in (lead[i], prev[i]) if j >= 0]
            v_new[i] = min([v_new[i]] + [v_new[j] for j in leaders])
