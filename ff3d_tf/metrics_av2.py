"""The Argoverse 2 scene-flow challenge protocol (2024 leaderboard) in NumPy: categories, meta-classes, the eval mask,
a streaming accumulator of the three-way EPE and the bucketed normalized EPE, and the challenge's text table.

Units and frames. Everything here is in metres per frame: the displacement of a sweep-0 point over the sweep pair
(AV2 sweeps are ~0.1 s apart; the leaderboard does not divide by the pair's time), with the ego motion removed (a
static point has flow 0), in the sweep-0 ego frame (any frame works as long as truth and prediction share it: only
norms are used). A model's m/s flow becomes metres per frame as flow_mps * (t1_ns - t0_ns) * 1e-9. The submission
format's flow, which includes the ego motion, is converted by `ff3d_tf.data.av2.av2_submission`.

Category index ("label index" below): the `classes` column of Argoverse's flow labels, av2-api's CATEGORY_TO_INDEX:
0 = NONE (the point is in no cuboid: background), i + 1 = `AV2_CATEGORIES[i]`. (The community evaluator's own label
files number the same categories from 0 with -1 = background, bucketed_scene_flow_eval/datasets/argoverse2/
argoverse_scene_flow.py @ed2e18be7b06cfb1a6e01e9cde69d9f749fa1aec: add 1 to get this index.)

Protocol (the arithmetic of kylevedder/BucketedSceneFlowEval, the leaderboard's evaluator, rewritten here):
- Points: those of the eval mask (`eval_mask`: not ground, max(|x|, |y|) < 35 m), each counted once.
- Dynamic: |flow_true| >= 0.05 m (`DYNAMIC_THRESHOLD_M`; av2-api labels `is_dynamic` the same way).
- Three-way EPE: mean EPE of foreground dynamic, foreground static, background static points (foreground = the four
  object meta-classes; background = label 0); "mean" is their plain average (NaN if one is empty, as av2-api's
  "EPE 3-Way Average"). Background dynamic points (none in human labels) are reported but not averaged.
- Bucketed normalized EPE: speed buckets [e_k, e_k+1) of |flow_true| with edges linspace(0, 2, 51) m and a last
  bucket [2, inf) (51 buckets). Per meta-class: static EPE = mean EPE of bucket 0 (< 0.04 m); dynamic normalized EPE =
  mean over the non-empty buckets 1..50 of (mean EPE in the bucket / mean |flow_true| in the bucket); the leaderboard's
  means are the NaN-skipping means of these over the five meta-classes (BACKGROUND included). A meta-class with no
  points is NaN, never 0. The evaluator averages per sweep and then weights sweeps by their point counts, and merges
  categories into meta-classes weighted by counts: both equal the pooled sums kept here (`AV2FlowAccumulator`).
- Categories outside the meta-classes (road signs and sign trailers, "ignored because of labelling oddities", and
  ANIMAL, DOG) count in neither table. av2-api's own 2023 evaluator instead counts every category as foreground.

What the community evaluator does around this arithmetic, and this module leaves to the caller: its loader zeroes
the pair's frame at the second sweep, so its 35 m box is measured on the sweep-0 points moved into the sweep-1 ego
frame (pass those points to `eval_mask` to select the same points; on the sample log 36 of ~74k points differ), and it
also keeps only points with -48 < x, y < 48 and -2.5 < z < 2.5 m in that frame (`z_range_m=COMMUNITY_Z_RANGE_M`; on the
sample log this drops 22k building points above 2.5 m). Its ground test is its own (map raster, 0.4 m); the sample
log's `is_ground_0` is av2-api's.

Sources (read for the arithmetic; facts and numbers cited, no code copied):
- argoverse/av2-api src/av2/datasets/sensor/constants.py @4ba9cbe38ce5a9ce1b4a376f78d4eb4b65246952 (the 30 categories)
- argoverse/av2-api src/av2/evaluation/scene_flow/constants.py @4f91795fec1f73634f1c806c29faf525f40b9b38
  (CATEGORY_TO_INDEX, SCENE_FLOW_DYNAMIC_THRESHOLD = 0.05), .../eval.py @8a211b92311f4e9c06c11b562f5bf5f704af72fb
  (three-way average), .../utils.py @8a211b92311f4e9c06c11b562f5bf5f704af72fb (eval mask files: |x|, |y| <= 50 m and not
  ground), .../make_annotation_files.py @02b1962a7a6f15ad2c23b9bffe4279142fcce270 (is_close: |x|, |y| <= 35 m),
  src/av2/torch/structures/flow.py @01e6d9585ab28f701f149b8f66f1ab55a0551486 (is_dynamic: >= 0.05 m)
- kylevedder/BucketedSceneFlowEval bucketed_scene_flow_eval/eval/bucketed_epe.py
  @a86047def636b9a1a01e20377920721607826805 (edges linspace(0, 2.0, 51) + inf; static = bucket 0; dynamic = nanmean of
  bucket EPE / bucket speed; means over meta-classes), .../eval/threeway_epe.py
  @a86047def636b9a1a01e20377920721607826805 (buckets [0, 0.05), [0.05, inf)), .../eval/base_per_frame_sceneflow_eval.py
  @b889b1ed9f19c60c39abaa71bd16e492813a57bd (lo <= speed < hi; max(|x|, |y|) < 35; count-weighted means),
  .../datasets/argoverse2/av2_metacategories.py @1ce36b5d416730b66f79c12f4e31ec7b8f707d14 (meta-classes),
  .../datasets/argoverse2/dataset.py @f1f09ee28433f28ded71f91f14d9df57f1bc6c53 and argoverse_raw_data.py
  @f1f09ee28433f28ded71f91f14d9df57f1bc6c53 (frame zeroed at the target sweep; point range; ground 0.4 m)
"""
from __future__ import annotations

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data.av2.argoverse2 import ANNOTATION_CATEGORIES, AV2_CLASS, SCENE_FLOW_DYNAMIC_THRESHOLD_M

