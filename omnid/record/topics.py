"""The recording's topics: names, schemas Foxglove understands, and the encoders.

Everything here runs on the recorder's writer thread (never in the control loop). Standard
Foxglove schemas (``foxglove.CompressedImage``, ``PointCloud``, ``Grid``, ``FrameTransforms``,
``PoseInFrame``, ``Log``, ``SceneUpdate``) are protobuf, built with the ``foxglove-sdk`` message
types; omnid's own records are JSON with a JSON schema (``omnid.*``), so a Plot panel can
follow ``/safety/limits.scale`` and ``omnid replay`` reads them with ``json.loads``.

Units: Foxglove's 3-D panel works in metres, so poses, clouds, transforms and the grid are in
metres (float64: mm / 1000 and back is exact to 1e-13 mm, so a replayed cloud rasterises as
recorded); omnid's JSON records keep omnid's units in their names (mm, s, rad, deg).

Frames: ``odom`` (odometry origin: the chair's pose at start) → ``base_link`` (axle midpoint
on the floor, x forward, y left, z up) → ``rig`` (SPEC §2: X forward, Y along the baseline =
−y, Z down; origin ``rig_x_offset_mm`` ahead of the axle, the mirrors' height above the floor).
The simulator adds ``world`` (its course) → ``odom`` (the start pose) and ``world`` →
``sim_chair`` (the true pose) on ``/sim/tf``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

#: recording format; a reader refuses other major versions with one line
FORMAT = "omnid-recording"
FORMAT_VERSION = 1

CAMERA_TOPICS = {
    ("mask", 1): "/camera1/mask",
    ("base", 1): "/camera1/base",
    ("mask", 2): "/camera2/mask",
    ("base", 2): "/camera2/base",
}
CLOUD = "/perception/cloud"
PERCEPTION = "/perception/result"
MAP = "/map"
TF = "/tf"
POSE = "/odometry/pose"
DEMAND = "/rider/demand"
TILT = "/rider/tilt"
JOYSTICK = "/rider/joystick"
KEY = "/rider/key"
INPUT_LOST = "/rider/input_lost"  # a source's device says it is gone (port, stale readings)
SAFETY = "/safety/limits"
COMMAND = "/control_unit/command"
STATUS = "/control_unit/status"
FAULTS = "/faults"
LOG = "/log"
RECORDER = "/recorder"
SIM_TF = "/sim/tf"
SIM_POSE = "/sim/pose"
SIM_WORLD = "/sim/world"
SIM_TRUTH = "/sim/truth"

#: topics whose last message is written again at the start of every new segment (static)
LATCHED = (SIM_WORLD,)


def _obj(**props: str) -> dict[str, Any]:
    types = {"n": "number", "i": "integer", "s": "string", "b": "boolean", "o": "object"}
    return {
        "type": "object",
        "properties": {k: {"type": types[v]} for k, v in props.items()},
    }


_NUM_LIST = {"type": "array", "items": {"type": "string"}}
JSON_SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    PERCEPTION: (
        "omnid.PerceptionResult",
        _obj(
            seq="i",
            t_s="n",
            capture_time_s="n",
            points="i",
            floor="i",
            obstacle="i",
            dropoff="i",
            floor_depth_mm="n",
            calibration_fit="n",
            not_understood="i",
        ),
    ),
    DEMAND: (
        "omnid.RiderDemand",
        _obj(
            seq="i", t_s="n", forward="n", turn="n", stop="b", source="s", reason="s", sources="o"
        ),
    ),
    TILT: ("omnid.TiltReading", _obj(seq="i", t_s="n", roll_deg="n", pitch_deg="n")),
    JOYSTICK: ("omnid.JoystickReading", _obj(seq="i", t_s="n", forward="n", turn="n")),
    KEY: ("omnid.KeyCommand", _obj(seq="i", t_s="n", command="s")),
    INPUT_LOST: ("omnid.InputLost", _obj(seq="i", t_s="n", source="s")),
    SAFETY: (
        "omnid.SafetyLimits",
        {
            **_obj(
                seq="i",
                t_s="n",
                v_mm_s="n",
                omega_rad_s="n",
                scale="n",
                clearance_mm="n",
                perception_age_s="n",
                capturing="b",
                link_ok="b",
                camera_ok="b",
                halt="b",
                reason_bits="i",
            ),
        }
        | {"required": ["seq", "t_s"]},
    ),
    COMMAND: (
        "omnid.WheelCommand",
        _obj(seq="i", t_s="n", left_duty="n", right_duty="n", laser_on="b", enable="b"),
    ),
    STATUS: (
        "omnid.ControlUnitStatus",
        _obj(
            seq="i",
            t_s="n",
            unit_seq="i",
            left_clocks="i",
            right_clocks="i",
            laser_on="b",
            faults="i",
            left_applied_duty="n",
            right_applied_duty="n",
        ),
    ),
    FAULTS: ("omnid.Fault", _obj(t_s="n", name="s", event="s", detail="s")),
    RECORDER: (
        "omnid.RecorderStats",
        _obj(
            t_s="n",
            queued="i",
            dropped="i",
            written="i",
            bytes="i",
            segment="s",
            failed="s",
            busy_s="n",
            slice_max_ms="n",
            slices_over_half_ms="i",
        ),
    ),
    SIM_TRUTH: (
        "omnid.SimTruth",
        _obj(
            t_s="n",
            x_mm="n",
            y_mm="n",
            theta_rad="n",
            left_speed_mm_s="n",
            right_speed_mm_s="n",
            clearance_mm="n",
            contacts="i",
            faults="s",
        ),
    ),
}
JSON_SCHEMAS[SAFETY][1]["properties"]["reasons"] = _NUM_LIST

#: protobuf topics and their Foxglove schema (message type in ``foxglove.messages``)
PROTO_TOPICS: dict[str, str] = {
    **{t: "CompressedImage" for t in CAMERA_TOPICS.values()},
    CLOUD: "PointCloud",
    MAP: "Grid",
    TF: "FrameTransforms",
    POSE: "PoseInFrame",
    LOG: "Log",
    SIM_TF: "FrameTransforms",
    SIM_POSE: "PoseInFrame",
    SIM_WORLD: "SceneUpdate",
}


@dataclass(frozen=True)
class TopicSchema:
    """What an MCAP channel (and a WebSocket channel) of a topic needs."""

    topic: str
    schema_name: str
    schema_encoding: str  # "protobuf" | "jsonschema"
    schema_data: bytes
    message_encoding: str  # "protobuf" | "json"


def schema_of(topic: str) -> TopicSchema:
    """The schema of a known topic (KeyError for an unknown one)."""
    if topic in JSON_SCHEMAS:
        name, schema = JSON_SCHEMAS[topic]
        return TopicSchema(topic, name, "jsonschema", json.dumps(schema).encode(), "json")
    import foxglove.messages as fm

    s = getattr(fm, PROTO_TOPICS[topic]).get_schema()
    return TopicSchema(topic, s.name, s.encoding, bytes(s.data), "protobuf")


# -- encoders (writer thread) --------------------------------------------------------------------


def _finite(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    return v


def json_bytes(doc: dict[str, Any]) -> bytes:
    """Compact JSON; non-finite numbers become null (JSON has no inf/NaN)."""
    try:
        return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:  # an inf or NaN somewhere (rare: clearance with nothing ahead)
        return json.dumps(_finite(doc), separators=(",", ":")).encode()


def _ts(t_ns: int) -> Any:
    import foxglove.messages as fm

    return fm.Timestamp(t_ns // 1_000_000_000, t_ns % 1_000_000_000)


def _quat_yaw(theta_rad: float) -> Any:
    import foxglove.messages as fm

    return fm.Quaternion(x=0.0, y=0.0, z=math.sin(theta_rad / 2), w=math.cos(theta_rad / 2))


def compressed_image(t_ns: int, frame_id: str, png: bytes) -> bytes:
    import foxglove.messages as fm

    return fm.CompressedImage(
        timestamp=_ts(t_ns), frame_id=frame_id, data=png, format="png"
    ).encode()


#: PointCloud layout: x, y, z float64 m (rig frame), class uint8 (0 floor, 1 obstacle, 2 drop-off)
CLOUD_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("class", "u1"), ("_", "V7")])


def point_cloud(t_ns: int, xyz_mm: np.ndarray, classes: np.ndarray) -> bytes:
    import foxglove.messages as fm

    rec = np.zeros(len(xyz_mm), dtype=CLOUD_DTYPE)
    rec["x"], rec["y"], rec["z"] = (xyz_mm[:, i] / 1000.0 for i in range(3))
    rec["class"] = classes
    f64, u8 = fm.PackedElementFieldNumericType.Float64, fm.PackedElementFieldNumericType.Uint8
    fields = [
        fm.PackedElementField(name="x", offset=0, type=f64),
        fm.PackedElementField(name="y", offset=8, type=f64),
        fm.PackedElementField(name="z", offset=16, type=f64),
        fm.PackedElementField(name="class", offset=24, type=u8),
    ]
    return fm.PointCloud(
        timestamp=_ts(t_ns),
        frame_id="rig",
        point_stride=CLOUD_DTYPE.itemsize,
        fields=fields,
        data=rec.tobytes(),
    ).encode()


def decode_point_cloud(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(xyz mm (N, 3), classes (N,) uint8) from a :data:`CLOUD_DTYPE` cloud's ``data``."""
    rec = np.frombuffer(data, dtype=CLOUD_DTYPE)
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]]) * 1000.0
    return xyz.reshape(-1, 3), rec["class"].copy()


