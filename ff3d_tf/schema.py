"""Every data schema of the project, declared once. The reader, the synthetic writer, the model and the tests import it.

Decoded frame (`ff3d_tf.data.wod.waymo.decode_frame`; one WOD `Frame`, N points of the selected lidars and returns):

| key              | dtype   | shape  | frame / unit                                                            |
|------------------|---------|--------|-------------------------------------------------------------------------|
| points_xyz       | float32 | [N,3]  | vehicle frame at the frame timestamp, metres                            |
| intensity        | float32 | [N]    | WOD range image channel "intensity" (`RANGE_CHANNELS`)                  |
| elongation       | float32 | [N]    | WOD range image channel "elongation"                                    |
| flow_mps         | float32 | [N,3]  | vx, vy, vz in the vehicle frame of this frame, m/s, t-1 -> t0, ego-free  |
| class_id         | int32   | [N]    | -1 no label, 0 background, 1 vehicle, 2 pedestrian, 3 sign, 4 cyclist   |
| laser_name       | int32   | [N]    | 1 TOP, 2 FRONT, 3 SIDE_LEFT, 4 SIDE_RIGHT, 5 REAR                       |
| pose             | float64 | [4,4]  | vehicle -> world                                                        |
| timestamp_micros | int64   | []     | microseconds                                                            |

Points are ordered by ascending laser name, then return, then row-major pixel order (the official conversion's order).

Model input example (`ff3d_tf.data.pairs`; one pair t-1 -> t0, N0 / N1 points): the per-point keys of `POINT_KEYS`
(dtype, per-point shape, whose points, frame and unit, how pair records store it: one entry per key), plus
`pose_t0`, `pose_tm1` (float64 [4,4], vehicle -> world at each time) and `num_points_t0` / `num_points_tm1` (int32,
real point counts; batches are padded).

Batched model input adds `point_mask_t0` [B,N0] and `point_mask_tm1` [B,N1] (True = a real point, never padding).
"""
from __future__ import annotations

import dataclasses

# WOD dataset.proto LaserName; returns are ri_return1 and ri_return2 of a Laser.
LASER_NAMES = {1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}
ALL_LASERS = (1, 2, 3, 4, 5)
ALL_RETURNS = (1, 2)


def lidar_selection_problem(laser_names, returns) -> str | None:
    """What is wrong with a selection of lasers and returns ("laser_names=...: ..."), or None if it is usable."""
    if not laser_names or any(n not in ALL_LASERS for n in laser_names):
        return f"laser_names={tuple(laser_names)}: need one or more of {ALL_LASERS} (TOP..REAR)"
    if not returns or any(r not in ALL_RETURNS for r in returns):
        return f"returns={tuple(returns)}: need one or more of {ALL_RETURNS} (first, second return)"
    return None


# Flow class channel of range_image_flow_compressed (paper appendix "Dataset Format"); label.proto Type uses the same
# numbers for the four object types.
CLASS_NO_LABEL = -1
CLASS_BACKGROUND = 0
CLASS_VEHICLE = 1
CLASS_PEDESTRIAN = 2
CLASS_SIGN = 3
CLASS_CYCLIST = 4
CLASS_NAMES = {0: "background", 1: "vehicle", 2: "pedestrian", 3: "sign", 4: "cyclist"}
OBJECT_CLASSES = (1, 2, 3, 4)
# The classes the paper's tables report (Table 2 columns; Fig. 3/4 curves), in the paper's order.
PAPER_TABLE_CLASSES = ("vehicle", "pedestrian", "cyclist")

# "Moving" as the paper's evaluation defines it (Sec. 5, Table 2 and 4): |flow| >= 0.5 m/s. The Argoverse 2 three-way
# EPE uses the same 0.05 m per 0.1 s. The dataset-statistics figure (paper Fig. 2 caption) instead calls points
# below 0.1 m/s stationary; both are named here and nowhere else.
MOVING_THRESHOLD_MPS = 0.5
STATS_MOVING_THRESHOLD_MPS = 0.1

FRAME_KEYS = ("points_xyz", "intensity", "elongation", "flow_mps", "class_id", "laser_name", "pose",
              "timestamp_micros")


