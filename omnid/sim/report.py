"""Reports of simulated runs: a top-down PNG of the course and a Markdown summary.

The drawing shows the floor (white), drop-offs (hatched red), boxes and walls (gray), the chair's
path (blue) with its footprint at the start (green) and the end (blue outline), the non-floor
points perception reported (obstacles red, drop-offs orange), where the daemon refused a command
(magenta rings) and any collision or fall (black crosses).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from omnid.core.types import PointClass
from omnid.sim.chair import Chair, ChairSettings
from omnid.sim.course import Course
from omnid.sim.simulator import SimResult

_BGR = {
    "floor": (255, 255, 255),
    "drop": (200, 200, 255),
    "drop_hatch": (90, 90, 220),
    "box": (150, 150, 150),
    "path": (200, 90, 20),
    "start": (40, 160, 40),
    "obstacle": (30, 30, 230),
    "dropoff": (0, 140, 255),
    "refusal": (200, 0, 200),
    "end": (120, 40, 0),
    "contact": (0, 0, 0),
    "text": (40, 40, 40),
}


class _Canvas:
    """World mm → image px (x up the page, y to the left), with a margin for the legend."""

    def __init__(
        self, course: Course, px_per_mm: float, margin_px: int = 30, extra_px: int = 0
    ) -> None:
        self.s = px_per_mm
        self.m = margin_px
        (self.x0, self.x1), (self.y0, self.y1) = course.x_range_mm, course.y_range_mm
        self.w = math.ceil((self.y1 - self.y0) * self.s) + 2 * margin_px
        self.map_h = math.ceil((self.x1 - self.x0) * self.s) + 2 * margin_px
        self.h = self.map_h + 60 + extra_px
        self.img = np.full((self.h, self.w, 3), 235, np.uint8)

    def px(self, xy_mm: NDArray[np.float64]) -> NDArray[np.int32]:
        q = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        col = self.m + (self.y1 - q[:, 1]) * self.s
        row = self.m + (self.x1 - q[:, 0]) * self.s
        return np.column_stack([col, row]).round().astype(np.int32)

    def rect(self, x0: float, x1: float, y0: float, y1: float) -> NDArray[np.int32]:
        return self.px(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))


def draw_run(
    path: str | Path,
    course: Course,
    result: SimResult,
    chair_settings: ChairSettings | None = None,
    px_per_mm: float = 0.1,
) -> Path:
    """Write the top-down PNG of ``result`` in ``course`` to ``path``; returns the path."""
    import cv2

    groups = refusal_groups(result)
    shown = groups[:_MAX_GROUPS]
    cv = _Canvas(course, px_per_mm, extra_px=40 + 18 * (len(shown) + (len(groups) > len(shown))))
    img = cv.img
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.fillPoly(img, [cv.rect(cv.x0, cv.x1, cv.y0, cv.y1)], _BGR["floor"])
    for d in course.world.dropoffs:
        poly = cv.rect(d.x_min_mm, d.x_max_mm, d.y_min_mm, d.y_max_mm)
        cv2.fillPoly(img, [poly], _BGR["drop"])
        (c0, r0), (c1, r1) = poly.min(axis=0), poly.max(axis=0)
        for k in range(int(c0 - (r1 - r0)), int(c1), 12):  # 45° hatch, clipped to the rect
            a = np.array([[k, r1], [k + (r1 - r0), r0]], np.int32)
            sub = img[r0 : r1 + 1, c0 : c1 + 1]
            cv2.line(sub, tuple(a[0] - [c0, r0]), tuple(a[1] - [c0, r0]), _BGR["drop_hatch"], 1)
    for b in course.world.boxes:
        cv2.fillPoly(img, [cv.rect(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm)], _BGR["box"])

    seen = result.seen
    for code, color in ((PointClass.OBSTACLE, "obstacle"), (PointClass.DROPOFF, "dropoff")):
        pts = cv.px(seen[seen[:, 2] == code, :2]) if len(seen) else np.zeros((0, 2), np.int32)
        for c, r in pts:
            cv2.circle(img, (int(c), int(r)), 1, _BGR[color], -1)

    traj = result.trajectory
    chair = Chair(chair_settings)
    if len(traj):
        chair.x_mm, chair.y_mm, chair.theta_rad = traj[0, 1:4]
        cv2.polylines(img, [cv.px(chair.footprint())], True, _BGR["start"], 2)
        chair.x_mm, chair.y_mm, chair.theta_rad = traj[-1, 1:4]
        cv2.polylines(img, [cv.px(chair.footprint())], True, _BGR["end"], 2)
        cv2.polylines(img, [cv.px(traj[:, 1:3])], False, _BGR["path"], 3)
    # Course labels above the dots, on a white card, so they stay readable.
    for text, x, y in course.labels:
        c, r = cv.px(np.array([[x, y]]))[0]
        _label(img, text, int(c), int(r), centre=True)
    # Refusals: one numbered ring per place and reason, explained under the map.
    placed: list[tuple[int, int]] = []
    for n, (x, y, _, _) in enumerate(shown, 1):
        c, r = (int(v) for v in cv.px(np.array([[x, y]]))[0])
        cv2.circle(img, (c, r), 8, _BGR["refusal"], 2)
        dx = 12 + 22 * sum(1 for p in placed if abs(p[0] - c) < 20 and abs(p[1] - r) < 20)
        placed.append((c, r))
        _label(img, str(n), c + dx, r, color=_BGR["refusal"], scale=0.5, thick=2)
    for t, _ in result.contacts:
        i = min(int(np.searchsorted(traj[:, 0], t)), len(traj) - 1)
        c, r = cv.px(traj[i, 1:3])[0]
        cv2.drawMarker(img, (int(c), int(r)), _BGR["contact"], cv2.MARKER_TILTED_CROSS, 18, 3)

    legend = [
        ("path", "path"),
        ("start", "chair at start"),
        ("end", "at end"),
        ("obstacle", "obstacle seen"),
        ("dropoff", "drop-off seen"),
        ("refusal", "refused (n)"),
        ("contact", "collision/fall"),
    ]
    y = cv.map_h + 8
    x = 10
    for key, text in legend:
        if x + 18 + cv2.getTextSize(text, font, 0.42, 1)[0][0] > cv.w - 5:  # wrap the legend
            x, y = 10, y + 18
        cv2.circle(img, (x + 5, y), 5, _BGR[key], -1)
        cv2.putText(img, text, (x + 13, y + 5), font, 0.42, _BGR["text"], 1, cv2.LINE_AA)
        x += 18 + cv2.getTextSize(text, font, 0.42, 1)[0][0] + 8
    scale_px = round(1000 * cv.s)
    y += 22
    cv2.line(img, (10, y), (10 + scale_px, y), _BGR["text"], 2)
    cv2.putText(img, "1 m", (16 + scale_px, y + 4), font, 0.42, _BGR["text"], 1, cv2.LINE_AA)
    n_contacts = len(result.contacts)
    verdict = (
        f"{n_contacts} collision(s)/fall(s)"
        if n_contacts
        else f"no contact, closest {result.min_clearance_mm:.0f} mm"
    )
    cv2.putText(img, f"{result.duration_s:.0f} s simulated, {verdict}", (30 + scale_px + 40, y + 4),
                font, 0.42, _BGR["contact"] if n_contacts else _BGR["text"], 1, cv2.LINE_AA)  # fmt: skip
    for n, (_, _, times, text) in enumerate(shown, 1):
        y += 18
        when = ", ".join(f"{t:.1f}" for t in times[:4]) + (", ..." if len(times) > 4 else "")
        line = f"{n}  t = {when} s: {text}"
        cv2.putText(img, line, (10, y + 4), font, 0.42, _BGR["refusal"], 1, cv2.LINE_AA)
    if len(groups) > len(shown):
        y += 18
        more = f"... {len(groups) - len(shown)} more places (report.md lists every refusal)"
        cv2.putText(img, more, (10, y + 4), font, 0.42, _BGR["text"], 1, cv2.LINE_AA)
    out = Path(path)
    if not cv2.imwrite(str(out), img):
        raise OSError(f"{out}: cannot write the PNG")
    return out


_MAX_GROUPS = 8


def refusal_groups(
    result: SimResult, near_mm: float = 150.0
) -> list[tuple[float, float, list[float], str]]:
    """Refusals grouped by place and text: ``(x_mm, y_mm, times_s, text)`` in order of first
    occurrence; a refusal joins a group with the same text whose place is within ``near_mm``."""
    traj = result.trajectory
    groups: list[tuple[float, float, list[float], str]] = []
    if not len(traj):
        return groups
    for t, text in result.refusals:
        i = min(int(np.searchsorted(traj[:, 0], t)), len(traj) - 1)
        x, y = float(traj[i, 1]), float(traj[i, 2])
        for gx, gy, times, gtext in groups:
            if gtext == text and math.hypot(gx - x, gy - y) <= near_mm:
                times.append(t)
                break
        else:
            groups.append((x, y, [t], text))
    return groups


def _label(
    img: NDArray[np.uint8],
    text: str,
    c: int,
    r: int,
    centre: bool = False,
    color: tuple[int, int, int] = _BGR["text"],
    scale: float = 0.42,
    thick: int = 1,
) -> None:
    """``text`` at column ``c``, row ``r`` (left end, or centre) on a white card."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (w, h), base = cv2.getTextSize(text, font, scale, thick)
    x0 = c - w // 2 if centre else c
    y0 = r + h // 2
    cv2.rectangle(img, (x0 - 3, y0 - h - 3), (x0 + w + 3, y0 + base), (255, 255, 255), -1)
    cv2.rectangle(img, (x0 - 3, y0 - h - 3), (x0 + w + 3, y0 + base), (190, 190, 190), 1)
    cv2.putText(img, text, (x0, y0), font, scale, color, thick, cv2.LINE_AA)


