"""3D recordings for the Rerun viewer: both clouds and the predicted flow of each pair, on a time line over sweeps.

`FlowRecording(path)` writes an `.rrd` file (rerun-sdk, the `viz3d` extra; imported only here, when a recording is
made or read). Open it with `rerun out.rrd` (the viewer ships with rerun-sdk) and scrub the `sweep` time line.
What it holds (`ENTITY_*`):

| entity | what (logged at each sweep unless static) |
|---|---|
| `world` | static: view coordinates FLU, x forward, y left, z up (the vehicle frame's axes) |
| `world/ego` | Transform3D: the vehicle frame at t0 in `world`, which is the vehicle frame of the first pair's t0 |
|             | sweep (identity when the pairs have no poses: every pair then shows in its own t0 frame) |
| `world/ego/points_t0` | Points3D: the t0 cloud, coloured by predicted speed (`speed_colors`; no prediction: grey) |
| `world/ego/points_tm1` | Points3D: the t-1 cloud in the t0 vehicle frame, one colour (`TM1_COLOR`) |
| `world/ego/flow` | Arrows3D from each t0 point with a prediction and speed >= `min_arrow_speed_mps` (default the |
|                  | paper's moving threshold, 0.5 m/s): vector = flow x `arrow_seconds` (default 0.1 s, the |
|                  | displacement over one 10 Hz sweep), coloured by speed |

The time line `sweep` (a sequence) is the index of the pair's t0 sweep in its log (1 for a single pair).
`recording_frames(path)` reads a recording back into NumPy (entity -> sweep -> component -> array).
"""
from __future__ import annotations

import os
import uuid

import numpy as np

from ff3d_tf import schema

APPLICATION_ID = "ff3d_tf"
TIMELINE = "sweep"
ENTITY_WORLD = "world"
ENTITY_EGO = "world/ego"
ENTITY_POINTS_T0 = "world/ego/points_t0"
ENTITY_POINTS_TM1 = "world/ego/points_tm1"
ENTITY_FLOW = "world/ego/flow"
MAX_SPEED_MPS = 15.0  # the top of the speed colour scale (a car in town); faster points get its colour
NO_PREDICTION_COLOR = (128, 128, 128)
TM1_COLOR = (90, 140, 255)
POINT_RADIUS_M = 0.04
SPEED_COLORMAP = "turbo"  # matplotlib's: dark blue (still) -> green -> red (MAX_SPEED_MPS and faster)
VIZ3D_HELP = ("3D recordings need the viz3d extra (rerun-sdk==0.41.0): pip install -c constraints.txt -e '.[viz3d]' "
              "(make install installs it)")


class Viz3dUnavailableError(ImportError):
    """rerun-sdk is not installed; the message says how to install it."""


def _rerun():
    try:
        import rerun as rr
    except ImportError as err:
        raise Viz3dUnavailableError(f"{VIZ3D_HELP} ({err})") from None
    return rr


def speed_colors(flow_mps: np.ndarray, point_valid: np.ndarray | None = None,
                 max_speed_mps: float = MAX_SPEED_MPS) -> np.ndarray:
    """[N,3] uint8 RGB: `SPEED_COLORMAP` at |flow| / max_speed_mps (clipped to 1); points without a prediction
    `NO_PREDICTION_COLOR`."""
    import matplotlib
    flow = np.asarray(flow_mps, np.float64).reshape(-1, 3)
    speed = np.linalg.norm(flow, axis=1)
    rgb = matplotlib.colormaps[SPEED_COLORMAP](np.clip(speed / max_speed_mps, 0.0, 1.0))[:, :3]
    out = np.round(rgb * 255).astype(np.uint8)
    if point_valid is not None:
        out[~np.asarray(point_valid, bool)] = NO_PREDICTION_COLOR
    return out


