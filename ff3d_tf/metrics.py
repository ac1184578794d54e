"""Scene-flow metrics as a Keras metric that keeps sums and counts (adds up over batches and replicas).

`SceneFlowMetrics(moving_threshold_mps=schema.MOVING_THRESHOLD_MPS)`; `update_state(flow_true, flow_pred, class_id)`;
`result()` -> dict:
- "{cls}/{subset}/{stat}": cls in background, vehicle, pedestrian, sign, cyclist, all (= classes 0..4); subset in all,
  moving, stationary (moving: |flow_true| >= threshold); stat in mean_l2_mps, mean_l2_mph, frac_l2_le_0.1,
  frac_l2_le_1.0, count (paper Table 2).
- "{cls}/moving_precision", "{cls}/moving_recall": moving vs stationary classification of the prediction against the
  truth, both by the threshold (paper Table 4).
- "three_way/{fg_dynamic,fg_static,bg_static,mean}_epe_m": Argoverse 2 three-way EPE in metres per 0.1 s
  (foreground = classes 1..4, dynamic = |flow_true| >= threshold); mean over the non-empty three.
- "bucketed/{cls}/{static_epe_m,dynamic_norm_epe}" and "bucketed/mean_{static,dynamic}": bucketed normalized EPE
  (Khatri et al. 2024): speed buckets of 0.04 m per 0.1 s up to 2.0, plus [2.0, inf); static = mean EPE of the first
  bucket; dynamic = mean over the other non-empty buckets of (bucket mean EPE / bucket mean speed); NaN-mean over
  classes.
Class -1 points (and points outside `point_valid`) are ignored. An empty cell is NaN, never 0.

`max_distance_m`: None (default) counts every point, as the paper's tables do. The community's evaluator of the
three-way and bucketed EPE (Argoverse 2 scene flow challenge; published FastFlow3D results) counts only points with
max(|x|, |y|) < 35 m in the ego frame (`AV2_MAX_DISTANCE_M`); with `max_distance_m` set, `update_state` takes the t0
points as the keyword `points_xyz` [..., 3] (vehicle frame at t0, metres) and keeps only those.
"""
from __future__ import annotations

import keras
import numpy as np
import tensorflow as tf

from ff3d_tf import schema
from ff3d_tf.metrics_av2 import BUCKET_EDGES_M as _AV2_BUCKET_EDGES_M, MAX_DISTANCE_M, NUM_BUCKETS

CLASS_KEYS = tuple(schema.CLASS_NAMES[c] for c in sorted(schema.CLASS_NAMES))  # class id order 0..4
ALL_CLASS_KEYS = CLASS_KEYS + ("all",)
SUBSETS = ("all", "moving", "stationary")
MPS_TO_MPH = 2.2369362920544
SECONDS_PER_FRAME = 0.1  # AV2-style metrics are in metres per 0.1 s
# The Argoverse 2 evaluator's speed buckets (0, 0.04, ..., 2.0 m per frame, then [2.0, inf)) and crop.
BUCKET_EDGES_M = _AV2_BUCKET_EDGES_M[:-1]  # without the last edge, inf
AV2_MAX_DISTANCE_M = MAX_DISTANCE_M