# The Argoverse 2 sensor-dataset annotation categories, in av2-api's AnnotationCategories order (alphabetical); the
# reader holds the list (`ff3d_tf.data.av2.argoverse2.ANNOTATION_CATEGORIES`).
AV2_CATEGORIES = ANNOTATION_CATEGORIES
LABEL_NONE = 0  # label index of a point in no cuboid
LABEL_NAMES = ("NONE",) + AV2_CATEGORIES  # label index -> name
NUM_LABELS = len(LABEL_NAMES)  # 31

# The challenge's meta-classes, in the evaluator's (sorted) order, and the categories each merges.
META_CLASS_CATEGORIES = {
    "BACKGROUND": ("NONE",),
    "CAR": ("REGULAR_VEHICLE",),
    "OTHER_VEHICLES": ("BOX_TRUCK", "LARGE_VEHICLE", "RAILED_VEHICLE", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER",
                       "ARTICULATED_BUS", "BUS", "SCHOOL_BUS"),
    "PEDESTRIAN": ("PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"),
    "WHEELED_VRU": ("BICYCLE", "BICYCLIST", "MOTORCYCLE", "MOTORCYCLIST", "WHEELED_DEVICE", "WHEELED_RIDER"),
}
META_CLASSES = tuple(META_CLASS_CATEGORIES)
FOREGROUND_META_CLASSES = ("CAR", "OTHER_VEHICLES", "PEDESTRIAN", "WHEELED_VRU")  # the three-way EPE's foreground
# Categories in no meta-class: the evaluator's road signs (labelling oddities such as the stop sign on a school bus)
# and the two animal categories, which its meta-class lists leave out.
IGNORED_CATEGORIES = tuple(c for c in AV2_CATEGORIES if not any(c in v for v in META_CLASS_CATEGORIES.values()))

_META_INDEX = {name: META_CLASSES.index(m) for m, names in META_CLASS_CATEGORIES.items() for name in names}
META_OF_LABEL = np.array([_META_INDEX.get(n, -1) for n in LABEL_NAMES], np.int64)  # label -> meta-class, -1 ignored
# label -> paper class (`schema` class ids), through the project's one AV2 -> paper mapping `AV2_CLASS`.
PAPER_CLASS_OF_LABEL = np.array([AV2_CLASS.get(n, schema.CLASS_BACKGROUND) for n in LABEL_NAMES], np.int32)

MAX_DISTANCE_M = 35.0  # eval mask: max(|x|, |y|) < 35 m
COMMUNITY_Z_RANGE_M = (-2.5, 2.5)  # the community loader's z range (exclusive), metres, in its frame
DYNAMIC_THRESHOLD_M = SCENE_FLOW_DYNAMIC_THRESHOLD_M  # 0.05 m per frame = schema.MOVING_THRESHOLD_MPS x 0.1 s
BUCKET_EDGES_M = np.concatenate([np.linspace(0.0, 2.0, 51), [np.inf]])  # 52 edges: 0, 0.04, ..., 2.0, inf
NUM_BUCKETS = len(BUCKET_EDGES_M) - 1  # 51; bucket 0 = static (< 0.04 m)