def summary_lines(result: SimResult) -> list[str]:
    """The figures of a run as Markdown list items."""
    t = result.timings
    lines = [
        f"- simulated time: {result.duration_s:.1f} s in {t.get('wall_s', 0):.1f} s wall "
        f"({t.get('realtime_factor', 0):.1f}x real time)",
        f"- distance driven: {result.distance_mm / 1000:.2f} m",
        f"- collisions: {len(result.collisions)}, falls: {len(result.falls)}",
        f"- closest approach of the footprint to a box or of a wheel to a drop-off: "
        f"{result.min_clearance_mm:.0f} mm",
        f"- refusals by the daemon: {len(result.refusals)}",
        f"- perception: {int(t.get('perception_cycles', 0))} cycles, "
        f"{t.get('perception_mean_ms', 0):.1f} ms mean, {t.get('perception_max_ms', 0):.1f} ms max",
        f"- control step: {t.get('control_step_mean_ms', 0):.3f} ms mean, "
        f"{t.get('control_step_max_ms', 0):.3f} ms max",
        f"- control-unit watchdog trips: {int(t.get('watchdog_trips', 0))}",
    ]
    return lines


#: The demo story's checked steps (:func:`omnid.sim.story.demo_story`): step, the reason its
#: refusal must name, and where the thing refused stands in the built-in course — the refusal
#: counts only if the chair stood within ``_NEAR_MM`` of it (not a phantom elsewhere).
_NEAR_MM = 700.0


