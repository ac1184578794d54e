"""Synthetic driving segments written as complete WOD v1 `Frame` records (the project's embedded default).

The street scene of `ff3d_tf.data.synthetic.scene` is raycast with the five WOD lidars (`wod_lidars`: TOP 64 x 2650
with explicit inclinations and per-pixel poses; FRONT, SIDE_LEFT, SIDE_RIGHT, REAR 200 x 600 with uniform
inclinations), and each frame is written as WOD writes it: header and calibrations, range images of both returns,
camera projections, the TOP pixel pose, and `laser_labels` (tracked boxes with speed and acceleration, in the vehicle
frame). The ego vehicle drives the road.

Flow labels (`range_image_flow_compressed`) come from the simulator's own kinematics in the paper's convention
(`synthetic_scene.point_labels`). An object without a label at the previous frame of the segment (its first labelled
frame, or the segment's first frame) gets class -1; background and static structures get class 0 and flow 0.

With a realism profile other than the default (`SegmentSpec.realism`, `synthetic.realism`), each column of every
lidar fires at its own time (`synthetic.lidar`; a spin of 0.1 s centred on the frame timestamp): TOP from the ego
pose at that time, recorded in its pixel pose as WOD records it, so the reader's per-pixel decoding compensates the
ego's motion; the short-range lidars from the frame pose (the reader decodes them with it); the objects where they
are at each column's time, so a moving object is smeared by its own motion. Ranges are noisy and some returns are
dropped. Labels then follow the paper's rule on the stored points: a laser label is the box an annotator draws
(the object where TOP swept over it, grown by `Realism.box_margin_m`: `lidar.label_box`), its speed and acceleration
the differences of those boxes over the frames; a point inside a labelled box (`lidar.points_in_box`, the first box
in label order) gets that box's rigid motion from the previous frame's box of its track, (p - T p) / 0.1 s in the
vehicle frame (class -1 where the track has no box there), every other point class 0 and flow 0. That is what
`ff3d_tf.labels.box_flow.bootstrap_flow` computes from the laser labels, up to the float32 rounding of the stored
ranges; the distorted points of a fast object that leave its box, and noisy points beyond its margin, are
background, as they are in labels bootstrapped from real boxes.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from ff3d_tf import geometry, schema
from ff3d_tf.data.synthetic import city
from ff3d_tf.data.synthetic import lidar as lidar_lib
from ff3d_tf.data.synthetic import realism as realism_lib
from ff3d_tf.data.synthetic import scene as sim
from ff3d_tf.data.wod import wod_format
from ff3d_tf.data.synthetic.scene import LidarSpec

SHORT_MAX_RANGE_M = 20.0  # Waymo Open Dataset paper: the four short-range lidars, range 20 m, VFOV -90 to +30 deg
_RANGE = schema.RANGE_CHANNEL
_FLOW_CLASS = schema.FLOW_CHANNEL["class"]


def _extrinsic(x, y, z, roll, pitch, yaw) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = wod_format.rotation_from_rpy(roll, pitch, yaw)
    m[:3, 3] = (x, y, z)
    return m


def _top_inclinations() -> np.ndarray:
    """64 explicit beams from -17.6 to +2.4 degrees (the top lidar's vertical field of view in the Waymo Open Dataset
    paper), denser near the horizon (ascending, as stored)."""
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
    realism: str | realism_lib.Realism = realism_lib.IDEAL.name  # a `synthetic.realism` profile (or its name)


def generate_segment(spec: SegmentSpec):
    """Yields serialized WOD `Frame` records (bytes) of one segment: scene, then per frame header, lidar images and
    laser labels."""
    from waymo_open_dataset import dataset_pb2

    realism = realism_lib.profile(spec.realism)
    if realism != realism_lib.IDEAL:
        yield from _generate_realistic(spec, realism)
        return
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
    valid = np.isfinite(ranges) & (ranges > 0.5)
    points_w = origins_w + dirs_w * np.where(valid, ranges, 0.0)[..., None]
    mat, classes, flow_v = sim.point_labels(scene, road, valid, hits, points_w, prev_labelled, point_counts)
    intensity = _draw_intensity(rng, mat)
    _encode_laser(laser, lidar, valid, ranges, intensity, classes, flow_v, top_pose, rng)


def _draw_intensity(rng: np.random.Generator, materials: np.ndarray) -> np.ndarray:
    """Intensity per pixel drawn from its material's (`scene.MATERIAL_INTENSITY`), in [0, 1.5]."""
    intensity = np.zeros(materials.shape, np.float32)
    for material, (mean, std) in sim.MATERIAL_INTENSITY.items():
        sel = materials == material
        if sel.any():
            intensity[sel] = np.clip(rng.normal(mean, std, int(sel.sum())), 0.0, 1.5)
    return intensity