def grid(t_ns: int, states: np.ndarray, x_min_mm: float, y_min_mm: float, res_mm: float) -> bytes:
    """The robot-frame free-space grid (``states[ix, iy]`` CellState codes) in ``base_link``:
    columns along x, rows along y, one uint8 ``state`` per cell."""
    import foxglove.messages as fm

    cells = np.ascontiguousarray(states.view(np.uint8).T)  # (ny, nx): row = y, column = x
    return fm.Grid(
        timestamp=_ts(t_ns),
        frame_id="base_link",
        pose=fm.Pose(
            position=fm.Vector3(x=x_min_mm / 1000.0, y=y_min_mm / 1000.0, z=0.0),
            orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        column_count=cells.shape[1],
        cell_size=fm.Vector2(x=res_mm / 1000.0, y=res_mm / 1000.0),
        row_stride=cells.shape[1],
        cell_stride=1,
        fields=[
            fm.PackedElementField(
                name="state", offset=0, type=fm.PackedElementFieldNumericType.Uint8
            )
        ],
        data=cells.tobytes(),
    ).encode()


def transform(
    t_ns: int, parent: str, child: str, x_m: float, y_m: float, z_m: float, rotation: Any
) -> Any:
    import foxglove.messages as fm

    return fm.FrameTransform(
        timestamp=_ts(t_ns),
        parent_frame_id=parent,
        child_frame_id=child,
        translation=fm.Vector3(x=x_m, y=y_m, z=z_m),
        rotation=rotation,
    )


def rig_rotation() -> Any:
    """base_link → rig: 180° about x (rig Y = −y, Z = −z)."""
    import foxglove.messages as fm

    return fm.Quaternion(x=1.0, y=0.0, z=0.0, w=0.0)


def frame_transforms(transforms: list[Any]) -> bytes:
    import foxglove.messages as fm

    return fm.FrameTransforms(transforms=transforms).encode()


def pose_in_frame(t_ns: int, frame: str, x_mm: float, y_mm: float, theta_rad: float) -> bytes:
    import foxglove.messages as fm

    return fm.PoseInFrame(
        timestamp=_ts(t_ns),
        frame_id=frame,
        pose=fm.Pose(
            position=fm.Vector3(x=x_mm / 1000.0, y=y_mm / 1000.0, z=0.0),
            orientation=_quat_yaw(theta_rad),
        ),
    ).encode()


_LEVELS = {10: "Debug", 20: "Info", 30: "Warning", 40: "Error", 50: "Fatal"}


def log_message(t_ns: int, levelno: int, name: str, message: str, file: str, line: int) -> bytes:
    import foxglove.messages as fm

    level = getattr(fm.LogLevel, _LEVELS.get(levelno - levelno % 10, "Info"))
    return fm.Log(
        timestamp=_ts(t_ns), level=level, message=message, name=name, file=file, line=line
    ).encode()


def world_scene(
    t_ns: int, boxes: list[tuple[float, ...]], dropoffs: list[tuple[float, ...]]
) -> bytes:
    """The simulator's course in ``world``: boxes as grey cubes (their height), drop-offs as
    thin orange slabs at floor level (depth shown below)."""
    import foxglove.messages as fm

    def cube(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, rgba: tuple) -> Any:
        return fm.CubePrimitive(
            pose=fm.Pose(
                position=fm.Vector3(
                    x=(x0 + x1) / 2000.0, y=(y0 + y1) / 2000.0, z=(z0 + z1) / 2000.0
                ),
                orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            size=fm.Vector3(
                x=max(x1 - x0, 1.0) / 1000.0,
                y=max(y1 - y0, 1.0) / 1000.0,
                z=max(z1 - z0, 1.0) / 1000.0,
            ),
            color=fm.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3]),
        )

    cubes = [cube(b[0], b[1], b[2], b[3], 0.0, b[4], (0.55, 0.55, 0.6, 0.9)) for b in boxes]
    cubes += [
        cube(d[0], d[1], d[2], d[3], -d[4], -d[4] + 5.0, (1.0, 0.55, 0.0, 0.6)) for d in dropoffs
    ]
    entity = fm.SceneEntity(
        timestamp=_ts(t_ns), frame_id="world", id="course", cubes=cubes, frame_locked=True
    )
    return fm.SceneUpdate(entities=[entity]).encode()
