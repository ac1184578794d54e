"""Synthetic driving segments written as complete WOD v1 `Frame` records (the project's embedded default).

The street scene of `ff3d_tf.data.synthetic.scene` is raycast with the five WOD lidars (`wod_lidars`: TOP 64 x 2650
with explicit inclinations and per-pixel poses; FRONT, SIDE_LEFT, SIDE_RIGHT, REAR 200 x 600 with uniform
inclinations), and each frame is written as WOD writes it: header and calibrations, range images of both returns,
camera projections, the TOP pixel pose, and `laser_labels` (tracked boxes with speed and acceleration, in the vehicle
frame). The ego vehicle drives the road.

Flow labels (`range_image_flow_compressed`) come from the simulator's own kinematics in the paper's convention
(`synthetic_scene.point_labels`). An object without a label at the previous frame of the segment (its first labelled
frame, or the segment's first frame) gets class -1; background and static structures get class 0 and flow 0.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from ff3d_tf import schema
from ff3d_tf.data.synthetic import scene as sim
from ff3d_tf.data.wod import wod_format
from ff3d_tf.data.synthetic.scene import LidarSpec

SHORT_MAX_RANGE_M = 20.0
_RANGE = schema.RANGE_CHANNEL
_FLOW_CLASS = schema.FLOW_CHANNEL["class"]


def _extrinsic(x, y, z, roll, pitch, yaw) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = wod_format.rotation_from_rpy(roll, pitch, yaw)
    m[:3, 3] = (x, y, z)
    return m


def _top_inclinations() -> np.ndarray:
    """64 explicit beams from -17.6 to +2.4 degrees, denser near the horizon (ascending, as stored)."""
    u = np.linspace(0.0, 1.0, 64)
    return np.deg2rad(-17.6 + 20.0 * (1.0 - (1.0 - u) ** 1.6))


def wod_lidars(scale: float = 1.0) -> tuple[LidarSpec, ...]:
    """The five WOD lidars with slightly rotated (non-trivial) extrinsics. `scale` < 1 shrinks the images (tests)."""
    def sz(n):
        return max(8, int(round(n * scale)))
    top_h = 64 if scale >= 1 else max(8, int(round(64 * scale)))
    top_incl = _top_inclinations() if top_h == 64 else np.interp(np.linspace(0, 63, top_h), np.arange(64),
                                                                   _top_inclinations())
    short = dict(max_range_m=SHORT_MAX_RANGE_M, beam_inclinations=None, inclination_min=np.deg2rad(-90.0),
                 inclination_max=np.deg2rad(30.0), half_fov_rad=np.deg2rad(100.0))
    return (
        LidarSpec(1, top_h, sz(2650), _extrinsic(1.43, 0.0, 2.18, 0.003, -0.006, 0.0148), sim.TOP_MAX_RANGE_M,
                  top_incl),
        LidarSpec(2, sz(200), sz(600), _extrinsic(4.07, 0.0, 0.69, 0.002, 0.05, 0.004), **short),
        LidarSpec(3, sz(200), sz(600), _extrinsic(3.24, 1.03, 0.98, 0.04, 0.01, np.pi / 2 - 0.01), **short),
        LidarSpec(4, sz(200), sz(600), _extrinsic(3.24, -1.03, 0.98, -0.04, 0.01, -np.pi / 2 + 0.012), **short),
        LidarSpec(5, sz(200), sz(600), _extrinsic(-1.15, 0.0, 0.45, 0.0, 0.04, np.pi - 0.006), **short),
    )


@dataclasses.dataclass
class SegmentSpec:
    seed: int
    num_frames: int = 20
    name: str = ""
    lidar_scale: float = 1.0
    start_time_s: float = 0.0


def generate_segment(spec: SegmentSpec):
    """Yields serialized WOD `Frame` records (bytes) of one segment: scene, then per frame header, lidar images and
    laser labels."""
    from waymo_open_dataset import dataset_pb2

    rng = np.random.default_rng(spec.seed)
    ego_speed = float(rng.uniform(4.0, 9.0))
    road, agents = sim.make_scene(rng, ego_speed)
    lidars = wod_lidars(spec.lidar_scale)
    name = spec.name or f"synthetic_seed{spec.seed}"
    t0_micros = 1_550_000_000_000_000 + spec.seed * 1_000_000_000
    prev_labelled: set[str] = set()
    for i in range(spec.num_frames):
        scene = sim.frame_scene(i, spec.start_time_s + i * sim.DT_S, road, agents, ego_speed)
        frame = dataset_pb2.Frame()
        _frame_header(frame, scene, t0_micros, name, lidars)
        point_counts: dict[str, int] = {}
        for lidar in lidars:
            _write_laser(frame.lasers.add(), lidar, scene, road, ego_speed, prev_labelled, point_counts, rng)
        _laser_labels(frame, scene, road, name, point_counts)
        prev_labelled = scene.labelled_now
        yield frame.SerializeToString()


def _frame_header(frame, scene: sim.FrameScene, t0_micros: int, name: str, lidars) -> None:
    """Timestamp, vehicle pose, segment name and every lidar's calibration."""
    frame.timestamp_micros = t0_micros + int(round(scene.t * 1e6))
    frame.pose.transform[:] = wod_format.encode_transform(scene.pose)
    frame.context.name = name
    for lidar in lidars:
        cal = frame.context.laser_calibrations.add()
        cal.name = lidar.name
        cal.extrinsic.transform[:] = wod_format.encode_transform(lidar.extrinsic)
        if lidar.beam_inclinations is not None:
            cal.beam_inclinations[:] = [float(v) for v in lidar.beam_inclinations]
        else:
            cal.beam_inclination_min, cal.beam_inclination_max = lidar.inclination_min, lidar.inclination_max


