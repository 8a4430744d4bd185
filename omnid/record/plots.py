"""``omnid report FILE.mcap``: the top-down picture and the timeline of a recording, as PNG.

Drawn with OpenCV (already a base dependency) rather than matplotlib: two fixed figure types
do not need a plotting library, and the chair's computer does not need 40 MB more and a font
cache to explain an incident.

- top-down (``top.png``): the path on odometry (blue) and, for a simulator recording, the true
  path (black) with the course's boxes and drop-offs; every obstacle (red) and drop-off
  (orange) point perception reported, placed by the odometry at its capture; where the safety
  layer refused a motion the rider asked for (red crosses). 1 m grid, a legend, a title.
- timeline (``timeline.png``): the rider's demand (forward, turn), the speed (allowed by the
  safety layer, measured by odometry, and true in a simulator), the limit scale with a band per
  reason, and the faults (bands from start to end, ticks for single events).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnid.record import topics as tp
from omnid.record.reader import Recording

WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GRID = (225, 225, 225)
BLUE = (200, 90, 20)
RED = (40, 40, 220)
ORANGE = (0, 140, 255)
GREEN = (60, 160, 40)
GREY = (130, 130, 130)
FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX

REASON_BGR = {
    "obstacle_stop": (40, 40, 220),
    "dropoff_stop": (0, 120, 255),
    "slow_zone": (0, 200, 230),
    "approach": (80, 180, 240),
    "escape_creep": (180, 120, 200),
    "unknown_ahead": (150, 150, 150),
    "unknown_stop": (90, 90, 90),
    "unknown_creep": (190, 190, 190),
    "bump": (200, 40, 200),
    "perception_stale": (120, 60, 160),
    "rider_stop": (90, 160, 60),
    "input_stale": (20, 20, 140),
    "status_stale": (60, 60, 60),
    "fault": (0, 0, 160),
}


@dataclass
class Series:
    """The recording's time series, on its own clock (s)."""

    t0_s: float
    cycles_t: NDArray[np.float64]
    forward: NDArray[np.float64]
    turn: NDArray[np.float64]
    allowed_v: NDArray[np.float64]
    scale: NDArray[np.float64]
    reasons: list[list[str]]
    refused: NDArray[np.bool_]
    pose_t: NDArray[np.float64]
    pose: NDArray[np.float64]  # (N, 3) odom x, y mm, theta
    truth_t: NDArray[np.float64]
    truth: NDArray[np.float64]  # (M, 5) x, y, theta, left, right speed
    faults: list[tuple[float, float, str]]  # start, end (inf: open), name
    events: list[tuple[float, str]]


def series(rec: Recording) -> Series:
    safety = [m.doc for m in rec.topic(tp.SAFETY)]
    demand = {m.doc["seq"]: m.doc for m in rec.topic(tp.DEMAND)}
    commands = {m.doc["seq"]: m.doc for m in rec.topic(tp.COMMAND)}
    t = np.array([d["t_s"] for d in safety], dtype=np.float64)
    fwd, turn, refused = [], [], []
    for d in safety:
        dm = demand.get(d["seq"], {})
        cm = commands.get(d["seq"], {})
        f, w = float(dm.get("forward") or 0.0), float(dm.get("turn") or 0.0)
        fwd.append(f)
        turn.append(w)
        asked = not dm.get("stop", True) and (f != 0.0 or w != 0.0)
        still = not cm.get("left_duty") and not cm.get("right_duty")
        refused.append(asked and still and bool(d.get("reasons")))
    pose_msgs = rec.topic(tp.POSE)
    pose_t = np.array([rec.t_s(m) for m in pose_msgs], dtype=np.float64)
    pose = np.array(
        [
            (
                m.doc.pose.position.x * 1000.0,
                m.doc.pose.position.y * 1000.0,
                2.0 * math.atan2(m.doc.pose.orientation.z, m.doc.pose.orientation.w),
            )
            for m in pose_msgs
        ],
        dtype=np.float64,
    ).reshape(-1, 3)
    truth_docs = [m.doc for m in rec.topic(tp.SIM_TRUTH)]
    truth_t = np.array([d["t_s"] for d in truth_docs], dtype=np.float64)
    truth = np.array(
        [
            (d["x_mm"], d["y_mm"], d["theta_rad"], d["left_speed_mm_s"], d["right_speed_mm_s"])
            for d in truth_docs
        ],
        dtype=np.float64,
    ).reshape(-1, 5)
    open_: dict[str, float] = {}
    faults: list[tuple[float, float, str]] = []
    events: list[tuple[float, str]] = []
    for m in rec.topic(tp.FAULTS):
        d = m.doc
        if d["event"] == "start":
            open_[d["name"]] = d["t_s"]
        elif d["event"] == "end" and d["name"] in open_:
            faults.append((open_.pop(d["name"]), d["t_s"], d["name"]))
        elif d["event"] == "event":
            events.append((d["t_s"], f"{d['name']}: {d['detail']}"))
    faults += [(t0, math.inf, n) for n, t0 in open_.items()]
    t0 = float(t[0]) if len(t) else 0.0
    return Series(
        t0,
        t,
        np.array(fwd),
        np.array(turn),
        np.array([np.nan if d.get("v_mm_s") is None else d["v_mm_s"] for d in safety]),
        np.array([np.nan if d.get("scale") is None else d["scale"] for d in safety]),
        [list(d.get("reasons") or ()) for d in safety],
        np.array(refused, dtype=bool),
        pose_t,
        pose,
        truth_t,
        truth,
        faults,
        events,
    )