@dataclasses.dataclass(frozen=True)
class PointKey:
    """One per-point key of a pair: what an example holds under it, and how pair records store it."""
    dtype: str  # of the example's tensor
    tail_shape: tuple  # after the point axis
    cloud: str  # "t0" or "tm1": whose points it follows (masked, padded and counted with them)
    meaning: str  # frame and unit, or the values
    stored: str  # dtype in pair records (`ff3d_tf.data.pair_records`, precision "exact")
    stored_compact: str = ""  # ... with precision "compact" (empty: as `stored`)
    optional: bool = False  # an extra: present where the source has it (a records directory's manifest lists it)
    padding: int = 0  # the value of padded points in a batch (-1 for the ids whose -1 means "none")


PSEUDO_FLOW_KEY, PSEUDO_VALID_KEY = "flow_mps_pseudo_t0", "pseudo_valid_t0"
# Every per-point key of a pair, in record order: the required ones, then the optional extras (pair records carry an
# extra when their source has it; `ff3d_tf.data.pairs` masks and pads it with its cloud's points).
POINT_KEYS = {
    "points_xyz_t0": PointKey("float32", (3,), "t0", "t0 cloud, vehicle frame at t0, m", "float32"),
    "point_features_t0": PointKey("float32", (2,), "t0", "intensity, elongation", "float32", "float16"),
    "flow_mps_t0": PointKey("float32", (3,), "t0", "label: motion from t-1 to t0, vehicle frame at t0, m/s",
                            "float32", "float16"),
    "class_id_t0": PointKey("int32", (), "t0", "label class (CLASS_NAMES; -1 no label)", "int8", padding=-1),
    "points_xyz_tm1_in_t0": PointKey("float32", (3,), "tm1", "t-1 cloud moved into the vehicle frame at t0, m",
                                     "float32"),
    "point_features_tm1": PointKey("float32", (2,), "tm1", "intensity, elongation", "float32", "float16"),
    PSEUDO_FLOW_KEY: PointKey("float32", (3,), "t0", "pseudo-label, as flow_mps_t0 (m/s)", "float32", "float16",
                              optional=True),
    PSEUDO_VALID_KEY: PointKey("bool", (), "t0", "the point has a pseudo-label (False: outside the fitted region, "
                               "ground, or its pair's fit failed; no label, not a zero label)", "uint8",
                               optional=True),
    "is_ground_t0": PointKey("bool", (), "t0", "ground (Argoverse 2: the log's ground-height raster; other records: "
                             "the height rule of `tools/add_ground_masks.py`)", "uint8", optional=True),
    "category_t0": PointKey("int32", (), "t0", "Argoverse 2 category index (-1: none)", "int8", optional=True,
                            padding=-1),
    "is_ground_tm1": PointKey("bool", (), "tm1", "the partner cloud's ground by the same rule as t0's", "uint8",
                              optional=True),
    "instance_id_t0": PointKey("int32", (), "t0", "the labelled box (track) the point is in, numbered within its "
                               "pair from 0; -1: in no box", "int32", optional=True,
                               padding=-1),
}


# Sweeps beyond the pair (`data.num_frames` > 2): the past sweep k (k = 1 is the pair's t-1) is the cloud "tm{k}",
# under the keys of `cloud_keys`; the field's multi-sweep models read up to 5 sweeps (DeltaFlow, Flow4D).
MAX_NUM_FRAMES = 5
for _k in range(2, MAX_NUM_FRAMES):
    POINT_KEYS[f"points_xyz_tm{_k}_in_t0"] = PointKey("float32", (3,), f"tm{_k}", f"t-{_k} cloud moved into the "
                                                      "vehicle frame at t0, m", "float32")
    POINT_KEYS[f"point_features_tm{_k}"] = PointKey("float32", (2,), f"tm{_k}", "intensity, elongation", "float32",
                                                    "float16")


# An example of more than 2 sweeps near the start of its log has fewer real past sweeps than it reads: the oldest
# one it has (the log's first sweep) stands in for those missing, as the DeltaFlow authors' evaluation loader clamps
# history to a scene's first frame (KTH-RPL/OpenSceneFlow, src/dataset.py). This bool scalar says whether every past
# sweep is its own; training reads only examples where it is True (their training loader never starts a sample
# without its history); evaluation, prediction and the submission read every example.
FULL_HISTORY_KEY = "full_history"