def _encode_laser(laser, lidar: LidarSpec, valid, ranges, intensity, classes, flow_v, top_pose,
                  rng: np.random.Generator) -> None:
    """Range images (return 1: range where valid, intensity, a drawn elongation; return 2 empty), flow images, camera
    projections (none) and the TOP pixel pose of one laser."""
    h, w = lidar.height, lidar.width
    range_img = np.full((h, w, len(schema.RANGE_CHANNELS)), -1.0, np.float32)  # is_in_nlz -1: no no-label zone
    range_img[..., _RANGE["range"]] = np.where(valid, ranges, -1.0)
    range_img[..., _RANGE["intensity"]] = np.where(valid, intensity, 0.0)
    range_img[..., _RANGE["elongation"]] = np.where(valid, np.clip(rng.gamma(2.0, 0.05, (h, w)), 0.0, 1.5), 0.0)
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


def _spin_offset_s(share):
    """Time of a TOP column firing at `share` of the turn, relative to the frame (`scene.column_time_offsets`)."""
    return (np.asarray(share) - 0.5) * sim.DT_S


def _generate_realistic(spec: SegmentSpec, realism: realism_lib.Realism):
    """`generate_segment` under a realism profile (module docstring)."""
    from waymo_open_dataset import dataset_pb2

    rng = np.random.default_rng(spec.seed)
    world = city.world_for(realism, rng, spec.start_time_s + spec.num_frames * sim.DT_S + 1.0)
    lidars = wod_lidars(spec.lidar_scale)
    name = spec.name or f"synthetic_seed{spec.seed}"
    t0_micros = 1_550_000_000_000_000 + spec.seed * 1_000_000_000
    prev_boxes: dict = {}
    for i in range(spec.num_frames):
        scene = world.frame_scene(i, spec.start_time_s + i * sim.DT_S)
        frame = dataset_pb2.Frame()
        _frame_header(frame, scene, t0_micros, name, lidars)
        boxes = {a.track_id: _label_box(world, a, scene.t, realism, scene.pose) for a in scene.near
                 if a.track_id in scene.labelled_now}
        point_counts: dict[str, int] = {}
        for lidar in lidars:
            _write_laser_realistic(frame.lasers.add(), lidar, scene, world, realism, boxes, prev_boxes, point_counts,
                                   rng)
        _laser_labels_realistic(frame, scene, world, realism, boxes, name, point_counts)
        prev_boxes = boxes
        yield frame.SerializeToString()


def _label_box(world: sim.World, agent, t: float, realism: realism_lib.Realism, pose=None):
    """The annotated box of `agent` in the frame at `t` (`lidar.label_box` with TOP's spin; `pose`: the ego's at
    t, computed when not given)."""
    pose = world.ego_poses([t])[0] if pose is None else pose
    return lidar_lib.label_box(world.road, agent, t, pose, _spin_offset_s, realism.box_margin_m,
                               realism.motion_distortion)


def _write_laser_realistic(laser, lidar: LidarSpec, scene: sim.FrameScene, world: sim.World,
                           realism: realism_lib.Realism, boxes: dict, prev_boxes: dict, point_counts: dict,
                           rng: np.random.Generator) -> None:
    """`_write_laser` under a realism profile: timed columns, measured ranges, labels by the box rule."""
    laser.name = lidar.name
    column_times = scene.t + sim.column_time_offsets(lidar.width)
    top_pose = None
    if lidar.name == 1:
        top_pose = sim.pixel_pose_of(lidar, world.ego_poses(column_times))
        pix = top_pose[0].astype(np.float64)  # the pose as stored (float32), as the reader decodes it
        poses = np.tile(np.eye(4), (lidar.width, 1, 1))
        poses[:, :3, :3] = wod_format.rotation_from_rpy(*(pix[:, schema.TOP_POSE_CHANNEL[c]]
                                                          for c in ("roll", "pitch", "yaw")))
        poses[:, :3, 3] = pix[:, schema.TOP_POSE_TRANSLATION]
    else:
        poses = np.broadcast_to(scene.pose, (lidar.width, 4, 4))
    ranges, hits, origins_w, dirs_w = lidar_lib.scan(lidar, column_times, poses, scene, world.road, rng,
                                                     realism.motion_distortion)
    measured, returned = lidar_lib.measure_scan(rng, ranges, hits, scene.near, realism)
    valid = returned & (measured > 0.5)
    points_w = origins_w + dirs_w * np.where(valid, measured, 0.0)[..., None]
    classes, flow_v = _box_rule_labels(scene, points_w, valid, boxes, prev_boxes, point_counts)
    mat = np.array([a.material for a in scene.near] + ["ground", "ground"], dtype=object)[hits]
    intensity = _draw_intensity(rng, mat)
    _encode_laser(laser, lidar, valid, np.where(valid, measured, -1.0), intensity, classes, flow_v, top_pose, rng)