def _near_narrow(pose: tuple[float, float, float]) -> tuple[bool, str]:
    front = pose[0] + ChairSettings().footprint_front_mm * math.cos(pose[2])
    gap = 3800.0 - front  # partition B's face
    return 0.0 <= gap <= _NEAR_MM, f"footprint front {gap:.0f} mm before the narrow passage"


def _near_stairs(pose: tuple[float, float, float]) -> tuple[bool, str]:
    front = pose[1] + ChairSettings().footprint_front_mm * math.sin(pose[2])
    gap = front - (-1700.0)  # the stairs' edge
    return 0.0 <= gap <= _NEAR_MM, f"footprint front {gap:.0f} mm before the stairs' edge"


def _near_box3(pose: tuple[float, float, float]) -> tuple[bool, str]:
    dx = max(2100.0 - pose[0], 0.0, pose[0] - 2400.0)
    dy = max(-1100.0 - pose[1], 0.0, pose[1] - (-700.0))
    d = math.hypot(dx, dy)
    reach = math.hypot(ChairSettings().footprint_front_mm, ChairSettings().footprint_width_mm / 2)
    # the turn sweeps the front corners (radius ``reach``): refused within the stop line's reach
    return d - reach <= 300.0, f"box 3 {d:.0f} mm from the axle (corner reach {reach:.0f} mm)"