def sweep_clouds(num_frames: int) -> tuple[str, ...]:
    """The clouds of an example of `num_frames` sweeps, newest first: ("t0", "tm1", ..., "tm{num_frames-1}")."""
    return ("t0",) + tuple(f"tm{k}" for k in range(1, num_frames))


# Which sweep an example's "tm1" slot (the partner of t0) holds: "previous", the sweep before t0 (WOD, own sequences:
# the paper's pair), or "next", the sweep after it (Argoverse 2 challenge records, whose flow is scored from t0 to the
# next sweep). The older slots tm2, tm3, ... hold t-1, t-2, ... with "next", t-2, t-3, ... with "previous".
PARTNERS = ("previous", "next")
DEFAULT_PARTNER = PARTNERS[0]  # records and models that say nothing of their partner: the paper's pair


def slot_sweep_offsets(num_frames: int, partner: str) -> tuple[int, ...]:
    """The time of each slot's sweep from t0 (slot 0 = t0, 1 = tm1, ...), in sweeps: (0, -1, -2, ...) with `partner`
    "previous"; (0, +1, -1, -2, ...) with "next"."""
    if partner not in PARTNERS:
        raise ValueError(f"partner={partner!r}: one of {PARTNERS}")
    if partner == "previous":
        return tuple(-k for k in range(num_frames))
    return (0, 1) + tuple(-k for k in range(1, num_frames - 1))


def slots_newest_first(num_frames: int, partner: str) -> tuple[int, ...]:
    """The slots of `sweep_clouds(num_frames)` ordered by the time of the sweep they hold, newest first: with
    `partner` "previous" the slot order itself; with "next" the partner (slot 1, sweep t+1) first, then t0 and the
    history."""
    offsets = slot_sweep_offsets(num_frames, partner)
    return tuple(sorted(range(num_frames), key=lambda slot: -offsets[slot]))


def cloud_keys(cloud: str) -> dict:
    """The keys of one cloud of an example ("t0", "tm1", ...): xyz (vehicle frame at t0, m), features (intensity,
    elongation), mask (batched: real points), count (real points), pose (vehicle -> world at the sweep's time)."""
    return {"xyz": "points_xyz_t0" if cloud == "t0" else f"points_xyz_{cloud}_in_t0",
            "features": f"point_features_{cloud}", "mask": f"point_mask_{cloud}", "count": f"num_points_{cloud}",
            "pose": f"pose_{cloud}"}


def model_input_keys(num_frames: int = 2) -> tuple[str, ...]:
    """What the model reads of a batched example of `num_frames` sweeps (`MODEL_INPUT_KEYS` for the pair)."""
    return tuple(cloud_keys(c)[part] for c in sweep_clouds(num_frames) for part in ("xyz", "features", "mask"))


def past_sweep_keys(num_frames: int) -> tuple[str, ...]:
    """The keys an example of `num_frames` sweeps holds beyond the pair's (`PAIR_KEYS`): the per-point keys, count
    and pose of the sweeps t-2 and older."""
    return tuple(cloud_keys(c)[part] for c in sweep_clouds(num_frames)[2:]
                 for part in ("xyz", "features", "count", "pose"))


# Self-supervision (SeFlow, TeFlow; written by `tools/prepare_self_supervision.py`, read by `train.loss=seflow` and
# `teflow`): one key per sweep of an example, what the preparation job found of each of its points: ground
# (`DYNAMIC_CLUSTER_GROUND`), static by DUFOMap (`DYNAMIC_CLUSTER_STATIC`), dynamic in no cluster of its sweep (HDBSCAN's
# noise, `DYNAMIC_CLUSTER_NOISE`), or dynamic in the cluster k >= 1 of its sweep (numbered within the sweep).
DYNAMIC_CLUSTER_KEY_FORMAT = "dynamic_cluster_{cloud}"
DYNAMIC_CLUSTER_GROUND, DYNAMIC_CLUSTER_STATIC, DYNAMIC_CLUSTER_NOISE = -2, -1, 0
for _cloud in sweep_clouds(MAX_NUM_FRAMES):
    POINT_KEYS[DYNAMIC_CLUSTER_KEY_FORMAT.format(cloud=_cloud)] = PointKey(
        "int32", (), _cloud, "self-supervision: -2 ground, -1 static (DUFOMap), 0 dynamic in no cluster, k >= 1 "
        "dynamic in cluster k of its sweep (HDBSCAN)", "int16", optional=True, padding=DYNAMIC_CLUSTER_STATIC)