def _box_rule_labels(scene: sim.FrameScene, points_w: np.ndarray, valid: np.ndarray, boxes: dict, prev_boxes: dict,
                     point_counts: dict) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (class, flow m/s in the vehicle frame at t) by the box rule of the module docstring."""
    classes = np.zeros(valid.shape, np.int32)
    flow_v = np.zeros(valid.shape + (3,), np.float64)
    vehicle_from_world = np.linalg.inv(scene.pose)[:3, :3]
    pts = points_w[valid]
    by_x = lidar_lib.PointsByX(pts)
    taken = np.zeros(len(pts), bool)
    cls_flat, flow_flat = np.zeros(len(pts), np.int32), np.zeros((len(pts), 3))
    by_id = {a.track_id: a for a in scene.near}
    for track_id, (centre, heading, size) in boxes.items():
        inside = by_x.inside(centre, heading, size)
        inside = inside[~taken[inside]]
        if not inside.size:
            continue
        taken[inside] = True
        point_counts[track_id] = point_counts.get(track_id, 0) + int(inside.size)
        if track_id not in prev_boxes or scene.index == 0:
            cls_flat[inside] = schema.CLASS_NO_LABEL
            continue
        c1, h1, _ = prev_boxes[track_id]
        moved = geometry.box_matrices_np(c1, h1)[0] @ np.linalg.inv(geometry.box_matrices_np(centre, heading)[0])
        p1 = pts[inside] @ moved[:3, :3].T + moved[:3, 3]
        flow_flat[inside] = ((pts[inside] - p1) / sim.DT_S) @ vehicle_from_world.T
        cls_flat[inside] = by_id[track_id].class_id
    classes[valid], flow_v[valid] = cls_flat, flow_flat
    return classes, flow_v


def _laser_labels_realistic(frame, scene: sim.FrameScene, world: sim.World, realism: realism_lib.Realism,
                            boxes: dict, name: str, point_counts: dict) -> None:
    """`_laser_labels` of the annotated boxes: speed and acceleration by backward differences of the track's boxes
    over the frames (each frame's box at its own annotation time)."""
    vehicle_from_world = np.linalg.inv(scene.pose)
    ego_yaw = np.arctan2(scene.pose[1, 0], scene.pose[0, 0])
    by_id = {a.track_id: a for a in scene.near}
    earlier = [world.ego_poses([scene.t - k * sim.DT_S])[0] for k in (1, 2)]
    for track_id, (centre_w, heading_w, size) in boxes.items():
        a = by_id[track_id]
        label = frame.laser_labels.add()
        center_v = vehicle_from_world[:3, :3] @ centre_w + vehicle_from_world[:3, 3]
        heading_v = heading_w - ego_yaw
        label.box.center_x, label.box.center_y, label.box.center_z = (float(v) for v in center_v)
        label.box.length, label.box.width, label.box.height = (float(v) for v in size)
        label.box.heading = float(np.arctan2(np.sin(heading_v), np.cos(heading_v)))
        c1, c2 = (_label_box(world, a, scene.t - k * sim.DT_S, realism, earlier[k - 1])[0] for k in (1, 2))
        velocity_w = (centre_w - c1) / sim.DT_S
        acceleration_w = (velocity_w - (c1 - c2) / sim.DT_S) / sim.DT_S
        vel_v, acc_v = vehicle_from_world[:3, :3] @ velocity_w, vehicle_from_world[:3, :3] @ acceleration_w
        label.metadata.speed_x, label.metadata.speed_y = float(vel_v[0]), float(vel_v[1])
        label.metadata.accel_x, label.metadata.accel_y = float(acc_v[0]), float(acc_v[1])
        label.type = a.class_id
        label.id = f"{name}_{track_id}"
        label.num_lidar_points_in_box = point_counts.get(track_id, 0)


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
