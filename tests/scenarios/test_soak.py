"""Soak (issue 6): random riding in a cluttered room, the daemon core at its configured rates:
2 simulated minutes in CI (the pytest option ``--soak-minutes``; the half hour, about a minute
of wall time: ``python -m pytest tests/scenarios/test_soak.py --soak-minutes 30``).

The rider uses a joystick (the one input that can reverse) and does what a rider does: drives
on, arcs, turns in place, reverses out when the chair refuses, pauses (``random_ride``). The
daemon core runs exactly as configured: control at ``control.rate_hz`` (50 Hz: 3 000 steps a
minute), perception cycles at ``perception.period_s`` (0.5 s: 120 a minute) through the real
laser-off/mask/laser-on/base cycle (``perception.capture: stationary``; the shipped stream
capture would be 1 200 clouds a minute), joystick read every 20 ms.

Perception is ``truth`` (the laser dots of the simulator's default physical laser cast into the
world with their true classes, 3 mm noise), not the rendered-image pipeline, to fit CI
(``ControlCore.step`` 0.15 ms mean with the closed-form safety sweep); ``python tools/soak.py
--rider --minutes 30 --perception pipeline`` runs a rider soak with images.

The safety layer's escape moves are switched on (``safety.escape_speed_mm_s: 40``; off by
default): with them the chair creeps out of the pocket between the first three boxes where the
stop rule alone strands it. And it crosses unseen space at creep speed (``safety.unknown_policy:
creep``; the shipped policy is ``refuse``): this rider never looks where it goes, and with the
refuse policy it strands the chair within ten minutes beside floor the laser never saw; the soak
is about the loop running on, not about that policy (the scenario suite is:
tools/safety_figures.py --suite, docs/benchmarks.md). Creeping, it may turn or back into a box it
never saw: the simulator blocks the chair (``Chair.press_log``: each contact's start and end).

Asserted: no fall; every contact at creep speed, pressing at most 1.5 s (duty 0 or a move away by
then), and every press long enough for the clocks to tell a held wheel from a free one (the bump
detector replayed on the press's duties says when) counted as a bump by then. The clocks cannot
always tell within 1.5 s: a wheel asked for 11 mm/s passes a hole every 2.9 s, and a wheel that
may need 0.05 duty to break away gives no sure travel at the duty that speed takes (docs/daemon.md
"Bumps"); such a press ends by the daemon refusing, the rider letting go, or a bump later — the
1.5 s bound holds it. The chair moves on
(over 1.5 rad of heading, and somewhere new — 300 mm from where it began — in two of three
windows, a third of the run each), every refusal carries the safety layer's named reasons and
each was logged, and no memory growth: memory is sampled up to 120 times a run (at the
simulator's progress reports, one a simulated second), and after a warm-up of a third of the
run Python's allocated blocks grow by under 1000 a minute (one leaked object per control step
is 3000) and resident memory, trimmed, by under 1 MB per simulated minute (50 kB
for the half hour). Both hold whatever the process ran before: run alone, a fresh process's
heap still settles during the short run, which a slope of resident memory alone took for a leak.

Not met (issue 13), measured with the swing model (2026-12-02): ``--soak-minutes 30`` passes
at rider seed 7 (19.5 m, reaches 2908/3796/2468 mm in the three windows, 2 contacts, 1 counted
as a bump); seeds 3 and 11 (run by hand, same setup) wedge in the last window (reaches
5201/205/279 and 2437/1836/0 mm). Seed 11's wedge: having crept over unseen floor, the tail's
corner stands 10 mm from a wall that runs across behind it and a box is 50 mm ahead; every move
the rider asks is refused: reversing closes on the wall, forward arcs trade the margin to the box,
a left turn drives the corner into the wall, and the right turn that would open it fails the
escape test point by point (the corner's noisy wall points dip the gap by more than
``escape_tolerance_mm``; a wall point behind the tail comes nearer inside the margin).
docs/benchmarks.md, "The soak wedge". The shipped policy (refuse the unseen) would not have
crept there.
"""

