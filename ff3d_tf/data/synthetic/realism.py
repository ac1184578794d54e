"""How real the synthetic lidars are: the generators' profiles (`IDEAL`, the default, and `REALISTIC`) and the sensor
effects a profile switches on (range noise, dropped returns, per-ray firing times).

`IDEAL` is the generators' world and sensor as they were before profiles: the street world of `synthetic.scene`
(agents at constant speeds along the lanes), flat ground, every ray cast at one instant, exact ranges, every ray with
a surface in range returns. The tests, `make demo` and the benchmarks' recorded figures use it; it stays bit for bit.

`REALISTIC` (`tools/make_synthetic_data.py --realistic`) is what a multi-sweep model's history is for:
- the city world (`synthetic.city`): sloped ground, intersections with traffic lights, vehicles and cyclists that
  accelerate, brake, stop and turn, pedestrians that pause, turn into side streets and doors, vegetation (porous
  tree crowns and hedges), more poles and bollards;
- motion distortion: each ray is fired at its own time within the sweep (`synthetic.lidar`) from the ego pose at
  that time, against the objects where they are at that time; the formats then compensate the ego motion as the
  datasets do (AV2: points in the ego frame at the sweep timestamp, `offset_ns` per point; WOD TOP: a pose per
  pixel), so static points are exact up to the noise and a moving object is smeared by its own motion over the
  sweep;
- range noise along each ray (`range_noise_std_m`), dropped returns (`dropout_fraction`, and a detection
  probability that falls with range and reflectivity, `range_at_10pct_m`).

Defaults: published sensor figures, cited by source name; where no sensor figure exists the default is a stated
modelling choice. How the labels relate to distorted, noisy points is written in `synthetic.av2` and
`synthetic.wod` (the boxes an annotator would draw; the box rule on the stored points).
"""
from __future__ import annotations

import dataclasses

import numpy as np

# Velodyne VLP-32C datasheet: range accuracy "up to +/-3 cm (typical)", read here as one standard deviation along the
# ray. Argoverse 2's two lidars are VLP-32Cs (Argoverse 2 paper: two roof-mounted 32-beam VLP-32C, 10 Hz). The
# Waymo Open Dataset paper publishes no range accuracy for its lidars; the same figure serves them.
VLP32C_RANGE_ACCURACY_M = 0.03
# Velodyne HDL-64E S2 datasheet: 50 m range on pavement (~10 % reflectivity), 120 m on cars and foliage (~80 %); the
# first taken here as the range at which a 10 %-reflective target is detected half the time. Received power of an extended target falls as
# reflectivity / range^2, so equal detection needs range proportional to sqrt(reflectivity) (the datasheet's second
# pair is of the order that law gives from the first).
HDL64E_RANGE_AT_10PCT_M = 50.0
REFERENCE_REFLECTIVITY = 0.10
# Modelling choices (no datasheet publishes them): the share of returns lost independently of range (dark, wet or
# specular spots, absorbed pulses) and how sharply the detection probability falls around the range of half
# detection (a logistic in log range of this slope).
DROPOUT_FRACTION = 0.05
DETECTION_SLOPE = 8.0


@dataclasses.dataclass(frozen=True)
class Realism:
    """A profile of the synthetic generators (module docstring)."""

    name: str
    city: bool  # the city world of `synthetic.city` (else the street world of `synthetic.scene`)
    motion_distortion: bool  # every ray at its own firing time (else the whole scan at the frame time)
    range_noise_std_m: float  # Gaussian noise along each ray
    dropout_fraction: float  # share of returns lost whatever their range
    range_at_10pct_m: float  # range at which a 10 %-reflective surface returns half the time (inf: always)

    @property
    def box_margin_m(self) -> float:
        """How far the labelled boxes reach beyond the object's surface on each side and above it: three standard
        deviations of the range noise, as an annotator draws a box around the noisy points (0 when exact)."""
        return 3.0 * self.range_noise_std_m


IDEAL = Realism("ideal", city=False, motion_distortion=False, range_noise_std_m=0.0, dropout_fraction=0.0,
                range_at_10pct_m=np.inf)
REALISTIC = Realism("realistic", city=True, motion_distortion=True, range_noise_std_m=VLP32C_RANGE_ACCURACY_M,
                    dropout_fraction=DROPOUT_FRACTION, range_at_10pct_m=HDL64E_RANGE_AT_10PCT_M)
PROFILES = {p.name: p for p in (IDEAL, REALISTIC)}


def profile(realism: str | Realism) -> Realism:
    """The profile named `realism` (a `Realism` is returned as is); an unknown name is a ValueError naming the
    profiles."""
    if isinstance(realism, Realism):
        return realism
    if realism not in PROFILES:
        raise ValueError(f"unknown realism profile {realism!r}; the profiles are {sorted(PROFILES)}")
    return PROFILES[realism]


def detection_probability(range_m, reflectivity, realism: Realism) -> np.ndarray:
    """Probability that a surface at `range_m` (metres) of `reflectivity` (0..1) returns: (1 - dropout_fraction)
    times a logistic in log range that is 1/2 at range_at_10pct_m * sqrt(reflectivity / 0.1)."""
    range_m = np.asarray(range_m, np.float64)
    keep = np.full(range_m.shape, 1.0 - realism.dropout_fraction)
    if np.isfinite(realism.range_at_10pct_m):
        half = realism.range_at_10pct_m * np.sqrt(np.maximum(np.asarray(reflectivity, np.float64), 1e-3) /
                                                  REFERENCE_REFLECTIVITY)
        with np.errstate(divide="ignore"):
            keep = keep / (1.0 + (np.maximum(range_m, 1e-6) / half) ** DETECTION_SLOPE)
    return keep


def measure(rng: np.random.Generator, range_m: np.ndarray, reflectivity: np.ndarray,
            realism: Realism) -> tuple[np.ndarray, np.ndarray]:
    """(measured range [K], returned [K] bool) of K true ranges (inf: no surface): each return kept with
    `detection_probability`, its range plus Gaussian noise of `range_noise_std_m`. Draws from `rng` only for the
    effects the profile has on."""
    range_m = np.asarray(range_m, np.float64)
    returned = np.isfinite(range_m)
    measured = range_m.copy()
    if realism.dropout_fraction > 0 or np.isfinite(realism.range_at_10pct_m):
        p = detection_probability(np.where(returned, range_m, 0.0), reflectivity, realism)
        returned &= rng.uniform(size=range_m.shape) < p
    if realism.range_noise_std_m > 0:
        measured = np.where(returned, measured + rng.normal(0.0, realism.range_noise_std_m, range_m.shape), measured)
    return measured, returned
