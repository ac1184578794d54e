"""The city world of the realistic profile (`realism.REALISTIC`): the street world's curved road and lanes
(`scene.Road`, with wider curves that never wind back), on sloped ground, with intersections and everything that makes
a multi-sweep history informative.

- Ground: `Terrain`, a smooth height field (three plane waves; grades up to a few per cent, a modelling choice of
  gentle urban slopes). Agents stand on it (yaw-only boxes: their bottom just above the highest ground under their
  footprint); the ego's pose follows it (yaw only, as the street world's, so boxes stay yaw-only in its frame).
- Intersections on straight stretches, each with side streets on both sides and a traffic light (main road red for
  part of a cycle), stop lines for the lanes and bike lanes.
- Traffic (`traffic.simulate`): vehicles of several sizes (cars, vans, trucks and buses) and the ego in four lanes,
  cyclists in two bike lanes, pedestrians in four sidewalk lines, each with a free speed profile whose events brake
  to a stop, slow down and accelerate again, queueing behind each other and at red lights; outer-lane vehicles and
  some cyclists turn right into side streets (vehicles yield to cyclists going straight) and vanish 40 m down it;
  pedestrians reaching an intersection turn into its side street (and vanish likewise), some turn into doors and
  vanish, some appear mid-log. No two boxes overlap (`tests/data/synthetic/test_realism.py`).
- Static: parked vehicles, standing pedestrians and cyclists, poles with signs, street lights and bollards at the
  corners, trees (a solid trunk under a porous crown) and hedges (porous), buildings (buried in the slope).

Cruise speeds per lane or line (modelling choices near the paper's dataset figure, moving means near 5.6, 1.3 and
3.8 m/s for vehicles, pedestrians, cyclists): vehicles N(7, 2) m/s within [4, 12] (stops, lights, queues and turns
slow them), pedestrians N(1.35, 0.2), cyclists N(3.8, 0.8), each mover within 15 % of its line's.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ff3d_tf.data.synthetic import scene as sim
from ff3d_tf.data.synthetic import traffic

WARMUP_S = 15.0  # the traffic runs this long before t = 0 (queues form at the lights)
# Curves wide enough that the offsets of the cross-section (buildings up to ~35 m out) stay outside their centres, and
# a heading within 50 degrees of the start's, so the road never crosses itself (modelling choices).
ROAD_RADIUS_M = (60.0, 150.0)
ROAD_MAX_HEADING_RAD = np.deg2rad(50.0)
SIDE_STREET_TRAVEL_M = 40.0  # movers that turned into a side street vanish this far past their turn
MAX_SPEED_MPS = 13.0
INTERSECTION_HALF_SPAN_M = 16.0  # straight road needed either side of an intersection
INTERSECTION_CLEAR_M = 11.0  # no parked cars, standing people, poles, trees or buildings this close to one
SIDE_LANE_S_M = 1.75  # side street lanes at s_int +/- this
SIDE_BIKE_S_M = 4.5
SIDE_WALK_S_M = 6.0
STOP_LINE_M = 10.0  # before the intersection's centre
VEHICLE_TURN_RADIUS_M = 6.0
CYCLIST_TURN_RADIUS_M = SIDE_BIKE_S_M - 1.5
PEDESTRIAN_TURN_RADIUS_M = 1.0
DOOR_TURN_RADIUS_M = 0.6
# The cross-section (lateral offsets d, metres, left positive), laid out so that no two boxes of neighbouring lines
# overlap: the street world's four lanes (vehicles up to 2.6 m wide), bike lanes, parking (cars and vans up to 2.2 m
# wide), standing cyclists, two sidewalk lines, standing pedestrians, poles, trees, hedges, then buildings.
LANES = ((-1.75, 1), (-5.25, 1), (1.75, -1), (5.25, -1))  # (d, direction)
EGO_LANE = LANES[0]
BIKE_LANES = ((-7.2, 1), (7.2, -1))
PARKING_D = 8.9
STANDING_CYCLIST_D = 10.4
BOLLARD_D = 10.2
SIDEWALK_LINES = ((-11.2, 1), (-12.0, -1), (11.2, -1), (12.0, 1))
STANDING_PEDESTRIAN_D = 12.8
POLE_D = 13.4
TREE_D = 13.9
HEDGE_D = 14.6
BUILDING_D = 15.0
# (share, category, length, width, height ranges) of moving vehicles; the Argoverse categories are all vehicles.
VEHICLE_KINDS = ((0.75, None, (4.0, 5.2), (1.8, 2.1), (1.4, 1.9)), (0.15, None, (4.8, 5.9), (1.9, 2.2), (1.9, 2.5)),
                 (0.06, "BOX_TRUCK", (6.5, 9.0), (2.3, 2.6), (2.8, 3.6)), (0.04, "BUS", (10.5, 12.5), (2.5, 2.6),
                                                                          (3.0, 3.4)))
EGO_SIZE = np.array([4.9, 1.9, 1.5])
TREE_CROWN_EXTINCTION_PER_M = (0.8, 2.0)  # modelling choices: a crown a ray crosses by 2 m returns most of the time
HEDGE_EXTINCTION_PER_M = (2.0, 4.0)


class Terrain:
    """Ground height z(x, y) = sum_i a_i sin(k_i . (x, y) + phase_i): wavelengths 120-400 m, the steepest grade
    (sum of a_i |k_i|) 1-3 % (the ego and the boxes stay yaw-only, so the ground leans by up to that grade in their
    frames)."""

    def __init__(self, rng: np.random.Generator, count: int = 3):
        wavelength = rng.uniform(120.0, 400.0, count)
        direction = rng.uniform(0.0, 2 * np.pi, count)
        self.phase = rng.uniform(0.0, 2 * np.pi, count)
        self.max_grade = float(rng.uniform(0.01, 0.03))
        k = 2 * np.pi / wavelength
        self.kx, self.ky = k * np.cos(direction), k * np.sin(direction)
        self.amplitude = self.max_grade * rng.dirichlet(np.ones(count)) / k

    def height(self, x, y) -> np.ndarray:
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        out = np.zeros(np.broadcast(x, y).shape)
        for a, kx, ky, ph in zip(self.amplitude, self.kx, self.ky, self.phase):
            out = out + a * np.sin(kx * x + ky * y + ph)
        return out

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, max_range: float, samples: int = 32,
                  chunk: int = 16384) -> np.ndarray:
        """Distance [K] along unit rays to the first ground crossing within max_range (inf: none): the first sign
        change of height above ground on samples denser near the origin, 18 bisections, then the secant between the
        last two."""
        out = np.full(len(dirs), np.inf)
        # A ray climbing faster than the steepest grade never meets ground it starts above.
        climb = dirs[:, 2] / np.maximum(np.hypot(dirs[:, 0], dirs[:, 1]), 1e-9)
        todo = np.flatnonzero(climb < self.max_grade)
        ts = max_range * (np.arange(1, samples + 1) / samples) ** 2
        for lo in range(0, len(todo), chunk):
            rays = todo[lo:lo + chunk]
            o, d = origins[rays], dirs[rays]
            above = o[:, 2:3] + ts[None] * d[:, 2:3] - self.height(o[:, 0:1] + ts[None] * d[:, 0:1],
                                                                    o[:, 1:2] + ts[None] * d[:, 1:2])  # [R, S]
            below = above < 0
            hit = below.any(axis=1)
            first = np.argmax(below, axis=1)[hit]
            rays, o, d = rays[hit], o[hit], d[hit]
            t_hi = ts[first]
            t_lo = np.where(first > 0, ts[np.maximum(first - 1, 0)], 0.0)
            f_hi = above[hit, first]
            f_lo = np.where(first > 0, above[hit, np.maximum(first - 1, 0)], o[:, 2] - self.height(o[:, 0], o[:, 1]))
            for _ in range(18):
                mid = (t_lo + t_hi) / 2
                p = o + mid[:, None] * d
                f_mid = p[:, 2] - self.height(p[:, 0], p[:, 1])
                under = f_mid < 0
                t_hi, f_hi = np.where(under, mid, t_hi), np.where(under, f_mid, f_hi)
                t_lo, f_lo = np.where(under, t_lo, mid), np.where(under, f_lo, f_mid)
            out[rays] = t_lo + (t_hi - t_lo) * f_lo / np.maximum(f_lo - f_hi, 1e-300)
        return out


def _intersections(rng: np.random.Generator, road: sim.Road, s_lo: float, s_hi: float) -> list[float]:
    """Road s of intersection centres: on straight stretches (no curvature within INTERSECTION_HALF_SPAN_M), 90-200 m
    apart."""
    straight = np.abs(road.kappa) < 1e-12
    window = int(round(INTERSECTION_HALF_SPAN_M / road.ds))
    # A point is usable when every tabulated point within the window is straight.
    run = np.convolve(~straight, np.ones(2 * window + 1), mode="same") == 0
    out = []
    s = s_lo + rng.uniform(20.0, 90.0)
    while s < s_hi:
        i = np.searchsorted(road.s, s)
        usable = np.flatnonzero(run[i:])
        if usable.size == 0:
            break
        s_int = float(road.s[i + usable[0]])
        if s_int >= s_hi:
            break
        out.append(s_int)
        s = s_int + rng.uniform(90.0, 200.0)
    return out


def _red_masks(rng: np.random.Generator, times: np.ndarray, count: int) -> list[np.ndarray]:
    """Per intersection, [T] True while the main road has red: a 30-50 s cycle, green 60-75 % of it, random phase
    (modelling choices of a fixed-time signal)."""
    masks = []
    for _ in range(count):
        cycle, green, phase = rng.uniform(30.0, 50.0), rng.uniform(0.6, 0.75), rng.uniform(0.0, 1.0)
        masks.append(((times / cycle + phase) % 1.0) >= green)
    return masks


def _near_any(s: float, centres, half: float) -> bool:
    return any(abs(s - c) < half for c in centres)


class _Builder:
    """Collects the agents of one city (module docstring), in the order they are made."""

    def __init__(self, rng: np.random.Generator, road: sim.Road, times: np.ndarray, intersections: list,
                 red: list):
        self.rng, self.road, self.times = rng, road, times
        self.intersections, self.red = intersections, red
        self.agents: list[sim.Agent] = []
        self.doors: list[tuple[float, float]] = []  # (s, d) of doors pedestrians walk into

    def doors_on(self, d: float) -> list:
        """Road s of the doors on the side of lateral offset d."""
        return [s for s, dd in self.doors if dd * d > 0]

    def add(self, **kw) -> sim.Agent:
        agent = sim.Agent(track_id=f"obj{len(self.agents):04d}", **kw)
        self.agents.append(agent)
        return agent

    def ground_under(self, s: float, d: float, size, heading_offset: float = 0.0) -> tuple[float, float]:
        """(lowest, highest) ground height under a yaw box of `size` centred at road (s, d)."""
        x, y, th = self.road.pose(s, d)
        h = th + heading_offset
        cx = x + np.array([1, 1, -1, -1]) * size[0] / 2 * np.cos(h) - np.array([1, -1, 1, -1]) * size[1] / 2 * np.sin(h)
        cy = y + np.array([1, 1, -1, -1]) * size[0] / 2 * np.sin(h) + np.array([1, -1, 1, -1]) * size[1] / 2 * np.cos(h)
        g = self.road.ground_height(np.append(cx, x), np.append(cy, y))
        return float(g.min()), float(g.max())

    def static(self, size, s, d, material, class_id=0, labelled=False, base="lift", reverse=False, lift=0.0,
               extinction=0.0, category=None) -> sim.Agent:
        """A standing box at road (s, d): `base` "lift" puts its bottom `lift` above the highest ground under it (a
        labelled object), "bury" sinks it to the lowest ground less 0.5 m (buildings, poles: no gap on a slope)."""
        size = np.asarray(size, np.float64).copy()
        low, high = self.ground_under(s, d, size, np.pi if reverse else 0.0)
        if base == "bury":
            bottom = low - 0.5
            size[2] += high - bottom
        else:
            bottom = high + lift
        return self.add(class_id=class_id, size=size, s0=s, d=d, speed=0.0, reverse=reverse, z_bottom=bottom,
                        material=material, labelled=labelled, extinction_per_m=extinction, category=category)


def _vehicle_size(rng: np.random.Generator, kinds=VEHICLE_KINDS):
    shares = np.array([k[0] for k in kinds])
    kind = kinds[int(rng.choice(len(kinds), p=shares / shares.sum()))]
    return kind[1], np.array([rng.uniform(*kind[2]), rng.uniform(*kind[3]), rng.uniform(*kind[4])])


def _next_intersection(s: float, direction: int, intersections: list, turn_before_m: float) -> float | None:
    """The next intersection ahead of road s whose turn, starting `turn_before_m` before its centre, is still ahead
    of a mover at s (a mover past that point drives through to the next)."""
    ahead = [c for c in intersections if (c - s) * direction > turn_before_m + 0.5]
    return min(ahead, key=lambda c: abs(c - s)) if ahead else None


def _stop_lines(b: _Builder, direction: int) -> list:
    return [traffic.StopLine(c - direction * STOP_LINE_M, red) for c, red in zip(b.intersections, b.red)]


@dataclasses.dataclass
class _Pending:
    """A queue waiting to be simulated, with what its agents will be: per mover a size, an Argoverse category
    ("ego": the ego's own mover, no agent), a time of appearing and a progress at which it vanishes (a door)."""

    queue: traffic.Queue
    sizes: list
    class_id: int
    material: str
    categories: list
    t_starts: list
    door_ends: list


def _realize(b: _Builder, pendings: list) -> tuple[list, traffic.Track | None]:
    """Simulates the queues together and adds an agent per mover; returns ([agents per queue], the ego's track)."""
    progress = traffic.simulate([p.queue for p in pendings], b.times)
    agents, ego_track = [], None
    for pending, us in zip(pendings, progress):
        added = []
        for k, (mover, u) in enumerate(zip(pending.queue.movers, us)):
            if pending.categories[k] == "ego":
                ego_track = traffic.Track(b.times, u, mover.path(), 0.0)
                added.append(None)
                continue
            # A mover vanishes into its door, or SIDE_STREET_TRAVEL_M down the side street it turned into (out of the
            # street's view between the buildings, and before side streets of other intersections could meet).
            vanish = pending.door_ends[k]
            if not np.isfinite(vanish) and mover.lane.turn_s is not None:
                vanish = mover.turn_u() + mover.lane.turn_radius_m * np.pi / 2 + SIDE_STREET_TRAVEL_M
            t_end = float(np.interp(vanish, u, b.times)) if np.isfinite(vanish) and u[-1] >= vanish else np.inf
            added.append(b.add(class_id=pending.class_id, size=pending.sizes[k], s0=mover.start_s, d=mover.lane.d,
                               speed=0.0, reverse=mover.lane.direction < 0, z_bottom=sim.BOX_LIFT_M,
                               material=pending.material, category=pending.categories[k],
                               track=traffic.Track(b.times, u, mover.path(), sim.BOX_LIFT_M),
                               t_start=pending.t_starts[k], t_end=t_end))
        agents.append(added)
    return agents, ego_track


def _pending(queue, sizes, class_id, material, categories=None, t_starts=None, door_ends=None) -> _Pending:
    n = len(queue.movers)
    return _Pending(queue, sizes, class_id, material, categories or [None] * n, t_starts or [-np.inf] * n,
                    door_ends or [np.inf] * n)


def _cyclists(b: _Builder, s_lo: float, s_hi: float) -> list:
    """Bike lane queues, simulated; returns [(direction, [agent per mover], [going straight per mover])]."""
    rng, pendings, straight = b.rng, [], []
    turn_before = SIDE_BIKE_S_M + CYCLIST_TURN_RADIUS_M
    for d, direction in BIKE_LANES:
        cruise = float(np.clip(rng.normal(3.8, 0.8), 2.0, 6.0))
        movers, sizes, turns = [], [], []
        s = s_lo + rng.uniform(0, 30)
        while s < s_hi:
            if not _near_any(s, b.intersections, INTERSECTION_CLEAR_M):
                size = np.array([rng.uniform(1.6, 1.9), rng.uniform(0.6, 0.8), rng.uniform(1.6, 1.8)])
                c = _next_intersection(s, direction, b.intersections, turn_before)
                turn = c is not None and rng.uniform() < 0.4
                lane = traffic.LaneGeometry(d, direction, (c - direction * turn_before) if turn else None,
                                            CYCLIST_TURN_RADIUS_M, -1)
                v0 = cruise * rng.uniform(0.85, 1.15)
                free = traffic.free_speed_profile(rng, b.times, v0, 1 / 60, 1 / 40, 1.0, 2.0)
                movers.append(traffic.Mover(lane, s, size[0], size[1], v0, free, turn_speed_mps=2.5))
                sizes.append(size)
                turns.append(turn)
            s += rng.uniform(25.0, 70.0)
        pendings.append(_pending(traffic.Queue(direction, movers, _stop_lines(b, direction), traffic.CYCLIST_IDM),
                                 sizes, 4, "cyclist"))
        straight.append([not t for t in turns])
    agents, _ = _realize(b, pendings)
    return [(p.queue.direction, a, st) for p, a, st in zip(pendings, agents, straight)]


def _bike_conflict(b: _Builder, bikes, direction: int, turn_s: float) -> np.ndarray:
    """[T] True while a cyclist going straight is within the zone a vehicle turning right from the outer lane at
    `turn_s` sweeps across the bike lane of its side (25 m before to 8 m after the turn start: time for a long
    vehicle to clear the lane)."""
    red = np.zeros(len(b.times), bool)
    for bike_direction, agents, straight in bikes:
        if bike_direction != direction:
            continue
        for agent, going_straight in zip(agents, straight):
            if going_straight:
                s, _, _ = agent.track.path.at(agent.track.u)
                ahead = (s - turn_s) * direction
                red |= (ahead > -25.0) & (ahead < 8.0)
    return red


def _vehicles(b: _Builder, s_lo: float, s_hi: float, bikes) -> list:
    """Lane queues (the ego a member of its lane's, category "ego"), not yet simulated."""
    rng, pendings = b.rng, []
    turn_before = SIDE_LANE_S_M + VEHICLE_TURN_RADIUS_M
    for d, direction in LANES:
        cruise = float(np.clip(rng.normal(7.0, 2.0), 4.0, 12.0))
        movers, sizes, cats, yield_lines = [], [], [], {}
        ego_placed = (d, direction) != EGO_LANE
        s = s_lo + rng.uniform(0, 20)
        while s < s_hi:
            if not ego_placed and s > -8.0:
                v0 = float(np.clip(rng.normal(cruise, 1.0), 3.0, MAX_SPEED_MPS - 2))
                free = traffic.free_speed_profile(rng, b.times, v0, 1 / 240, 1 / 120, 1.2, 2.0)
                movers.append(traffic.Mover(traffic.LaneGeometry(d, direction), 0.0, EGO_SIZE[0], EGO_SIZE[1], v0,
                                            free))
                sizes.append(EGO_SIZE)
                cats.append("ego")
                ego_placed = True
                s = EGO_SIZE[0] + rng.uniform(12.0, 40.0)
                continue
            category, size = _vehicle_size(rng)
            c = _next_intersection(s, direction, b.intersections, turn_before)
            turn = abs(d) > 3.5 and c is not None and rng.uniform() < 0.5
            turn_s = c - direction * turn_before if turn else None
            v0 = cruise * rng.uniform(0.85, 1.15)
            free = traffic.free_speed_profile(rng, b.times, v0, 1 / 90, 1 / 45, rng.uniform(0.8, 2.0),
                                              rng.uniform(1.5, 3.5))
            movers.append(traffic.Mover(traffic.LaneGeometry(d, direction, turn_s, VEHICLE_TURN_RADIUS_M, -1), s,
                                        size[0], size[1], v0 * 0.8, free, turn_speed_mps=rng.uniform(3.0, 4.5),
                                        yields=turn))
            if turn and turn_s not in yield_lines:
                yield_lines[turn_s] = traffic.StopLine(turn_s, _bike_conflict(b, bikes, direction, turn_s), True)
            sizes.append(size)
            cats.append(category)
            s += size[0] + rng.uniform(10.0, 40.0)
        queue = traffic.Queue(direction, movers, _stop_lines(b, direction) + list(yield_lines.values()),
                              traffic.VEHICLE_IDM)
        pendings.append(_pending(queue, sizes, 1, "vehicle", cats))
    return pendings


def _pedestrians(b: _Builder, s_lo: float, s_hi: float) -> list:
    """Sidewalk lines, not yet simulated: one queue per line and stretch between intersections (every member of it
    turns into the same side street, or into a door and vanishes)."""
    rng, pendings = b.rng, []
    turn_before = SIDE_WALK_S_M + PEDESTRIAN_TURN_RADIUS_M
    for d, direction in SIDEWALK_LINES:
        cruise = float(np.clip(rng.normal(1.35, 0.2), 0.8, 2.0))
        away = -1 if (d < 0) == (direction > 0) else 1  # turn sign away from the road
        stretches: dict = {}  # next intersection -> (movers, sizes, starts, door_ends)
        s = s_lo + rng.uniform(0, 5)
        while s < s_hi:
            if not _near_any(s, b.intersections, turn_before + 1.0):
                size = np.array([rng.uniform(0.5, 0.9), rng.uniform(0.5, 0.8), rng.uniform(1.55, 1.9)])
                c = _next_intersection(s, direction, b.intersections, turn_before)
                lane = traffic.LaneGeometry(d, direction, None if c is None else c - direction * turn_before,
                                            PEDESTRIAN_TURN_RADIUS_M, away)
                door_end, exits = np.inf, False
                if abs(d) > 11.5 and rng.uniform() < 0.1:  # the building-side line: a door 2-15 m ahead
                    door_s = s + direction * rng.uniform(2.0, 15.0)
                    if c is None or (c - door_s) * direction > turn_before + 2.0:
                        lane = traffic.LaneGeometry(d, direction, door_s, DOOR_TURN_RADIUS_M, away)
                        door_end, exits = (door_s - s) * direction + DOOR_TURN_RADIUS_M * np.pi / 2 + 2.5, True
                        b.doors.append((door_s, d))
                v0 = cruise * rng.uniform(0.85, 1.15)
                free = traffic.free_speed_profile(rng, b.times, v0, 1 / 20, 1 / 20, 0.8, 1.5)
                group = stretches.setdefault(c, ([], [], [], []))
                group[0].append(traffic.Mover(lane, s, size[0], size[1], v0, free, turn_speed_mps=v0 * 0.8,
                                              exits_line=exits))
                group[1].append(size)
                group[2].append(rng.uniform(0.0, 10.0) if rng.uniform() < 0.1 else -np.inf)
                group[3].append(door_end)
            s += rng.uniform(4.0, 15.0)
        for movers, sizes, starts, door_ends in stretches.values():
            pendings.append(_pending(traffic.Queue(direction, movers, [], traffic.PEDESTRIAN_IDM), sizes, 2,
                                     "pedestrian", None, starts, door_ends))
    return pendings


def _static(b: _Builder, s_lo: float, s_hi: float) -> None:
    """Parked vehicles, standing people, poles, signs, lights, bollards, trees, hedges, buildings."""
    rng, ints = b.rng, b.intersections
    for d in (-PARKING_D, PARKING_D):
        s = s_lo + rng.uniform(0, 10)
        while s < s_hi:
            if rng.uniform() < 0.5 and not _near_any(s, ints, INTERSECTION_CLEAR_M + 2):
                category, size = _vehicle_size(rng, VEHICLE_KINDS[:2])  # cars and vans
                b.static(size, s + size[0] / 2, d, "vehicle", 1, True, reverse=bool(rng.uniform() < 0.3),
                         lift=sim.BOX_LIFT_M, category=category)
                s += size[0]
            s += rng.uniform(1.5, 4.0)
    for d, count_per_m, size, class_id, material in (
            (STANDING_CYCLIST_D, 1 / 120, [1.7, 0.7, 1.7], 4, "cyclist"),
            (STANDING_PEDESTRIAN_D, 1 / 50, [0.6, 0.6, 1.75], 2, "pedestrian")):
        for side in (-1.0, 1.0):
            placed: list = []
            for s in rng.uniform(s_lo, s_hi, size=int((s_hi - s_lo) * count_per_m)):
                # Apart by twice their length (the inner side of a curve shortens the gap up to a third).
                if not (_near_any(s, ints, INTERSECTION_CLEAR_M) or _near_any(s, placed, 2 * size[0])
                        or _near_any(s, b.doors_on(side), 2.0)):
                    placed.append(s)
                    b.static(size, float(s), side * d, material, class_id, True, reverse=bool(rng.uniform() < 0.5),
                             lift=sim.BOX_LIFT_M)
    poles = []
    for d in (-POLE_D, POLE_D):
        s = s_lo
        while s < s_hi:
            s += rng.uniform(12.0, 30.0)
            if _near_any(s, ints, INTERSECTION_CLEAR_M) or _near_any(s, b.doors_on(d), 2.0):
                continue
            pole = b.static([0.3, 0.3, 3.0], s, d, "pole", base="bury")
            poles.append((s, d))
            if rng.uniform() < 0.6:
                top = pole.z_bottom + pole.size[2]
                b.add(class_id=3, size=np.array([0.12, 0.8, 0.8]), s0=s, d=d, speed=0.0, reverse=False,
                      z_bottom=top + 0.05, material="sign")
    for c in ints:  # street lights and bollards at the corners
        for ds in (-INTERSECTION_CLEAR_M + 1.0, INTERSECTION_CLEAR_M - 1.0):
            for side in (-1.0, 1.0):
                b.static([0.25, 0.25, 7.0], c + ds, side * POLE_D, "pole", base="bury")
                for k in range(3):
                    b.static([0.2, 0.2, 1.0], c + ds * (0.75 + 0.08 * k), side * BOLLARD_D, "pole", base="bury")
    for d in (-TREE_D, TREE_D):  # trees between the poles: a solid trunk under a porous crown
        s = s_lo
        while s < s_hi:
            s += rng.uniform(8.0, 20.0)
            if (_near_any(s, ints, INTERSECTION_CLEAR_M) or _near_any(s, [ps for ps, pd in poles if pd * d > 0], 3.0)
                    or _near_any(s, b.doors_on(d), 2.5)):
                continue
            trunk = b.static([0.35, 0.35, rng.uniform(2.2, 3.2)], s, d, "trunk", base="bury")
            crown = rng.uniform(3.0, 5.5)
            b.add(class_id=0, size=np.array([crown, crown, rng.uniform(3.0, 5.0)]), s0=s, d=d, speed=0.0,
                  reverse=False, z_bottom=trunk.z_bottom + trunk.size[2] - 0.3, material="vegetation",
                  labelled=False, extinction_per_m=rng.uniform(*TREE_CROWN_EXTINCTION_PER_M))
    for side in (-1.0, 1.0):  # hedges in front of the buildings, away from doors
        s = s_lo
        while s < s_hi:
            length = rng.uniform(3.0, 10.0)
            centre = s + length / 2
            door_near = _near_any(centre, b.doors_on(side), length / 2 + 1.5)
            if rng.uniform() < 0.4 and not door_near and not _near_any(centre, ints, INTERSECTION_CLEAR_M + length):
                b.static([length, 0.8, rng.uniform(0.8, 1.5)], centre, side * HEDGE_D, "vegetation", base="bury",
                         extinction=rng.uniform(*HEDGE_EXTINCTION_PER_M))
            s += length + rng.uniform(2.0, 15.0)
    for side in (-1.0, 1.0):
        s = s_lo
        while s < s_hi:
            length, width = rng.uniform(8.0, 25.0), rng.uniform(6.0, 14.0)
            clash = [c for c in ints if s - INTERSECTION_CLEAR_M < c < s + length + INTERSECTION_CLEAR_M]
            if clash:
                s = clash[0] + INTERSECTION_CLEAR_M
                continue
            b.static([length, width, rng.uniform(5.0, 20.0)], s + length / 2,
                     side * (BUILDING_D + width / 2 + rng.uniform(0, 4)), "building", base="bury")
            s += length + rng.uniform(3.0, 12.0)


def make_world(rng: np.random.Generator, horizon_s: float) -> sim.World:
    """The city world for times in [0, horizon_s] (traffic simulated from -WARMUP_S; poses of later times hold the
    last state). Deterministic for the generator's state and the horizon."""
    reach = MAX_SPEED_MPS * (horizon_s + WARMUP_S)
    road = sim.Road(rng, s_min=-400.0, s_max=reach + 600.0, radius_range_m=ROAD_RADIUS_M,
                    max_heading_rad=ROAD_MAX_HEADING_RAD)
    road.ground = Terrain(rng)
    times = np.arange(-WARMUP_S, horizon_s + 1.0 + traffic.SIM_STEP_S, traffic.SIM_STEP_S)
    intersections = _intersections(rng, road, -150.0, reach + 250.0)
    red = _red_masks(rng, times, len(intersections))
    b = _Builder(rng, road, times, intersections, red)
    s_lo, s_hi = -250.0, reach + 450.0
    bikes = _cyclists(b, s_lo, s_hi)
    _, ego_track = _realize(b, _vehicles(b, s_lo, s_hi, bikes) + _pedestrians(b, -150.0, reach + 250.0))
    _static(b, -150.0, reach + 250.0)
    return sim.World(road, b.agents, ego_track=ego_track, intersections=tuple(intersections))


def world_for(realism, rng: np.random.Generator, horizon_s: float) -> sim.World:
    """The world of a profile: the city (`make_world`) or the street world (`scene.make_scene`, the ego at a speed
    drawn first, as the ideal generators draw it)."""
    if realism.city:
        return make_world(rng, horizon_s)
    ego_speed = float(rng.uniform(4.0, 9.0))
    road, agents = sim.make_scene(rng, ego_speed)
    return sim.World(road, agents, ego_speed=ego_speed)