from __future__ import annotations

import ctypes
import logging
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from omnid.daemon.motion import StallDetector
from omnid.daemon.safety import Reason
from omnid.sim.rider import random_ride
from omnid.sim.simulator import Simulator
from omnid.sim.suite import soak_core, soak_course, soak_settings


def _libc_trim() -> Callable[[int], object]:
    """glibc's ``malloc_trim(0)``: gives the heap's free pages back, so that resident memory
    counts what is in use, not what a fresh process's heap left free behind it (no-op elsewhere)."""
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return lambda _pad: None


_TRIM = _libc_trim()


def _memory() -> tuple[float, int]:
    """Resident memory (MB, after a trim) and Python's allocated blocks (every object, an
    array's header too, whatever the process ran before)."""
    _TRIM(0)
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * 4096 / 2**20, sys.getallocatedblocks()


class _ReasonsLogged(logging.Handler):
    """Keeps the reason code that heads each log line (``obstacle_stop: ...``): a bounded set,
    unlike pytest's caplog, whose growing record list would show up in the RSS slope below."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.reasons: set[str] = set()

    def emit(self, record: logging.LogRecord) -> None:
        self.reasons.add(record.getMessage().partition(":")[0])


@pytest.mark.slow(seconds=22)
def test_soak_random_riding_at_the_configured_rates(request):
    duration_s = 60.0 * float(request.config.getoption("--soak-minutes"))
    # the map's working set (its blocking evidence, kept points) grows while the chair explores
    # the room — bounded by the map's extent, not a leak: the slope is taken after it has
    warm_up_s = window_s = duration_s / 3.0
    sample_s = duration_s / 120.0  # (the progress reports come one a simulated second)
    handler = _ReasonsLogged()
    daemon_log = logging.getLogger("omnid.daemon")
    daemon_log.addHandler(handler)
    old_level = daemon_log.level
    daemon_log.setLevel(logging.WARNING)
    # pytest's own log capture keeps every record of a test: that list would be measured as
    # the daemon's memory (two refusal lines a second for 30 minutes); the records go to the
    # bounded handler above only
    old_propagate, daemon_log.propagate = daemon_log.propagate, False
    rss: list[tuple[float, float, int]] = []

    def sample(now_s: float, _sim: Simulator) -> None:
        if not rss or now_s >= rss[-1][0] + sample_s:
            rss.append((now_s, *_memory()))

    # escape moves on and the unseen crossed at creep speed (omnid.sim.suite.SOAK_SAFETY), on
    # the thesis' stationary capture (a cloud every 0.5 s, staleness 1.5 s), not the shipped
    # stream: the half hour is about the loop and its memory, and 36 000 stream clouds (each
    # a map update) do not fit CI; tools/soak.py runs the shipped configuration
    core = soak_core()
    sim = Simulator(
        soak_course(),
        core,
        soak_settings(),
        joystick=random_ride(7, duration_s),
        progress=sample,
    )
    assert sim.settings.control_period_s == core.config.control.period_s  # type: ignore[attr-defined]
    assert sim.settings.perception_period_s == core.config.perception.period_s  # type: ignore[attr-defined]
    try:
        result = sim.run(duration_s)
    finally:
        daemon_log.removeHandler(handler)
        daemon_log.setLevel(old_level)
        daemon_log.propagate = old_propagate
    assert result.duration_s >= duration_s - 1.0
    assert result.falls == []
    # Contacts only by creeping into the unseen, and no sustained push. A contact lasts from the
    # step that pressed into a box to the first that no longer did (duty 0 or away from it).
    cmds = result.commands
    w = result.wheel_speeds
    creep = core.config.safety.unknown_creep_speed_mm_s  # type: ignore[attr-defined]
    motion = core.config.motion  # type: ignore[attr-defined]
    presses = list(sim.chair.press_log)
    if sim.chair.blocked_by:
        presses.append((sim.chair.bump_log[-1][0], result.duration_s))
    assert len(presses) == len(sim.chair.bump_log)
    for t_contact, t_free in presses:
        before = w[(w[:, 0] > t_contact - 0.3) & (w[:, 0] < t_contact - 0.05)]
        # it was creeping (the wheel PI overshoots its target by up to a quarter at this speed)
        assert np.abs(before[:, 1:]).max() <= creep * 1.35, t_contact
        # it pressed at most 1.5 s (duty 0 or a move away by then)
        assert t_free - t_contact <= 1.5, (t_contact, t_free)
        # and a press the clocks could tell from a free wheel was noticed: the bump detector,
        # replayed on the press's duties from the contact with the wheels held (as if a hole had
        # just passed), says when the clocks could first know; the daemon counted a bump by then
        held = StallDetector(motion)
        press = cmds[(cmds[:, 0] >= t_contact - 0.02) & (cmds[:, 0] <= t_free)]
        knowable = [t for t, dl, dr, _, _ in press if any(held.on_status(0, 0, t, (dl, dr)))]
        if knowable:
            assert any(knowable[0] - 0.1 <= t <= t_free for t in core.bump_times), (
                t_contact,
                knowable[0],
                list(core.bump_times),
            )
    # The chair is not stranded: in a pocket the safety layer lets it creep out by the moves
    # that open the gap (reason escape_creep), so it keeps going for the whole half hour.
    traj = result.trajectory
    assert result.distance_mm > 2_000.0, result.distance_mm
    # It turned and reversed, not only drove ahead.
    assert np.ptp(traj[:, 3]) > 1.5, np.ptp(traj[:, 3])
    # Somewhere new: in two of the three windows (a third of the run each) the chair gets at least 300 mm from
    # where it started that window. (This rider asks blindly; in a dense room it can wedge the
    # chair where every move it asks is refused or creeps for a while — the scenario suite
    # counts that as false stops. A third of the time is the slack for one such wedge.)
    reaches = []
    for t0 in np.arange(0.0, duration_s - 1.0, window_s):
        win = traj[(traj[:, 0] >= t0) & (traj[:, 0] < t0 + window_s)]
        reaches.append(np.hypot(win[:, 1] - win[0, 1], win[:, 2] - win[0, 2]).max())
    assert sum(r > 300.0 for r in reaches) >= 2, reaches
    # Memory: the slopes after the warm-up (least squares over the samples). Objects: a leak of
    # one object every third control step is 1000 blocks a minute; the simulator's own records
    # and the map's working set add ~200 (measured in a fresh process). Resident memory: in a
    # fresh process the heap still settles in the short run (0.3-0.4 MB a minute, with no
    # object or array more: a warm pytest worker shows none of it), so the short run bounds
    # native leaks (cv2's buffers) at 1 MB a minute, 330 B a control step; the half hour at 0.05.
    mem = np.array([row for row in rss if row[0] >= warm_up_s])
    assert len(mem) >= 50, rss
    blocks_per_min = np.polyfit(mem[:, 0] / 60.0, mem[:, 2], 1)[0]
    assert blocks_per_min < 1000.0, (blocks_per_min, " ".join(f"{int(b)}" for *_, b in rss))
    slope_mb_per_min = np.polyfit(mem[:, 0] / 60.0, mem[:, 1], 1)[0]
    assert slope_mb_per_min < (0.05 if duration_s >= 1800.0 else 1.0), (
        slope_mb_per_min,
        " ".join(f"{m:.1f}" for _, m, _ in rss),
    )
    # Every refusal carries its reasons, each one the safety layer's named code, and the core
    # logged each reason it refused for.
    known = {r.value for r in Reason}
    assert result.refusals
    logged = " ".join(sorted(handler.reasons))
    for _, text in result.refusals:
        head, _, reasons = text.partition(": ")
        assert head.startswith("refused ") and reasons
        for reason in reasons.split(", "):
            assert reason in known
            assert reason in logged