def _write_laser(laser, lidar: LidarSpec, scene: sim.FrameScene, road: sim.Road, ego_speed: float,
                 prev_labelled: set, point_counts: dict, rng: np.random.Generator) -> None:
    """One lidar's range images (both returns), flow images, camera projections and TOP pixel pose."""
    laser.name = lidar.name
    top_pose = sim.top_pixel_pose(lidar, road, ego_speed, scene.t) if lidar.name == 1 else None
    boxes = [(j, scene.poses_t[a.track_id][0], scene.poses_t[a.track_id][1], a.size / 2)
             for j, a in enumerate(scene.near)]
    ranges, hits, origins_w, dirs_w = sim.scan(lidar, top_pose, scene.pose, boxes)
    h, w = lidar.height, lidar.width
    valid = np.isfinite(ranges) & (ranges > 0.5)
    points_w = origins_w + dirs_w * np.where(valid, ranges, 0.0)[..., None]
    mat, classes, flow_v = sim.point_labels(scene, road, valid, hits, points_w, prev_labelled, point_counts)
    intensity = np.zeros(hits.shape, np.float32)
    for material, (mean, std) in sim.MATERIAL_INTENSITY.items():
        sel = mat == material
        if sel.any():
            intensity[sel] = np.clip(rng.normal(mean, std, int(sel.sum())), 0.0, 1.5)
    range_img = np.full((h, w, len(schema.RANGE_CHANNELS)), -1.0, np.float32)  # is_in_nlz -1: no no-label zone
    range_img[..., _RANGE["range"]] = np.where(valid, ranges, -1.0)
    range_img[..., _RANGE["intensity"]] = np.where(valid, intensity, 0.0)
    range_img[..., _RANGE["elongation"]] = np.where(valid, np.clip(rng.gamma(2.0, 0.05, hits.shape), 0.0, 1.5), 0.0)
    flow_img = np.zeros((h, w, len(schema.FLOW_CHANNELS)), np.float32)
    flow_img[..., schema.FLOW_VELOCITY] = np.where(valid[..., None], flow_v, 0.0)
    flow_img[..., _FLOW_CLASS] = np.where(valid, classes, schema.CLASS_NO_LABEL)
    ri = laser.ri_return1
    ri.range_image_compressed = wod_format.encode_matrix(range_img)
    ri.range_image_flow_compressed = wod_format.encode_matrix(flow_img)
    ri.camera_projection_compressed = wod_format.encode_matrix(np.zeros((h, w, 6), np.int32))
    if lidar.name == 1:
        ri.range_image_pose_compressed = wod_format.encode_matrix(top_pose)
    # No second returns in this scene (empty range image: range -1), written so return 2 decodes.
    empty = np.full((h, w, len(schema.RANGE_CHANNELS)), -1.0, np.float32)
    empty[..., _RANGE["intensity"]] = empty[..., _RANGE["elongation"]] = 0.0
    empty_flow = np.zeros((h, w, len(schema.FLOW_CHANNELS)), np.float32)
    empty_flow[..., _FLOW_CLASS] = schema.CLASS_NO_LABEL
    laser.ri_return2.range_image_compressed = wod_format.encode_matrix(empty)
    laser.ri_return2.range_image_flow_compressed = wod_format.encode_matrix(empty_flow)
    laser.ri_return2.camera_projection_compressed = wod_format.encode_matrix(np.zeros((h, w, 6), np.int32))


def _laser_labels(frame, scene: sim.FrameScene, road: sim.Road, name: str, point_counts: dict) -> None:
    """Tracked 3D boxes (vehicle frame at t) with speed and acceleration (`synthetic_scene.box_motion`, rotated into
    the vehicle frame at t), type, track id and point count."""
    vehicle_from_world = np.linalg.inv(scene.pose)
    for a in scene.near:
        if a.track_id not in scene.labelled_now:
            continue
        center_w, heading_w = scene.poses_t[a.track_id]
        label = frame.laser_labels.add()
        center_v = vehicle_from_world[:3, :3] @ center_w + vehicle_from_world[:3, 3]
        heading_v = heading_w - np.arctan2(scene.pose[1, 0], scene.pose[0, 0])
        label.box.center_x, label.box.center_y, label.box.center_z = (float(v) for v in center_v)
        label.box.length, label.box.width, label.box.height = (float(v) for v in a.size)
        label.box.heading = float(np.arctan2(np.sin(heading_v), np.cos(heading_v)))
        velocity_w, acceleration_w = sim.box_motion(a, road, scene.t)
        vel_v, acc_v = vehicle_from_world[:3, :3] @ velocity_w, vehicle_from_world[:3, :3] @ acceleration_w
        label.metadata.speed_x, label.metadata.speed_y = float(vel_v[0]), float(vel_v[1])
        label.metadata.accel_x, label.metadata.accel_y = float(acc_v[0]), float(acc_v[1])
        label.type = a.class_id  # label.proto Type uses the flow class numbers for these four types
        label.id = f"{name}_{a.track_id}"
        label.num_lidar_points_in_box = point_counts.get(a.track_id, 0)


def write_segment(path: str, spec: SegmentSpec) -> int:
    """Writes one segment as a TFRecord file of `Frame`s; returns the number of frames."""
    import tensorflow as tf

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    n = 0
    with tf.io.TFRecordWriter(path) as writer:
        for record in generate_segment(spec):
            writer.write(record)
            n += 1
    return n