# Every sweep's ground (`data.drop_ground`: DeltaFlow's input without it): t0's and the partner's above, the past
# sweeps' here, each by the same rule as t0's (`ground_keys`).
GROUND_KEY_FORMAT = "is_ground_{cloud}"
for _cloud in sweep_clouds(MAX_NUM_FRAMES)[2:]:
    POINT_KEYS[GROUND_KEY_FORMAT.format(cloud=_cloud)] = PointKey(
        "bool", (), _cloud, "the past sweep's ground (Argoverse 2: the log's raster; other records: the height "
        "rule of `tools/add_ground_masks.py`)", "uint8", optional=True)


def ground_keys(num_frames: int) -> tuple[str, ...]:
    """The ground mask keys of every sweep of an example of `num_frames` sweeps, in slot order."""
    return tuple(GROUND_KEY_FORMAT.format(cloud=c) for c in sweep_clouds(num_frames))


def _point_keys(cloud: str, optional: bool) -> tuple[str, ...]:
    return tuple(k for k, spec in POINT_KEYS.items() if spec.cloud == cloud and spec.optional == optional)


def extra_point_keys(num_frames: int) -> tuple[str, ...]:
    """The optional per-point keys (extras) an example of `num_frames` sweeps may hold: those of each of its clouds."""
    return tuple(k for c in sweep_clouds(num_frames) for k in _point_keys(c, True))


PAIR_T0_POINT_KEYS = _point_keys("t0", False)  # [N0, ...] per point
PAIR_TM1_POINT_KEYS = _point_keys("tm1", False)  # [N1, ...] per point
PAIR_T0_EXTRA_POINT_KEYS = _point_keys("t0", True)
PAIR_TM1_EXTRA_POINT_KEYS = _point_keys("tm1", True)
# Every extra of any cloud (records of more sweeps may hold those of their older clouds): what a manifest may list.
PAIR_EXTRA_POINT_KEYS = extra_point_keys(MAX_NUM_FRAMES)
# The extras the Argoverse 2 challenge's evaluation reads (its eval mask and meta-classes), and those AV2 pair records
# carry (also the partner cloud's ground, for the pseudo-label job, and each point's cuboid, for DeltaFlow's loss).
AV2_EVAL_KEYS = ("is_ground_t0", "category_t0")
AV2_RECORD_EXTRAS = AV2_EVAL_KEYS + ("is_ground_tm1", "instance_id_t0")
# What the model reads of a batched example (labels and poses are not model input).
MODEL_INPUT_KEYS = ("points_xyz_t0", "point_features_t0", "point_mask_t0", "points_xyz_tm1_in_t0",
                    "point_features_tm1", "point_mask_tm1")
PAIR_KEYS = ("points_xyz_t0", "point_features_t0", "points_xyz_tm1_in_t0", "point_features_tm1", "flow_mps_t0",
             "class_id_t0", "pose_t0", "pose_tm1", "num_points_t0", "num_points_tm1")

# Range image channel layouts (dataset.proto comments; flow: paper appendix), and each channel's index by name.
RANGE_CHANNELS = ("range", "intensity", "elongation", "is_in_nlz")
FLOW_CHANNELS = ("vx", "vy", "vz", "class")
TOP_POSE_CHANNELS = ("roll", "pitch", "yaw", "x", "y", "z")
RANGE_CHANNEL = {name: i for i, name in enumerate(RANGE_CHANNELS)}
FLOW_CHANNEL = {name: i for i, name in enumerate(FLOW_CHANNELS)}
TOP_POSE_CHANNEL = {name: i for i, name in enumerate(TOP_POSE_CHANNELS)}
FLOW_VELOCITY = slice(FLOW_CHANNEL["vx"], FLOW_CHANNEL["vz"] + 1)  # vx, vy, vz
TOP_POSE_ROTATION = slice(TOP_POSE_CHANNEL["roll"], TOP_POSE_CHANNEL["yaw"] + 1)  # roll, pitch, yaw
TOP_POSE_TRANSLATION = slice(TOP_POSE_CHANNEL["x"], TOP_POSE_CHANNEL["z"] + 1)  # x, y, z
