"""``omnid replay``: this build's perception and safety layer on a recording.

What would this version have done? The recording holds every input the daemon's core was
given, in order (tilt readings, joystick, keys, control-unit replies, perception results) and
every cycle's flags (capturing, laser, link and camera health, shutdown). Replay builds a fresh
:class:`~omnid.daemon.core.ControlCore` from the recorded configuration (``--set`` changes
keys), feeds it the same inputs in the same order and runs ``step`` at each recorded cycle's
time; each command and reason set is compared with the recorded one. Where the recording holds
a camera capture (rate-limited), this build's perception runs on its pixels (the recorded
calibration, or ``--calib``) and its cloud replaces the recorded one, so a changed detector or
matcher shows up in the decisions; the clouds are compared too (points per class, nearest
obstacle and drop-off ahead).

A recording that starts mid-ride (a later segment) starts the core without its map and ramps:
the first ``warmup_s`` are replayed but not compared.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from omnid.errors import ConfigError, InputError
from omnid.record import topics as tp
from omnid.record.reader import Recording

DUTY_TOL = 1e-9  # a replay of the same build on the same inputs reproduces duties exactly


@dataclass
class CycleDiff:
    t_s: float
    recorded: tuple[float, float, tuple[str, ...]]
    replayed: tuple[float, float, tuple[str, ...]]


@dataclass
class PerceptionDiff:
    t_s: float
    recorded: dict[str, float]
    replayed: dict[str, float]


@dataclass
class ReplayResult:
    cycles: int = 0
    compared: int = 0
    t0_s: float = math.nan
    t1_s: float = math.nan
    differing: list[CycleDiff] = field(default_factory=list)
    captures: int = 0
    perception_diffs: list[PerceptionDiff] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def same(self) -> bool:
        return not self.differing and not self.perception_diffs

    def spans(self, gap_s: float = 0.25) -> list[tuple[CycleDiff, CycleDiff, int]]:
        """Differing cycles merged into spans (first, last, count) — a gap over ``gap_s``
        starts a new span."""
        out: list[tuple[CycleDiff, CycleDiff, int]] = []
        for d in self.differing:
            if out and d.t_s - out[-1][1].t_s <= gap_s:
                first, _, n = out[-1]
                out[-1] = (first, d, n + 1)
            else:
                out.append((d, d, 1))
        return out


def replay_config(rec: Recording, overrides: list[str] = ()) -> Any:  # type: ignore[assignment]
    """The recorded configuration, validated by this version (``--set KEY=VALUE`` applied)."""
    from omnid.config import from_mapping
    from omnid.daemon.config import OmnidConfig

    data = rec.config_data
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep:
            raise InputError(
                f"--set {item!r}: expected KEY=VALUE (e.g. safety.stop_distance_mm=300)"
            )
        import yaml

        node = data
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise InputError(f"--set {key}: {p} is not a section")
        node[parts[-1]] = yaml.safe_load(value)
    try:
        return from_mapping(OmnidConfig, data)
    except ConfigError as exc:
        raise InputError(
            f"{rec.paths[0]}: its configuration (omnid {rec.metadata.get('omnid_version', '?')}) "
            f"is not accepted by this version: {exc}"
        ) from None


def replay_calibration(rec: Recording, override: Any = None) -> Any:
    """The recorded calibration, or ``override`` if it fits the recorded rig (else one line)."""
    import yaml

    from omnid.core.calibration import Calibration

    rig = rec.rig
    if override is not None:
        shape = list(override.rig.cam1.image_shape)
        if rig and (
            shape != rig.get("image_shape")
            or abs(override.rig.baseline_mm - rig.get("baseline_mm", 0.0)) > 1.0
            or abs(override.floor_depth_mm - rig.get("floor_depth_mm", 0.0)) > 50.0
        ):
            raise InputError(
                f"{rec.paths[0]}: recorded with another rig (images {rig.get('image_shape')}, "
                f"baseline {rig.get('baseline_mm')} mm, floor {rig.get('floor_depth_mm')} mm) "
                f"than this calibration ({shape}, {override.rig.baseline_mm:g} mm, "
                f"{override.floor_depth_mm:g} mm)"
            )
        return override
    text = rec.metadata.get("calibration", "")
    if not text:
        return None
    try:
        return Calibration.from_mapping(yaml.safe_load(text), source=str(rec.paths[0]))
    except ConfigError as exc:
        raise InputError(
            f"{rec.paths[0]}: its calibration is not readable by this version: {exc}"
        ) from None


def _reasons(doc: dict[str, Any]) -> tuple[str, ...]:
    return tuple(sorted(doc.get("reasons") or ()))


def _cloud_summary(cloud: Any, half_width_mm: float = 350.0) -> dict[str, float]:
    from omnid.commands.perceive import nearest_ahead_mm

    cls = cloud.classes
    return {
        "points": float(len(cloud)),
        "floor": float((cls == 0).sum()),
        "obstacle": float((cls == 1).sum()),
        "dropoff": float((cls == 2).sum()),
        "nearest_obstacle_mm": nearest_ahead_mm(cloud, 1, half_width_mm),
        "nearest_dropoff_mm": nearest_ahead_mm(cloud, 2, half_width_mm),
    }


def _differs(a: dict[str, float], b: dict[str, float]) -> bool:
    """Clouds differ when a class count changes by more than 2 % of the points (at least 3),
    or the nearest obstacle / drop-off ahead moves by more than 50 mm (or appears, vanishes)."""
    tol = max(3.0, 0.02 * max(a["points"], b["points"]))
    if any(abs(a[k] - b[k]) > tol for k in ("floor", "obstacle", "dropoff")):
        return True
    for k in ("nearest_obstacle_mm", "nearest_dropoff_mm"):
        x, y = a[k], b[k]
        if math.isinf(x) != math.isinf(y) or (not math.isinf(x) and abs(x - y) > 50.0):
            return True
    return False


def replay(
    rec: Recording,
    overrides: list[str] = (),  # type: ignore[assignment]
    calibration: Any = None,
    perception: bool = True,
    warmup_s: float | None = None,
) -> ReplayResult:
    """Replay ``rec`` through this build (see the module docstring)."""
    import cv2

    from omnid.core.types import PointCloud, StereoCapture
    from omnid.daemon.core import ControlCore
    from omnid.devices.control_unit import ControlUnitStatus
    from omnid.devices.joystick import JoystickReading
    from omnid.devices.tilt import TiltReading

    config = replay_config(rec, overrides)
    calib = replay_calibration(rec, calibration) if perception else None
    result = ReplayResult()
    first_segment = rec.metadata.get("segment", "0") == "0"
    if warmup_s is None:
        warmup_s = 0.0 if first_segment else 2.0 * config.safety.perception_timeout_s
    if not first_segment:
        result.notes.append(
            f"a later segment: the core starts without the earlier map; the first "
            f"{warmup_s:g} s are not compared"
        )

    # -- the recorded captures, by their capture time (this build's perception on them) ------
    images: dict[float, dict[str, Any]] = {}
    for (what, cam), topic in tp.CAMERA_TOPICS.items():
        for m in rec.topic(topic):
            img = cv2.imdecode(np.frombuffer(m.doc.data, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(f"{rec.paths[0]}: a damaged image on {topic}")
            images.setdefault(round(rec.t_s(m), 6), {})[f"{what}{cam}"] = img

    # -- the inputs and cycles, in the order the core saw them --------------------------------
    events: list[tuple[int, str, Any]] = []
    for kind, topic in (
        ("tilt", tp.TILT),
        ("joystick", tp.JOYSTICK),
        ("key", tp.KEY),
        ("input_lost", tp.INPUT_LOST),
        ("status", tp.STATUS),
    ):
        events += [(m.doc["seq"], kind, m.doc) for m in rec.topic(topic)]
    results = rec.topic(tp.PERCEPTION)
    clouds = rec.topic(tp.CLOUD)
    if len(results) != len(clouds):
        raise InputError(f"{rec.paths[0]}: perception results and clouds do not pair up")
    for r, c in zip(results, clouds, strict=True):
        events.append((r.doc["seq"], "cloud", (r.doc, c.doc)))
    commands = {m.doc["seq"]: m.doc for m in rec.topic(tp.COMMAND)}
    for m in rec.topic(tp.SAFETY):
        cmd = commands.get(m.doc["seq"])
        if cmd is not None:
            events.append((m.doc["seq"], "cycle", (m.doc, cmd)))
    events.sort(key=lambda e: e[0])
    if not any(kind == "cycle" for _, kind, _ in events):
        raise InputError(f"{rec.paths[0]}: no control cycles recorded")

    from omnid.core.pipeline import PerceptionSettings as PipelineSettings
    from omnid.core.pipeline import perceive

    pipe = PipelineSettings(detection=config.detection)
    core = ControlCore(config)
    t_start: float | None = None
    for _, kind, doc in events:
        if kind == "tilt":
            core.on_tilt(TiltReading(doc["roll_deg"], doc["pitch_deg"], doc["t_s"]))
        elif kind == "joystick":
            fwd = math.nan if doc["forward"] is None else doc["forward"]
            turn = math.nan if doc["turn"] is None else doc["turn"]
            core.on_joystick(_joystick(JoystickReading, fwd, turn, doc["t_s"]))
        elif kind == "key":
            core.on_key(doc["command"], doc["t_s"])
        elif kind == "input_lost":
            core.on_input_lost(doc["source"], doc["t_s"])
        elif kind == "status":
            core.on_status(
                ControlUnitStatus(
                    seq=doc["unit_seq"],
                    left_clocks=doc["left_clocks"],
                    right_clocks=doc["right_clocks"],
                    laser_on=doc["laser_on"],
                    faults=doc["faults"],
                    timestamp_s=doc["t_s"],
                    left_applied_duty=doc.get("left_applied_duty") or 0.0,
                    right_applied_duty=doc.get("right_applied_duty") or 0.0,
                )
            )
        elif kind == "cloud":
            meta, msg = doc
            xyz, cls = tp.decode_point_cloud(msg.data)
            n = len(xyz)
            fit = meta.get("calibration_fit")  # absent in older recordings, null if unmeasured
            cloud = PointCloud(
                xyz,
                np.full((n, 3, 3), np.nan),
                np.zeros((n, 4)),
                cls,
                meta["floor_depth_mm"],
                calibration_fit=math.nan if fit is None else float(fit),
                not_understood=int(meta.get("not_understood", 0)),
            )
            t_cap = float(meta["capture_time_s"])
            cap = images.get(round(t_cap, 6))
            if perception and calib is not None and cap is not None and len(cap) == 4:
                result.captures += 1
                sc = StereoCapture(timestamp_s=t_cap, **cap)
                now = perceive(sc, calib, config.perception.method, pipe)
                a, b = _cloud_summary(cloud), _cloud_summary(now)
                if _differs(a, b):
                    result.perception_diffs.append(PerceptionDiff(t_cap, a, b))
                cloud = now
            core.on_perception(cloud, t_cap)
        else:
            safety, cmd_doc = doc
            t = float(safety["t_s"])
            t_start = t if t_start is None else t_start
            core.capturing = bool(safety.get("capturing"))
            core.link_ok = bool(safety.get("link_ok", True))
            core.camera_ok = bool(safety.get("camera_ok", True))  # absent in older recordings
            core.halt = bool(safety.get("halt"))
            core.laser_on = bool(cmd_doc.get("laser_requested", cmd_doc.get("laser_on", True)))
            cmd = core.step(t)
            report = core.last_report
            result.cycles += 1
            result.t0_s = t if math.isnan(result.t0_s) else result.t0_s
            result.t1_s = t
            if t - t_start < warmup_s:
                continue
            result.compared += 1
            mine = tuple(sorted(r.value for r in report.reasons)) if report else ()
            theirs = _reasons(safety)
            rl, rr = float(cmd_doc["left_duty"]), float(cmd_doc["right_duty"])
            if (
                mine != theirs
                or abs(cmd.left_duty - rl) > DUTY_TOL
                or abs(cmd.right_duty - rr) > DUTY_TOL
                or bool(cmd.enable) != bool(cmd_doc["enable"])
            ):
                result.differing.append(
                    CycleDiff(t, (rl, rr, theirs), (cmd.left_duty, cmd.right_duty, mine))
                )
    return result


def _joystick(cls: Any, fwd: float, turn: float, t: float) -> Any:
    try:
        return cls(fwd, turn, t)
    except ValueError:  # a reading the link would not have made: give the core what it got
        r = object.__new__(cls)
        for k, v in (("forward", fwd), ("turn", turn), ("timestamp_s", t)):
            object.__setattr__(r, k, v)
        return r


def summary_lines(rec: Recording, res: ReplayResult) -> list[str]:
    """What a person reads: where this build decides otherwise than the recording."""
    src = rec.metadata.get("source", "?")
    ver = rec.metadata.get("omnid_version", "?")
    names = ", ".join(str(p) for p in rec.paths)
    lines = [
        f"replayed {res.cycles} control cycles (t = {res.t0_s:.2f} … {res.t1_s:.2f} s) of "
        f"{names} (recorded by omnid {ver}, {src}); {res.compared} compared"
    ]
    lines += [f"note: {n}" for n in res.notes]
    if rec.truncated:
        lines.append(f"note: {rec.truncated}; replayed what is complete")
    if res.captures:
        lines.append(
            f"perception re-run on {res.captures} recorded captures: "
            + (
                "clouds as recorded"
                if not res.perception_diffs
                else f"{len(res.perception_diffs)} differ"
            )
        )
    for d in res.perception_diffs[:10]:
        a, b = d.recorded, d.replayed
        lines.append(
            f"  capture t = {d.t_s:.2f} s: points {a['points']:.0f} → {b['points']:.0f} "
            f"(obstacle {a['obstacle']:.0f} → {b['obstacle']:.0f}, drop-off {a['dropoff']:.0f} → "
            f"{b['dropoff']:.0f}), nearest obstacle ahead {_mm(a['nearest_obstacle_mm'])} → "
            f"{_mm(b['nearest_obstacle_mm'])}"
        )
    if not res.differing:
        lines.append("decisions: every compared cycle as recorded (commands and reasons)")
        return lines
    spans = res.spans()
    lines.append(
        f"decisions differ in {len(res.differing)} of {res.compared} cycles, {len(spans)} spans:"
    )
    for first, last, n in spans[:20]:
        rl, rr, rreasons = first.recorded
        ml, mr, mreasons = first.replayed
        lines.append(
            f"  t = {first.t_s:.2f} … {last.t_s:.2f} s ({n} cycles): recorded duty "
            f"{rl:+.2f}/{rr:+.2f} [{', '.join(rreasons) or 'ok'}] → this build {ml:+.2f}/{mr:+.2f} "
            f"[{', '.join(mreasons) or 'ok'}]"
        )
    if len(spans) > 20:
        lines.append(f"  ... and {len(spans) - 20} more spans")
    return lines


def _mm(v: float) -> str:
    return "none" if math.isinf(v) else f"{v:.0f} mm"


def as_json(rec: Recording, res: ReplayResult) -> dict[str, Any]:
    doc = dataclasses.asdict(res)
    doc["same"] = res.same
    doc["paths"] = [str(p) for p in rec.paths]
    doc["truncated"] = rec.truncated
    return doc
