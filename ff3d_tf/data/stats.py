"""Dataset statistics (paper Figure "Distribution of moving and stationary LiDAR points")."""
from __future__ import annotations

import numpy as np

from ff3d_tf import schema

STAT_CLASSES = (schema.CLASS_VEHICLE, schema.CLASS_PEDESTRIAN, schema.CLASS_CYCLIST, schema.CLASS_SIGN)  # figure order


class FlowStats:
    """Accumulates per-class moving/stationary counts and moving-point speeds over frames."""

    def __init__(self, max_speeds_kept: int = 2_000_000, seed: int = 0):
        self.counts = {c: [0, 0] for c in STAT_CLASSES}  # moving, stationary
        self.speeds = {c: [] for c in STAT_CLASSES}
        self.frames = 0
        self.points = 0
        self.no_label = 0
        self.background = 0
        self._rng = np.random.default_rng(seed)
        self._cap = max_speeds_kept

    def update(self, flow_mps: np.ndarray, class_id: np.ndarray) -> None:
        self.frames += 1
        self.points += len(class_id)
        self.no_label += int(np.sum(class_id == schema.CLASS_NO_LABEL))
        self.background += int(np.sum(class_id == schema.CLASS_BACKGROUND))
        speed = np.linalg.norm(flow_mps, axis=1)
        for c in STAT_CLASSES:
            sel = class_id == c
            moving = sel & (speed >= schema.STATS_MOVING_THRESHOLD_MPS)
            self.counts[c][0] += int(moving.sum())
            self.counts[c][1] += int((sel & ~moving).sum())
            if sum(len(s) for s in self.speeds[c]) < self._cap:
                self.speeds[c].append(speed[moving])

    def table(self) -> str:
        lines = [f"{self.frames} frames, {self.points} points ({self.points / max(self.frames, 1):.0f} per frame); "
                 f"background {self.background}, no flow label (class -1) {self.no_label}",
                 f"{'class':<12}{'moving':>10}{'(count)':>14}{'stationary':>12}{'(count)':>14}{'mean speed':>12}"]
        for c in STAT_CLASSES:
            mov, sta = self.counts[c]
            total = max(mov + sta, 1)
            sp = np.concatenate(self.speeds[c]) if self.speeds[c] else np.zeros(0)
            mean = f"{sp.mean():.2f} m/s" if sp.size else "-"
            lines.append(f"{schema.CLASS_NAMES[c]:<12}{100 * mov / total:>9.1f}%{mov:>14d}{100 * sta / total:>11.1f}%"
                         f"{sta:>14d}{mean:>12}")
        return "\n".join(lines)

    def as_dict(self) -> dict:
        out = {"frames": self.frames, "points": self.points, "no_label_points": self.no_label}
        for c in STAT_CLASSES:
            mov, sta = self.counts[c]
            sp = np.concatenate(self.speeds[c]) if self.speeds[c] else np.zeros(0)
            out[schema.CLASS_NAMES[c]] = {"moving": mov, "stationary": sta,
                                          "moving_share": mov / max(mov + sta, 1),
                                          "mean_moving_speed_mps": float(sp.mean()) if sp.size else float("nan")}
        return out

    def moving_speeds(self) -> dict[str, np.ndarray]:
        return {schema.CLASS_NAMES[c]: (np.concatenate(self.speeds[c]) if self.speeds[c] else np.zeros(0))
                for c in STAT_CLASSES}