class FlowRecording:
    """An `.rrd` file being written: `log_pair` once per pair (in any order of sweeps), then `close`."""

    def __init__(self, path: str, *, arrow_seconds: float = 0.1,
                 min_arrow_speed_mps: float = schema.MOVING_THRESHOLD_MPS, max_speed_mps: float = MAX_SPEED_MPS,
                 recording_name: str | None = None):
        rr = _rerun()
        self._rr = rr
        self.path = path
        self.arrow_seconds, self.min_arrow_speed_mps, self.max_speed_mps = arrow_seconds, min_arrow_speed_mps, \
            max_speed_mps
        self._world_from_pose = None  # inv(pose) of the first logged t0 pose: the world frame is that vehicle frame
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        self._rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        blueprint = rr.blueprint.Blueprint(rr.blueprint.Spatial3DView(origin=ENTITY_WORLD, name="flow"),
                                           collapse_panels=False)
        self._rec.save(path, default_blueprint=blueprint)
        if recording_name:
            self._rec.send_recording_name(recording_name)
        self._rec.log(ENTITY_WORLD, rr.ViewCoordinates.FLU, static=True)

    def log_pair(self, sweep: int, points_xyz_t0: np.ndarray, points_xyz_tm1_in_t0: np.ndarray,
                 flow_mps: np.ndarray, point_valid: np.ndarray, pose_t0: np.ndarray | None = None) -> dict:
        """Logs one pair at time `sweep`; returns the counts logged ({"points_t0", "points_tm1", "arrows"})."""
        rr = self._rr
        xyz = np.asarray(points_xyz_t0, np.float32).reshape(-1, 3)
        xyz_tm1 = np.asarray(points_xyz_tm1_in_t0, np.float32).reshape(-1, 3)
        flow = np.asarray(flow_mps, np.float32).reshape(-1, 3)
        valid = np.asarray(point_valid, bool).reshape(-1)
        if not len(xyz) == len(flow) == len(valid):
            raise ValueError(f"log_pair: {len(xyz)} t0 points, {len(flow)} flows, {len(valid)} validity flags")
        pose = np.eye(4) if pose_t0 is None else np.asarray(pose_t0, np.float64)
        if self._world_from_pose is None:
            self._world_from_pose = np.linalg.inv(pose)
        world_from_ego = self._world_from_pose @ pose
        self._rec.set_time(TIMELINE, sequence=int(sweep))
        self._rec.log(ENTITY_EGO, rr.Transform3D(translation=world_from_ego[:3, 3], mat3x3=world_from_ego[:3, :3]))
        self._rec.log(ENTITY_POINTS_T0, rr.Points3D(xyz, colors=speed_colors(flow, valid, self.max_speed_mps),
                                                    radii=POINT_RADIUS_M))
        self._rec.log(ENTITY_POINTS_TM1, rr.Points3D(xyz_tm1, colors=np.tile(np.array(TM1_COLOR, np.uint8),
                                                                             (len(xyz_tm1), 1)),
                                                     radii=POINT_RADIUS_M))
        arrows = valid & (np.linalg.norm(flow.astype(np.float64), axis=1) >= self.min_arrow_speed_mps)
        self._rec.log(ENTITY_FLOW, rr.Arrows3D(origins=xyz[arrows], vectors=flow[arrows] * self.arrow_seconds,
                                               colors=speed_colors(flow[arrows], None, self.max_speed_mps)))
        return {"points_t0": len(xyz), "points_tm1": len(xyz_tm1), "arrows": int(arrows.sum())}

    def close(self) -> str:
        """Writes everything out and closes the file; returns its path."""
        self._rec.flush()
        self._rec.disconnect()
        return self.path

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _unpack(column, component: str) -> list[np.ndarray | None]:
    """The values of each row of a rerun component column, as NumPy ([K,3] float for positions and vectors, [K,4]
    uint8 RGBA for colours, [K] otherwise); None where the row does not hold the component."""
    out = []
    for row in column.to_pylist():
        if row is None:
            out.append(None)
            continue
        values = np.asarray(row)
        if component.endswith(":colors"):
            packed = values.astype(np.uint32)
            values = np.stack([(packed >> s) & 0xFF for s in (24, 16, 8, 0)], -1).astype(np.uint8).reshape(-1, 4)
        elif component.endswith(":mat3x3"):  # stored column by column
            values = values.reshape(-1, 3, 3).transpose(0, 2, 1)
        out.append(values)
    return out


def recording_frames(path: str) -> dict[str, dict[int | None, dict[str, np.ndarray]]]:
    """What an `.rrd` file holds: {entity path (no leading /): {sweep (None: static): {component: array}}}, the
    last value logged at each sweep (read with `rerun.chunk.RrdReader`). Components are named as Rerun names them
    ("Points3D:positions"); colours come back as [K,4] uint8 RGBA, `Transform3D:mat3x3` as [K,3,3] matrices."""
    _rerun()
    from rerun.chunk import RrdReader
    out: dict = {}
    for chunk in RrdReader(path).stream().to_chunks():
        entity = chunk.entity_path.lstrip("/")
        if entity.startswith("__"):  # recording properties
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        sweeps = batch.column(names.index(TIMELINE)).to_pylist() if TIMELINE in names else [None] * batch.num_rows
        for name in names:
            field = batch.schema.field(name)
            if (field.metadata or {}).get(b"rerun:kind") != b"data":
                continue
            for sweep, values in zip(sweeps, _unpack(batch.column(names.index(name)), name)):
                if values is not None:
                    out.setdefault(entity, {}).setdefault(sweep, {})[name] = values
    return out