def _text(img: Any, s: str, org: tuple[int, int], scale: float = 0.42, colour: Any = BLACK) -> None:
    import cv2

    cv2.putText(img, s, org, FONT, scale, colour, 1, cv2.LINE_AA)


def timeline(rec: Recording, width: int = 1400) -> NDArray[np.uint8]:
    """The timeline figure (see the module docstring), BGR."""
    import cv2

    s = series(rec)
    if len(s.cycles_t) == 0:
        raise ValueError("no control cycles recorded")
    t = s.cycles_t - s.t0_s
    t_end = max(float(t[-1]), 1e-3)
    reason_names = sorted({r for rs in s.reasons for r in rs})
    fault_names = sorted({n for _, _, n in s.faults})
    left, right, top = 130, 30, 46
    panel_h = 150
    band_h = 16
    reason_h = max(1, len(reason_names)) * band_h + 30
    fault_h = max(1, len(fault_names) + (1 if s.events else 0)) * band_h + 30
    height = top + 3 * (panel_h + 34) + reason_h + fault_h + 76
    img = np.full((height, width, 3), 255, np.uint8)
    plot_w = width - left - right
    src = rec.metadata.get("source", "?")
    _text(
        img,
        f"omnid report: {', '.join(p.name for p in rec.paths)} ({src}, omnid "
        f"{rec.metadata.get('omnid_version', '?')}), {t_end:.1f} s",
        (10, 26),
        0.6,
    )

    def x_of(tt: NDArray[np.float64] | float) -> Any:
        return left + np.asarray(tt) / t_end * plot_w

    def axes(y0: int, h: int, title: str, lo: float, hi: float, unit: str) -> Any:
        cv2.rectangle(img, (left, y0), (left + plot_w, y0 + h), GREY, 1)
        step = _nice_step(t_end / 10.0)
        k = 0.0
        while k <= t_end + 1e-9:
            xx = int(x_of(k))
            cv2.line(img, (xx, y0 + 1), (xx, y0 + h - 1), GRID, 1)
            _text(img, f"{k:g}", (xx - 8, y0 + h + 14), 0.38)
            k += step
        for v in (lo, (lo + hi) / 2, hi):
            yy = int(y0 + h - (v - lo) / (hi - lo) * h)
            cv2.line(img, (left + 1, yy), (left + plot_w - 1, yy), GRID, 1)
            _text(img, f"{v:g}", (left - 46, yy + 4), 0.38)
        _text(img, title, (8, y0 + 14), 0.45)
        _text(img, unit, (8, y0 + 32), 0.38, GREY)

        def y_of(v: NDArray[np.float64]) -> Any:
            return y0 + h - (np.clip(v, lo, hi) - lo) / (hi - lo) * h

        return y_of

    def line(tt: NDArray[np.float64], v: NDArray[np.float64], y_of: Any, colour: Any) -> None:
        ok = np.isfinite(v)
        if ok.sum() < 2:
            return
        pts = np.column_stack([x_of(tt[ok]), y_of(v[ok])]).astype(np.int32)
        cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)

    def legend(y0: int, items: list[tuple[str, Any]]) -> None:
        x = left + plot_w - 10
        for label, colour in reversed(items):
            w = cv2.getTextSize(label, FONT, 0.4, 1)[0][0]
            x -= w + 30
            cv2.line(img, (x, y0 + 12), (x + 18, y0 + 12), colour, 2)
            _text(img, label, (x + 22, y0 + 16), 0.4)

    y = top
    y_of = axes(y, panel_h, "rider demand", -1.0, 1.0, "fraction")
    line(t, s.forward, y_of, BLUE)
    line(t, s.turn, y_of, GREEN)
    legend(y, [("forward", BLUE), ("turn (+ left)", GREEN)])
    y += panel_h + 34

    v_meas = _odometry_speed(s.pose_t, s.pose)
    vmax = max(100.0, float(np.nanmax(np.abs(np.concatenate([s.allowed_v, v_meas, [1.0]])))))
    vmax = _nice_step(vmax) * math.ceil(vmax / _nice_step(vmax))
    y_of = axes(y, panel_h, "speed", -vmax, vmax, "mm/s")
    items = [("allowed by safety", ORANGE), ("odometry", BLUE)]
    line(t, s.allowed_v, y_of, ORANGE)
    line(s.pose_t - s.t0_s, v_meas, y_of, BLUE)
    if len(s.truth_t):
        line(s.truth_t - s.t0_s, 0.5 * (s.truth[:, 3] + s.truth[:, 4]), y_of, BLACK)
        items.append(("true (simulator)", BLACK))
    legend(y, items)
    y += panel_h + 34

    y_of = axes(y, panel_h, "limit scale", 0.0, 1.0, "allowed/asked")
    line(t, s.scale, y_of, RED)
    refused_t = t[s.refused]
    for tt in refused_t[:: max(1, len(refused_t) // 400)]:
        xx = int(x_of(tt))
        cv2.line(img, (xx, y + panel_h - 8), (xx, y + panel_h - 1), RED, 1)
    legend(y, [("scale", RED), ("refused (ticks)", RED)])
    y += panel_h + 34

    _text(img, "reasons", (8, y + 12), 0.45)
    y += 18
    for i, name in enumerate(reason_names):
        yy = y + 6 + i * band_h
        _text(img, name, (8, yy + 12), 0.38)
        on = np.array([name in rs for rs in s.reasons])
        _bands(img, t, on, yy, band_h - 3, x_of, REASON_BGR.get(name, GREY))
    y += reason_h
    _text(img, "faults", (8, y + 12), 0.45)
    y += 18
    for i, name in enumerate(fault_names):
        yy = y + 6 + i * band_h
        _text(img, name, (8, yy + 12), 0.38)
        for t0, t1, n in s.faults:
            if n == name:
                a = int(x_of(max(t0 - s.t0_s, 0.0)))
                b = int(x_of(min(t1 - s.t0_s, t_end)))
                cv2.rectangle(img, (a, yy + 2), (max(b, a + 2), yy + band_h - 3), (0, 0, 170), -1)
    if s.events:
        yy = y + 6 + len(fault_names) * band_h
        _text(img, "events", (8, yy + 12), 0.38)
        for te, _ in s.events:
            xx = int(x_of(min(max(te - s.t0_s, 0.0), t_end)))
            cv2.line(img, (xx, yy + 2), (xx, yy + band_h - 3), (0, 0, 170), 2)
    if not fault_names and not s.events:
        _text(img, "none", (left, y + 18), 0.4, GREY)
    _text(img, "time, s", (left + plot_w // 2, height - 10), 0.45)
    return img


def _odometry_speed(
    t: NDArray[np.float64], pose: NDArray[np.float64], window_s: float = 0.5
) -> Any:
    """Signed speed along the heading over the last ``window_s`` (odometry moves in whole
    31.4 mm clocks, so a per-cycle difference is 0 or a spike), mm/s."""
    if len(t) < 3:
        return np.full(len(t), np.nan)
    step = np.diff(pose[:, :2], axis=0)
    along = np.cos(pose[1:, 2]) * step[:, 0] + np.sin(pose[1:, 2]) * step[:, 1]
    travel = np.concatenate([[0.0], np.cumsum(along)])
    j = np.searchsorted(t, t - window_s)
    dt = t - t[j]
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.where(dt > 0.5 * window_s, (travel - travel[j]) / dt, np.nan)
    return v


def _bands(img: Any, t: Any, on: Any, y: int, h: int, x_of: Any, colour: Any) -> None:
    import cv2

    if not on.any():
        return
    edges = np.flatnonzero(np.diff(np.concatenate([[0], on.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        xa = int(x_of(t[a]))
        xb = int(x_of(t[min(b, len(t) - 1)]))
        cv2.rectangle(img, (xa, y + 2), (max(xb, xa + 1), y + h), colour, -1)


def _nice_step(x: float) -> float:
    if x <= 0 or not math.isfinite(x):
        return 1.0
    e = 10 ** math.floor(math.log10(x))
    for m in (1, 2, 5, 10):
        if m * e >= x:
            return float(m * e)
    return float(10 * e)


def topdown(rec: Recording, size_px: int = 900) -> NDArray[np.uint8]:
    """The top-down figure (see the module docstring), BGR."""
    import json

    import cv2

    s = series(rec)
    sim = json.loads(rec.metadata.get("sim") or "{}")
    cfg = rec.config_data
    offset = float(
        sim.get("rig_x_offset_mm", cfg.get("perception", {}).get("rig_x_offset_mm", 300))
    )
    start = (0.0, 0.0, 0.0)
    world_name = "odom"
    if len(s.truth):  # the simulator: odometry starts at the true start pose
        first = rec.topic(tp.SIM_TF)
        if first:
            tr = next(x for x in first[0].doc.transforms if x.child_frame_id == "odom")
            start = (
                tr.translation.x * 1000.0,
                tr.translation.y * 1000.0,
                2.0 * math.atan2(tr.rotation.z, tr.rotation.w),
            )
        world_name = "world"

    def to_world(xy: NDArray[np.float64], pose: tuple[float, float, float]) -> NDArray[np.float64]:
        c, sn = math.cos(pose[2]), math.sin(pose[2])
        return np.column_stack(
            [pose[0] + c * xy[:, 0] - sn * xy[:, 1], pose[1] + sn * xy[:, 0] + c * xy[:, 1]]
        )

    odo = to_world(s.pose[:, :2], start) if len(s.pose) else np.zeros((0, 2))
    odo_th = s.pose[:, 2] + start[2] if len(s.pose) else np.zeros(0)
    seen: list[NDArray[np.float64]] = []
    results = rec.topic(tp.PERCEPTION)
    clouds = rec.topic(tp.CLOUD)
    for r, c in zip(results, clouds, strict=False):
        xyz, cls = tp.decode_point_cloud(c.doc.data)
        keep = cls != 0
        if not keep.any() or len(s.pose_t) == 0:
            continue
        i = int(np.clip(np.searchsorted(s.pose_t, r.doc["capture_time_s"]), 0, len(s.pose_t) - 1))
        robot = np.column_stack([xyz[keep, 0] + offset, -xyz[keep, 1]])
        w = to_world(robot, (odo[i, 0], odo[i, 1], odo_th[i]))
        seen.append(np.column_stack([w, cls[keep]]))
    pts = np.vstack(seen) if seen else np.zeros((0, 3))
    boxes, drops = _world_rects(rec)
    everything = [odo, pts[:, :2]]
    if len(s.truth):
        everything.append(s.truth[:, :2])
    for rect in boxes + drops:
        everything.append(np.array([[rect[0], rect[2]], [rect[1], rect[3]]]))
    allxy = np.vstack([e for e in everything if len(e)] or [np.zeros((1, 2))])
    lo = allxy.min(axis=0) - 800.0
    hi = allxy.max(axis=0) + 800.0
    span = float(max(hi - lo))
    band = 70
    scale = (size_px - 20) / span
    img = np.full((size_px + band, size_px, 3), 255, np.uint8)

    def px(xy: NDArray[np.float64]) -> NDArray[np.int32]:
        col = 10 + (hi[1] - xy[:, 1]) * scale  # y left → image left (x up)
        row = band + 10 + (hi[0] - xy[:, 0]) * scale
        return np.rint(np.column_stack([col, row])).astype(np.int32)

    g = 1000.0
    for gx in np.arange(math.floor(lo[0] / g) * g, hi[0] + 1, g):
        a, b = px(np.array([[gx, lo[1]], [gx, hi[1]]]))
        cv2.line(img, tuple(a), tuple(b), GRID, 1)
    for gy in np.arange(math.floor(lo[1] / g) * g, hi[1] + 1, g):
        a, b = px(np.array([[lo[0], gy], [hi[0], gy]]))
        cv2.line(img, tuple(a), tuple(b), GRID, 1)
    for rect in drops:
        a, b = px(np.array([[rect[1], rect[3]], [rect[0], rect[2]]]))
        cv2.rectangle(img, tuple(a), tuple(b), (170, 215, 255), -1)
    for rect in boxes:
        a, b = px(np.array([[rect[1], rect[3]], [rect[0], rect[2]]]))
        cv2.rectangle(img, tuple(a), tuple(b), (185, 185, 185), -1)
    for x, y_, c in pts:
        q = px(np.array([[x, y_]]))[0]
        cv2.circle(img, (int(q[0]), int(q[1])), 2, RED if c == 1 else ORANGE, -1)
    if len(s.truth) >= 2:
        cv2.polylines(img, [px(s.truth[:, :2])], False, BLACK, 2, cv2.LINE_AA)
    if len(odo) >= 2:
        cv2.polylines(img, [px(odo)], False, BLUE, 2, cv2.LINE_AA)
    if len(odo):
        idx = np.clip(np.searchsorted(s.pose_t, s.cycles_t[s.refused]), 0, len(odo) - 1)
        for i in np.unique(idx)[:: max(1, len(np.unique(idx)) // 60)]:
            q = px(odo[i : i + 1])[0]
            cv2.drawMarker(img, (int(q[0]), int(q[1])), RED, cv2.MARKER_TILTED_CROSS, 12, 2)
        q = px(odo[:1])[0]
        cv2.circle(img, (int(q[0]), int(q[1])), 6, GREEN, 2)
    _text(
        img,
        f"omnid report: top-down ({world_name} frame, x up, 1 m grid), {len(pts)} obstacle/"
        f"drop-off points",
        (10, 22),
        0.55,
    )
    items = [("odometry path", BLUE, "line"), ("start", GREEN, "ring")]
    if len(s.truth):
        items.append(("true path", BLACK, "line"))
    items += [
        ("obstacle point", RED, "dot"),
        ("drop-off point", ORANGE, "dot"),
        ("refused motion", RED, "cross"),
    ]
    if boxes:
        items.append(("box", (185, 185, 185), "rect"))
    if drops:
        items.append(("drop-off", (170, 215, 255), "rect"))
    x = 10
    yy = 48
    for label, colour, kind in items:
        if kind == "line":
            cv2.line(img, (x, yy - 4), (x + 16, yy - 4), colour, 2)
        elif kind == "dot":
            cv2.circle(img, (x + 8, yy - 4), 3, colour, -1)
        elif kind == "ring":
            cv2.circle(img, (x + 8, yy - 4), 5, colour, 2)
        elif kind == "cross":
            cv2.drawMarker(img, (x + 8, yy - 4), colour, cv2.MARKER_TILTED_CROSS, 10, 2)
        else:
            cv2.rectangle(img, (x, yy - 10), (x + 16, yy + 2), colour, -1)
        _text(img, label, (x + 22, yy), 0.42)
        x += 22 + cv2.getTextSize(label, FONT, 0.42, 1)[0][0] + 18
        if x > size_px - 150:
            x, yy = 10, yy + 18
    return img


def _world_rects(rec: Recording) -> tuple[list[tuple[float, ...]], list[tuple[float, ...]]]:
    """Boxes and drop-offs (x0, x1, y0, y1 mm) of a simulator recording's ``/sim/world``."""
    msgs = rec.topic(tp.SIM_WORLD)
    if not msgs:
        return [], []
    boxes: list[tuple[float, ...]] = []
    drops: list[tuple[float, ...]] = []
    for e in msgs[0].doc.entities:
        for c in e.cubes:
            p, sz = c.pose.position, c.size
            r = (
                1000 * (p.x - sz.x / 2),
                1000 * (p.x + sz.x / 2),
                1000 * (p.y - sz.y / 2),
                1000 * (p.y + sz.y / 2),
            )
            (drops if p.z < 0 else boxes).append(r)
    return boxes, drops


def write_report(rec: Recording, out: str | Path) -> list[Path]:
    """``top.png`` and ``timeline.png`` in ``out`` (created); returns their paths."""
    from omnid.io_images import write_png

    folder = Path(out)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        from omnid.errors import InputError

        raise InputError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from None
    paths = [folder / "top.png", folder / "timeline.png"]
    write_png(paths[0], topdown(rec))
    write_png(paths[1], timeline(rec))
    return paths