class SceneFlowMetrics(keras.metrics.Metric):
    def __init__(self, moving_threshold_mps: float = schema.MOVING_THRESHOLD_MPS,
                 max_distance_m: float | None = None, name: str = "scene_flow_metrics", **kwargs):
        super().__init__(name=name, **kwargs)
        self.moving_threshold_mps = float(moving_threshold_mps)
        if max_distance_m is not None and not max_distance_m > 0:
            raise ValueError(f"max_distance_m must be > 0 or None, got {max_distance_m}")
        self.max_distance_m = None if max_distance_m is None else float(max_distance_m)

        def var(name, shape):
            return self.add_variable(shape=shape, initializer="zeros", dtype="float64", aggregation="sum",
                                     name=name)
        # [class 0..4, subset all/moving/stationary, stat]: sum_l2, count, count_le_0.1, count_le_1.0
        self.cells = var("cells", (5, 3, 4))
        # [class, (tp, pred_moving, true_moving)]
        self.moving_cls = var("moving_cls", (5, 3))
        # [class, bucket, (sum_epe_m, sum_speed_m, count)]
        self.buckets = var("buckets", (5, NUM_BUCKETS, 3))

    def update_state(self, flow_true, flow_pred, class_id, point_valid=None, sample_weight=None, points_xyz=None):
        if sample_weight is not None:
            raise ValueError("SceneFlowMetrics takes point_valid, not sample_weight")
        if self.max_distance_m is not None and points_xyz is None:
            raise ValueError(f"SceneFlowMetrics(max_distance_m={self.max_distance_m}) needs the t0 points: "
                             "update_state(..., points_xyz=[..., 3])")
        flow_true = tf.reshape(tf.cast(flow_true, tf.float64), [-1, 3])
        flow_pred = tf.reshape(tf.cast(flow_pred, tf.float64), [-1, 3])
        class_id = tf.reshape(tf.cast(class_id, tf.int32), [-1])
        keep = class_id >= 0
        if point_valid is not None:
            keep = tf.logical_and(keep, tf.reshape(tf.cast(point_valid, tf.bool), [-1]))
        if self.max_distance_m is not None:
            xy = tf.reshape(tf.cast(points_xyz, tf.float64), [-1, 3])[:, :2]
            keep = tf.logical_and(keep, tf.reduce_max(tf.abs(xy), -1) < self.max_distance_m)
        cls = tf.where(keep, tf.clip_by_value(class_id, 0, 4), 0)
        err = tf.norm(flow_pred - flow_true, axis=-1)
        speed_true = tf.norm(flow_true, axis=-1)
        speed_pred = tf.norm(flow_pred, axis=-1)
        moving = speed_true >= self.moving_threshold_mps
        # Sums per cell through segment ids (dropped points get id -1, which unsorted_segment_sum drops): no
        # [N, cells] one-hot arrays.
        moving_i = tf.cast(moving, tf.int32)
        stats = tf.stack([err, tf.ones_like(err), tf.cast(err <= 0.1, tf.float64), tf.cast(err <= 1.0, tf.float64)],
                         -1)  # [N, 4]
        by_motion = tf.reshape(tf.math.unsorted_segment_sum(stats, tf.where(keep, cls * 2 + moving_i, -1), 10),
                               [5, 2, 4])  # [class, (stationary, moving), stat]
        self.cells.assign_add(tf.stack([by_motion[:, 0] + by_motion[:, 1], by_motion[:, 1], by_motion[:, 0]], 1))
        pred_moving = tf.cast(speed_pred >= self.moving_threshold_mps, tf.float64)
        true_moving = tf.cast(moving, tf.float64)
        self.moving_cls.assign_add(tf.math.unsorted_segment_sum(
            tf.stack([pred_moving * true_moving, pred_moving, true_moving], -1), tf.where(keep, cls, -1), 5))
        speed_m = speed_true * SECONDS_PER_FRAME
        bucket = tf.clip_by_value(tf.searchsorted(tf.constant(BUCKET_EDGES_M[1:]), speed_m[None, :],
                                                  side="right")[0], 0, NUM_BUCKETS - 1)
        vals = tf.stack([err * SECONDS_PER_FRAME, speed_m, tf.ones_like(err)], -1)
        self.buckets.assign_add(tf.reshape(tf.math.unsorted_segment_sum(
            vals, tf.where(keep, cls * NUM_BUCKETS + bucket, -1), 5 * NUM_BUCKETS), [5, NUM_BUCKETS, 3]))

    def reset_state(self):
        for v in (self.cells, self.moving_cls, self.buckets):
            v.assign(tf.zeros_like(v))

    def result(self) -> dict[str, float]:
        return compute_results(np.asarray(self.cells.numpy()), np.asarray(self.moving_cls.numpy()),
                               np.asarray(self.buckets.numpy()))

    def get_config(self):
        return {"name": self.name, "moving_threshold_mps": self.moving_threshold_mps,
                "max_distance_m": self.max_distance_m}


def _div(a, b):
    return float(a / b) if b > 0 else float("nan")


def _nanmean(values):
    values = [v for v in values if not np.isnan(v)]
    return float(np.mean(values)) if values else float("nan")