def label_index(category_names) -> np.ndarray:
    """Label indices (int64) of category names; "NONE" (or "") is 0. Unknown names raise, naming the first."""
    names = np.asarray(category_names).astype(str)
    lookup = {n: i for i, n in enumerate(LABEL_NAMES)}
    lookup[""] = LABEL_NONE
    bad = [str(n) for n in np.unique(names) if n not in lookup]
    if bad:
        raise ValueError(f"category_names: {bad[0]!r} is not an Argoverse 2 category (see AV2_CATEGORIES)")
    return np.array([lookup[n] for n in names.ravel()], np.int64).reshape(names.shape)


def speed_bucket(speed_m) -> np.ndarray:
    """Bucket index 0..50 of each |flow| (metres per frame, finite, >= 0): bucket k holds e_k <= speed < e_k+1."""
    return np.searchsorted(BUCKET_EDGES_M, np.asarray(speed_m, np.float64), side="right") - 1


def is_dynamic(flow_m) -> np.ndarray:
    """[N] bool: |flow| >= 0.05 m per frame (ego motion removed), for ground truth and predictions alike."""
    return np.linalg.norm(np.asarray(flow_m, np.float64), axis=-1) >= DYNAMIC_THRESHOLD_M


def _finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        row = int(np.argmin(np.isfinite(a).reshape(len(a), -1).all(1)))
        raise ValueError(f"{name}: non-finite value at row {row}")


def eval_mask(points_xyz, is_ground, max_distance_m: float = MAX_DISTANCE_M,
              z_range_m: tuple[float, float] | None = None) -> np.ndarray:
    """[N] bool: the points the challenge evaluates: not ground and max(|x|, |y|) < max_distance_m (and, with
    `z_range_m=(lo, hi)`, lo < z < hi). `points_xyz` [N,3] metres in the frame the box is meant in (see module doc)."""
    p = np.asarray(points_xyz, np.float64)
    g = np.asarray(is_ground)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points_xyz: shape {p.shape}, expected [N, 3]")
    if g.shape != (len(p),) or g.dtype != bool:
        raise ValueError(f"is_ground: shape {g.shape} dtype {g.dtype}, expected bool [{len(p)}]")
    _finite("points_xyz", p)
    keep = ~g & (np.max(np.abs(p[:, :2]), axis=1) < max_distance_m)
    if z_range_m is not None:
        keep &= (p[:, 2] > z_range_m[0]) & (p[:, 2] < z_range_m[1])
    return keep