_CHECKED = (
    ("on to the narrow passage", "narrow passage refused", "obstacle_stop", _near_narrow),
    ("forward towards the stairs", "stopped before the stairs", "dropoff_stop", _near_stairs),
    # box 3 beside the chair or the stairs' edge the front corner swings towards: from the map
    ("turn right, towards box 3", "turn towards box 3 refused", "_stop", _near_box3),
)


def story_checks(result: SimResult) -> list[tuple[str, bool, str]]:
    """The demo's story, checked against the run: ``(step, happened, evidence)``, from the
    reactive rider's step records (:attr:`SimResult.story`): each refusal must have ended its
    step, name the right reason and come where the thing refused stands."""
    traj = result.trajectory
    x_max = float(traj[:, 1].max()) if len(traj) else 0.0
    rear_mm = ChairSettings().footprint_rear_mm
    steps = [
        ("through the wide passage", x_max - rear_mm > 2000.0, f"axle reached x = {x_max:.0f} mm"),
    ]
    records = {r.what: r for r in result.story}
    for step, what, reason, near in _CHECKED:
        rec = records.get(step)
        if rec is None:
            steps.append((what, False, f"step {step!r} never ended"))
            continue
        ok_place, place = near(rec.pose_mm_rad)
        ok = rec.ended == "done" and reason in rec.evidence and ok_place
        steps.append((what, ok, f"{rec.evidence}; {place}"))
    n = len(result.contacts)
    steps.append(
        (
            "no collision, no fall",
            n == 0,
            f"{n} contacts, closest approach {result.min_clearance_mm:.0f} mm",
        )
    )
    return steps


def write_report(
    out_dir: str | Path,
    course: Course,
    result: SimResult,
    title: str,
    notes: list[str] | None = None,
    chair_settings: ChairSettings | None = None,
    story: bool = False,
) -> Path:
    """Write ``report.md`` and ``course.png`` into ``out_dir``; returns the report's path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    draw_run(out / "course.png", course, result, chair_settings)
    lines = [f"# {title}", "", *(notes or []), ""]
    if story:
        lines += ["## Story", ""]
        lines += [
            f"- [{'x' if ok else ' '}] {what} — {ev}" for what, ok, ev in story_checks(result)
        ]
        lines += [
            "",
            "The rider's steps (each ends when the rider sees it done, or times out):",
            "",
        ]
        lines += ["| step | from | to | ended | how |", "| --- | --- | --- | --- | --- |"]
        lines += [
            f"| {r.what} | {r.t0_s:.1f} s | {r.t1_s:.1f} s | {r.ended} | {r.evidence} |"
            for r in result.story
        ]
        lines.append("")
    lines += ["## Figures", "", *summary_lines(result), ""]
    lines += ["![course](course.png)", ""]
    if result.contacts:
        lines += ["## Collisions and falls", ""]
        lines += [f"- t = {t:.2f} s: {c.kind} ({c.part})" for t, c in result.contacts]
        lines.append("")
    if result.refusals:
        lines += ["## Refusals (time, command, reasons)", ""]
        shown = result.refusals[:40]
        lines += [f"- t = {t:.2f} s: {msg}" for t, msg in shown]
        if len(result.refusals) > len(shown):
            lines.append(f"- ... and {len(result.refusals) - len(shown)} more")
        lines.append("")
    path = out / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path