def compute_results(cells: np.ndarray, moving_cls: np.ndarray, buckets: np.ndarray) -> dict[str, float]:
    """The result dict from the accumulated sums (see the module docstring)."""
    out: dict[str, float] = {}
    all_cells = np.concatenate([cells, cells.sum(0, keepdims=True)], 0)
    all_moving = np.concatenate([moving_cls, moving_cls.sum(0, keepdims=True)], 0)
    for ci, cname in enumerate(ALL_CLASS_KEYS):
        for si, sname in enumerate(SUBSETS):
            s, n, le01, le1 = all_cells[ci, si]
            key = f"{cname}/{sname}/"
            out[key + "mean_l2_mps"] = _div(s, n)
            out[key + "mean_l2_mph"] = _div(s, n) * MPS_TO_MPH
            out[key + "frac_l2_le_0.1"] = _div(le01, n)
            out[key + "frac_l2_le_1.0"] = _div(le1, n)
            out[key + "count"] = float(n)
        tp, pred_m, true_m = all_moving[ci]
        out[f"{cname}/moving_precision"] = _div(tp, pred_m)
        out[f"{cname}/moving_recall"] = _div(tp, true_m)
    fg = cells[1:].sum(0)  # [subset, stat]
    bg = cells[0]
    fg_dyn = _div(fg[1, 0], fg[1, 1]) * SECONDS_PER_FRAME
    fg_sta = _div(fg[2, 0], fg[2, 1]) * SECONDS_PER_FRAME
    bg_sta = _div(bg[2, 0], bg[2, 1]) * SECONDS_PER_FRAME
    out["three_way/fg_dynamic_epe_m"] = fg_dyn
    out["three_way/fg_static_epe_m"] = fg_sta
    out["three_way/bg_static_epe_m"] = bg_sta
    out["three_way/mean_epe_m"] = _nanmean([fg_dyn, fg_sta, bg_sta])
    statics, dynamics = [], []
    for ci, cname in enumerate(CLASS_KEYS):
        b = buckets[ci]
        static = _div(b[0, 0], b[0, 2])
        ratios = [(b[k, 0] / b[k, 2]) / (b[k, 1] / b[k, 2]) for k in range(1, NUM_BUCKETS)
                  if b[k, 2] > 0 and b[k, 1] > 0]
        dynamic = float(np.mean(ratios)) if ratios else float("nan")
        out[f"bucketed/{cname}/static_epe_m"] = static
        out[f"bucketed/{cname}/dynamic_norm_epe"] = dynamic
        statics.append(static)
        dynamics.append(dynamic)
    out["bucketed/mean_static"] = _nanmean(statics)
    out["bucketed/mean_dynamic"] = _nanmean(dynamics)
    return out


def format_paper_table(result: dict[str, float], title: str = "") -> str:
    """The paper's Table 2 layout (vehicle / pedestrian / cyclist x all / moving / stationary, and background)."""
    cols = [(c, s) for c in schema.PAPER_TABLE_CLASSES for s in SUBSETS] + [("background", "all")]
    head1 = f"{'':<14}" + "".join(f"{c[:10]:>11}" for c, _ in cols)
    head2 = f"{'error metric':<14}" + "".join(f"{s[:10]:>11}" for _, s in cols)
    rows = []
    for label, stat, pct in (("mean (m/s)", "mean_l2_mps", False), ("mean (mph)", "mean_l2_mph", False),
                             ("<= 0.1 m/s", "frac_l2_le_0.1", True), ("<= 1.0 m/s", "frac_l2_le_1.0", True)):
        cells = []
        for c, s in cols:
            v = result[f"{c}/{s}/{stat}"]
            cells.append(f"{'nan':>11}" if np.isnan(v) else (f"{100 * v:>10.1f}%" if pct else f"{v:>11.2f}"))
        rows.append(f"{label:<14}" + "".join(cells))
    counts = f"{'points':<14}" + "".join(f"{int(result[f'{c}/{s}/count']):>11d}" for c, s in cols)
    return "\n".join(([title] if title else []) + [head1, head2] + rows + [counts])


CROP_PREFIX = f"within_{AV2_MAX_DISTANCE_M:g}m/"  # result keys of the cropped three-way and bucketed EPE


def published_epe_keys(result: dict[str, float]) -> dict[str, float]:
    """The three-way and bucketed EPE entries of a result (what is reported again under `CROP_PREFIX`)."""
    return {k: v for k, v in result.items() if k.startswith(("three_way/", "bucketed/"))}


def format_extra_tables(result: dict[str, float]) -> str:
    """Moving classification; three-way and bucketed EPE over all points and, when present, within the 35 m crop."""
    lines = [f"{'moving classification':<22}{'precision':>10}{'recall':>10}"]
    for c in schema.PAPER_TABLE_CLASSES + ("background", "all"):
        p, r = result[f"{c}/moving_precision"], result[f"{c}/moving_recall"]
        lines.append(f"{c:<22}{p:>10.3f}{r:>10.3f}")
    for label, prefix in (("all points", ""), (f"max(|x|, |y|) < {AV2_MAX_DISTANCE_M:g} m, as the AV2 evaluator",
                                               CROP_PREFIX)):
        if prefix + "three_way/mean_epe_m" not in result:
            continue
        r = {k[len(prefix):]: v for k, v in result.items() if k.startswith(prefix)}
        lines.append(f"three-way EPE (m per 0.1 s), {label}: " + ", ".join(
            f"{k} {r[f'three_way/{k}_epe_m']:.4f}" for k in ("fg_dynamic", "fg_static", "bg_static", "mean")))
        lines.append(f"bucketed normalized EPE, {label}: " + ", ".join(
            f"{c} static {r[f'bucketed/{c}/static_epe_m']:.4f} dynamic {r[f'bucketed/{c}/dynamic_norm_epe']:.3f}"
            for c in CLASS_KEYS) + f"; mean static {r['bucketed/mean_static']:.4f} dynamic "
            f"{r['bucketed/mean_dynamic']:.3f}")
    return "\n".join(lines)