def _ratio(num, den):
    """num / den elementwise, NaN where den == 0 (no warnings)."""
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    out = np.full(np.broadcast(num, den).shape, np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return out


def _nanmean(values, axis=None):
    """Mean of the non-NaN values (NaN where there are none), without RuntimeWarnings."""
    v = np.asarray(values, np.float64)
    ok = ~np.isnan(v)
    return _ratio(np.where(ok, v, 0.0).sum(axis), ok.sum(axis))


class AV2FlowAccumulator:
    """Streams the challenge metrics over many sweeps: sums per (label index, speed bucket) and per (label index,
    static/dynamic), never per-point lists. `update` once per sweep, `merge` shards, `result()` at the end;
    `state()` / `from_state()` save and resume a long evaluation."""

    def __init__(self):
        self.bucket_sums = np.zeros((NUM_LABELS, NUM_BUCKETS, 3))  # sum EPE (m), sum |flow_true| (m), count
        self.motion_sums = np.zeros((NUM_LABELS, 2, 2))  # [label, static/dynamic, (sum EPE (m), count)]
        self.num_sweeps = 0

    def update(self, flow_true_m, flow_pred_m, label_idx, mask=None) -> int:
        """Add one sweep: flow_true_m, flow_pred_m [N,3] (metres per frame, ego motion removed, same frame),
        label_idx [N] label indices 0..30, mask [N] bool (e.g. `eval_mask`, and av2-api's is_valid) or None = all.
        Returns the number of points counted."""
        ft = np.asarray(flow_true_m, np.float64)
        fp = np.asarray(flow_pred_m, np.float64)
        lab = np.asarray(label_idx)
        if ft.ndim != 2 or ft.shape[1] != 3:
            raise ValueError(f"flow_true_m: shape {ft.shape}, expected [N, 3]")
        if fp.shape != ft.shape:
            raise ValueError(f"flow_pred_m: shape {fp.shape}, expected {ft.shape} like flow_true_m")
        if lab.shape != (len(ft),) or not np.issubdtype(lab.dtype, np.integer):
            raise ValueError(f"label_idx: shape {lab.shape} dtype {lab.dtype}, expected integer [{len(ft)}]")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (len(ft),) or mask.dtype != bool:
                raise ValueError(f"mask: shape {mask.shape} dtype {mask.dtype}, expected bool [{len(ft)}]")
            ft, fp, lab = ft[mask], fp[mask], lab[mask]
        lab = lab.astype(np.int64)
        if lab.size and (lab.min() < 0 or lab.max() >= NUM_LABELS):
            row = int(np.argmax((lab < 0) | (lab >= NUM_LABELS)))
            raise ValueError(f"label_idx: {lab[row]} at (masked) row {row} is not a label index 0..{NUM_LABELS - 1}")
        _finite("flow_true_m", ft)
        _finite("flow_pred_m", fp)
        speed = np.linalg.norm(ft, axis=1)
        err = np.linalg.norm(fp - ft, axis=1)
        cell = lab * NUM_BUCKETS + speed_bucket(speed)
        size = NUM_LABELS * NUM_BUCKETS
        for k, w in enumerate((err, speed, None)):
            self.bucket_sums[..., k] += np.bincount(cell, weights=w, minlength=size).reshape(NUM_LABELS, NUM_BUCKETS)
        cell = lab * 2 + (speed >= DYNAMIC_THRESHOLD_M)
        for k, w in enumerate((err, None)):
            self.motion_sums[..., k] += np.bincount(cell, weights=w, minlength=NUM_LABELS * 2).reshape(NUM_LABELS, 2)
        self.num_sweeps += 1
        return int(len(err))

    def merge(self, other: "AV2FlowAccumulator") -> "AV2FlowAccumulator":
        """Add another accumulator's sums (shards of one evaluation); returns self."""
        self.bucket_sums += other.bucket_sums
        self.motion_sums += other.motion_sums
        self.num_sweeps += other.num_sweeps
        return self

    def state(self) -> dict[str, np.ndarray]:
        return {"bucket_sums": self.bucket_sums.copy(), "motion_sums": self.motion_sums.copy(),
                "num_sweeps": np.array(self.num_sweeps, np.int64)}

    @classmethod
    def from_state(cls, state) -> "AV2FlowAccumulator":
        acc = cls()
        for key, like in (("bucket_sums", acc.bucket_sums), ("motion_sums", acc.motion_sums)):
            a = np.asarray(state[key], np.float64)
            if a.shape != like.shape or not np.all(np.isfinite(a)) or np.any(a < 0):
                raise ValueError(f"state[{key!r}]: shape {a.shape}, expected {like.shape} of finite sums >= 0")
            like[...] = a
        acc.num_sweeps = int(state["num_sweeps"])
        return acc

    def meta_bucket_sums(self) -> np.ndarray:
        """[meta-class, bucket, (sum EPE, sum |flow_true|, count)] in `META_CLASSES` order (ignored labels left out)."""
        out = np.zeros((len(META_CLASSES), NUM_BUCKETS, 3))
        np.add.at(out, META_OF_LABEL[META_OF_LABEL >= 0], self.bucket_sums[META_OF_LABEL >= 0])
        return out

    def bucket_matrix(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean EPE, mean |flow_true|, count), each [meta-class, bucket]; NaN where a bucket is empty."""
        s = self.meta_bucket_sums()
        return _ratio(s[..., 0], s[..., 2]), _ratio(s[..., 1], s[..., 2]), s[..., 2]

    def result(self) -> dict[str, float]:
        """three_way/{fg_dynamic,fg_static,bg_static,bg_dynamic,mean}_epe_m and .../{...}_count;
        bucketed/{META}/{static_epe_m,dynamic_norm_epe,static_count,dynamic_count};
        bucketed/mean_static_epe_m, bucketed/mean_dynamic_norm_epe; num_points, num_sweeps."""
        out: dict[str, float] = {}
        fg_labels = np.isin(META_OF_LABEL, [META_CLASSES.index(m) for m in FOREGROUND_META_CLASSES])
        fg = self.motion_sums[fg_labels].sum(0)  # [static/dynamic, (sum EPE, count)]
        bg = self.motion_sums[LABEL_NONE]
        cells = {"fg_dynamic": fg[1], "fg_static": fg[0], "bg_static": bg[0], "bg_dynamic": bg[1]}
        for name, (s, n) in cells.items():
            out[f"three_way/{name}_epe_m"] = float(_ratio(s, n))
            out[f"three_way/{name}_count"] = float(n)
        out["three_way/mean_epe_m"] = float(np.mean([out[f"three_way/{k}_epe_m"]
                                                     for k in ("fg_dynamic", "fg_static", "bg_static")]))
        mean_epe, mean_speed, count = self.bucket_matrix()
        static = mean_epe[:, 0]
        dynamic = _nanmean(_ratio(mean_epe[:, 1:], mean_speed[:, 1:]), axis=1)
        for i, meta in enumerate(META_CLASSES):
            out[f"bucketed/{meta}/static_epe_m"] = float(static[i])
            out[f"bucketed/{meta}/dynamic_norm_epe"] = float(dynamic[i])
            out[f"bucketed/{meta}/static_count"] = float(count[i, 0])
            out[f"bucketed/{meta}/dynamic_count"] = float(count[i, 1:].sum())
        out["bucketed/mean_static_epe_m"] = float(_nanmean(static))
        out["bucketed/mean_dynamic_norm_epe"] = float(_nanmean(dynamic))
        out["num_points"] = float(self.bucket_sums[..., 2].sum())
        out["num_sweeps"] = float(self.num_sweeps)
        return out


def _cell(v: float, width: int, digits: int = 4) -> str:
    return f"{'-':>{width}}" if np.isnan(v) else f"{v:>{width}.{digits}f}"


def format_challenge_table(result: dict[str, float], title: str = "") -> str:
    """The challenge's numbers as text (m per frame, "-" = no points): three-way EPE, then the bucketed normalized
    EPE per meta-class and the leaderboard's means."""
    r = result
    lines = [title] if title else []
    lines.append(f"Argoverse 2 scene flow (2024 protocol), metres per frame (sweep pair, ~0.1 s), "
                 f"{int(r['num_points'])} points of {int(r['num_sweeps'])} sweeps")
    cols = ("fg_dynamic", "fg_static", "bg_static")
    lines.append(f"{'three-way EPE':<24}" + "".join(f"{c.replace('_', ' '):>12}" for c in cols) + f"{'mean':>12}")
    lines.append(f"{'EPE (m)':<24}" + "".join(_cell(r[f"three_way/{c}_epe_m"], 12) for c in cols)
                 + _cell(r["three_way/mean_epe_m"], 12))
    lines.append(f"{'points':<24}" + "".join(f"{int(r[f'three_way/{c}_count']):>12d}" for c in cols))
    lines.append(f"{'bucketed normalized EPE':<24}{'static EPE (m)':>16}{'dynamic norm.':>16}{'static pts':>12}"
                 f"{'dynamic pts':>12}")
    for meta in META_CLASSES:
        lines.append(f"{meta:<24}" + _cell(r[f"bucketed/{meta}/static_epe_m"], 16)
                     + _cell(r[f"bucketed/{meta}/dynamic_norm_epe"], 16)
                     + f"{int(r[f'bucketed/{meta}/static_count']):>12d}{int(r[f'bucketed/{meta}/dynamic_count']):>12d}")
    lines.append(f"{'mean (leaderboard)':<24}" + _cell(r["bucketed/mean_static_epe_m"], 16)
                 + _cell(r["bucketed/mean_dynamic_norm_epe"], 16))
    return "\n".join(lines)


def category_mapping_table() -> str:
    """Markdown: each AV2 label index and category, its challenge meta-class (bucketed EPE), its three-way group and
    its paper class (the project's `AV2_CLASS`)."""
    rows = ["| index | AV2 category | challenge meta-class | three-way | paper class |", "|---|---|---|---|---|"]
    for i, name in enumerate(LABEL_NAMES):
        meta = META_CLASSES[META_OF_LABEL[i]] if META_OF_LABEL[i] >= 0 else "(ignored)"
        three = ("background" if meta == "BACKGROUND" else "foreground" if meta in FOREGROUND_META_CLASSES
                 else "(ignored)")
        rows.append(f"| {i} | {name} | {meta} | {three} | {schema.CLASS_NAMES[int(PAPER_CLASS_OF_LABEL[i])]} |")
    return "\n".join(rows)
