"""The paper's studies: which model variants each one trains, what it reports, and its table and plot.

Every variant is a set of config changes applied to the same base config. `train_changes` hold while training only
(the evaluation sees the original labels: class ablation, data size); `input_changes` hold for training and
evaluation alike (they change what the model sees: point density, ground removal, ego motion). `tools/run_study.py`
trains and evaluates each variant and calls `write_report`.

| study | paper | variants |
|---|---|---|
| data_size | Fig. 3, Sec. 5.2 (segments subsampled, not frames) | share of training segments |
| point_density | Fig. 4 | share of points kept per frame |
| ground_removal | Sec. 5.2 (+159% moving, +31% stationary mean L2) | points below z = 0.2 m dropped |
| class_ablation | Table 4 | pedestrian / cyclist labels made stationary or ignored |
| ego_motion | appendix Table 6 | t-1 cloud left in its own frame |
"""
from __future__ import annotations

import dataclasses
import json
import math
import os

from ff3d_tf import schema

CLASSES = schema.PAPER_TABLE_CLASSES
TABLE4_CLASSES = ("cyclist", "pedestrian")  # the classes whose labels paper Table 4 withholds, in its row order
GROUND_REMOVAL_Z_M = 0.2  # paper Sec. 5.2: "a crude threshold of 0.2 m above ground"


@dataclasses.dataclass(frozen=True)
class Variant:
    name: str
    x: float | None = None  # position on the study's numeric axis (None: categorical study)
    train_changes: dict = dataclasses.field(default_factory=dict)
    input_changes: dict = dataclasses.field(default_factory=dict)

    def training_changes(self) -> dict:
        return {**self.train_changes, **self.input_changes}


@dataclasses.dataclass(frozen=True)
class Study:
    name: str
    title: str
    x_label: str | None  # numeric studies: the axis; categorical: None
    columns: tuple[str, ...]  # metric keys of the report table
    default_values: tuple[float, ...] = ()


_ACCURACY = tuple(f"{c}/moving/frac_l2_le_{t}" for t in ("0.1", "1.0") for c in CLASSES)
_MEAN_L2 = tuple(f"{c}/{m}/mean_l2_mps" for c in CLASSES for m in ("moving", "stationary")) + \
    ("background/all/mean_l2_mps",)

STUDIES = {s.name: s for s in (
    Study("data_size", "Accuracy vs amount of training data (segments)", "share of training segments",
          _ACCURACY + ("all/moving/mean_l2_mps",), (0.1, 0.25, 0.5, 1.0)),
    Study("point_density", "Accuracy vs point density (training and evaluation)", "share of points kept",
          _ACCURACY + ("all/moving/mean_l2_mps",), (0.1, 0.25, 0.5, 1.0)),
    Study("ground_removal", f"Ground removal (points below {GROUND_REMOVAL_Z_M} m dropped in training and evaluation)",
          None,
          ("all/moving/mean_l2_mps", "all/stationary/mean_l2_mps") + _MEAN_L2),
    Study("class_ablation", "Generalisation to unlabelled moving objects (paper Table 4)", None,
          tuple(f"{c}/{k}" for c in TABLE4_CLASSES for k in (
              "all/mean_l2_mps", "moving/mean_l2_mps", "stationary/mean_l2_mps", "moving_precision",
              "moving_recall"))),
    Study("ego_motion", "Ego-motion compensation of the input (paper appendix)", None, _MEAN_L2),
)}


def variants(study: str, num_train_segments: int, values: tuple[float, ...] = ()) -> list[Variant]:
    """The variants of a study; `values` replaces the default shares of the numeric studies."""
    if study not in STUDIES:
        raise ValueError(f"unknown study {study!r}; one of {sorted(STUDIES)}")
    values = tuple(values) or STUDIES[study].default_values
    if values and any(not 0.0 < v <= 1.0 for v in values):
        raise ValueError(f"study {study}: shares must be in (0, 1], got {values}")
    if study == "data_size":
        out, seen = [], set()
        for v in sorted(values):
            n = max(1, math.ceil(v * num_train_segments - 1e-9))
            if n not in seen:  # several shares can round to the same number of segments
                seen.add(n)
                out.append(Variant(f"segments_{n}", n / num_train_segments, {"data.max_training_segments": n}))
        return out
    if study == "point_density":
        return [Variant(f"points_{v:g}", v, input_changes={"data.point_keep_fraction": v}) for v in sorted(values)]
    if study == "ground_removal":
        return [Variant("with_ground"),
                Variant("ground_removed", input_changes={"data.remove_ground_below_z_m": GROUND_REMOVAL_Z_M})]
    if study == "class_ablation":
        return [Variant("supervised")] + [Variant(f"{c}_{m}", train_changes={"data.class_ablation": f"{c}_{m}"})
                                          for c in TABLE4_CLASSES for m in ("stationary", "ignored")]
    return [Variant("ego_compensated"), Variant("not_compensated",
                                                input_changes={"data.ego_motion_compensation": False})]


def _fmt(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def markdown_table(study: str, rows: list[dict]) -> str:
    """rows: {"variant", "metrics"}; the first row is the reference of the relative change column."""
    cols = STUDIES[study].columns
    lines = ["| variant | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for r in rows:
        lines.append(f"| {r['variant']} | " + " | ".join(_fmt(r["metrics"].get(c)) for c in cols) + " |")
    if study in ("ground_removal", "ego_motion") and len(rows) == 2:
        base, other = rows[0]["metrics"], rows[1]["metrics"]
        change = []
        for c in cols:
            a, b = base.get(c), other.get(c)
            change.append("n/a" if not a or a != a or b is None or b != b else f"{(b - a) / a * 100:+.0f}%")
        lines.append(f"| change vs {rows[0]['variant']} | " + " | ".join(change) + " |")
    return "\n".join(lines)


def plot(study: str, rows: list[dict], path: str) -> str:
    """Numeric studies: moving-point accuracy within 0.1 and 1.0 m/s per class vs the share (the paper's Figs. 3
    and 4). Categorical studies: grouped bars of the mean L2 columns per variant."""
    from ff3d_tf import viz

    spec = STUDIES[study]
    if spec.x_label is not None:
        xs = [r["x"] for r in rows]
        panels = {f"moving points with L2 <= {t} m/s": {
            c: (xs, [r["metrics"].get(f"{c}/moving/frac_l2_le_{t}", float("nan")) for r in rows]) for c in CLASSES}
            for t in ("0.1", "1.0")}
        return viz.lines_png(path, panels, spec.x_label, spec.title)
    cols = [c for c in spec.columns if c.endswith("mean_l2_mps")]
    series = {r["variant"]: [r["metrics"].get(c, float("nan")) for c in cols] for r in rows}
    return viz.grouped_bars_png(path, [c.replace("/mean_l2_mps", "") for c in cols], series, "mean L2 error (m/s)",
                                spec.title)


def write_report(study: str, rows: list[dict], out_dir: str) -> dict:
    """study.json (every metric of every variant), study.md (the table) and study.png under out_dir."""
    os.makedirs(out_dir, exist_ok=True)
    paths = {"json": os.path.join(out_dir, f"{study}.json"), "markdown": os.path.join(out_dir, f"{study}.md"),
             "png": os.path.join(out_dir, f"{study}.png")}
    with open(paths["json"], "w") as f:
        json.dump({"study": study, "title": STUDIES[study].title, "variants": rows}, f, indent=1, sort_keys=True)
    table = markdown_table(study, rows)
    with open(paths["markdown"], "w") as f:
        f.write(f"# {STUDIES[study].title}\n\n{table}\n")
    plot(study, rows, paths["png"])
    return paths
