"""Rider commands: thresholds, neutral offsets, hysteresis, dwell, stop priority, mux timeouts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from omnid.config import from_mapping
from omnid.daemon.rider import (
    Intent,
    JoystickSettings,
    RiderMux,
    RiderSettings,
    TiltInterpreter,
    TiltSettings,
    neutral_from_samples,
)
from omnid.errors import ConfigError


@dataclass(frozen=True)
class Tilt:
    roll_deg: float
    pitch_deg: float
    timestamp_s: float


@dataclass(frozen=True)
class Stick:
    forward: float
    turn: float
    timestamp_s: float


def feed(interp: TiltInterpreter, roll: float, pitch: float, t0: float, t1: float) -> Intent:
    intent = interp.active
    for t in np.arange(t0, t1, 0.01):
        intent = interp.update(roll, pitch, float(t))
    return intent


def settings(**kw) -> TiltSettings:
    base = dict(
        threshold_deg=12.0, release_deg=8.0, dwell_s=0.3, neutral_calibration_s=0.0, timeout_s=0.2
    )
    base.update(kw)
    return TiltSettings(**base)


@pytest.mark.parametrize(
    ("roll", "pitch", "expected"),
    [
        (-20.0, 0.0, Intent.FORWARD),
        (20.0, 0.0, Intent.STOP),
        (0.0, -20.0, Intent.RIGHT),
        (0.0, 20.0, Intent.LEFT),
        (5.0, -5.0, Intent.NONE),  # dead zone
    ],
)
def test_thesis_thresholds(roll, pitch, expected):
    interp = TiltInterpreter(settings())
    assert feed(interp, roll, pitch, 0.0, 0.5) is expected


def test_motion_needs_dwell_but_stop_is_immediate():
    interp = TiltInterpreter(settings(dwell_s=0.3))
    assert feed(interp, -20.0, 0.0, 0.0, 0.25) is Intent.NONE
    assert feed(interp, -20.0, 0.0, 0.25, 0.35) is Intent.FORWARD
    assert interp.update(20.0, 0.0, 0.36) is Intent.STOP  # one reading is enough


def test_short_involuntary_nod_does_not_drive():
    interp = TiltInterpreter(settings(dwell_s=0.3))
    feed(interp, -20.0, 0.0, 0.0, 0.2)
    feed(interp, 0.0, 0.0, 0.2, 0.3)  # back to neutral: dwell restarts
    assert feed(interp, -20.0, 0.0, 0.3, 0.5) is Intent.NONE


def test_hysteresis_holds_command_between_release_and_threshold():
    interp = TiltInterpreter(settings(dwell_s=0.0))
    assert interp.update(-13.0, 0.0, 0.0) is Intent.FORWARD
    assert interp.update(-9.0, 0.0, 0.01) is Intent.FORWARD  # inside T but past release
    assert interp.update(-7.0, 0.0, 0.02) is Intent.NONE  # inside release: released
    assert interp.update(-9.0, 0.0, 0.03) is Intent.NONE  # must pass T again to re-enter


def test_neutral_offsets_shift_thresholds():
    interp = TiltInterpreter(settings(dwell_s=0.0, roll_offset_deg=-10.0))
    assert interp.update(-15.0, 0.0, 0.0) is Intent.NONE  # only −5° from neutral
    assert interp.update(-23.0, 0.0, 0.01) is Intent.FORWARD
    off = neutral_from_samples([3.0, 3.2, 40.0, 2.9, 3.1], [-1.0, -1.0, -1.0, 10.0, -1.1])
    assert off == pytest.approx((3.1, -1.0))
    interp.set_neutral(*off)
    assert interp.active is Intent.NONE
    with pytest.raises(ValueError):
        neutral_from_samples([], [])


def test_latch_mode_keeps_forward_until_stop():
    interp = TiltInterpreter(settings(dwell_s=0.0, forward_mode="latch"))
    interp.update(-20.0, 0.0, 0.0)
    assert interp.update(0.0, 0.0, 0.1) is Intent.FORWARD
    assert interp.update(20.0, 0.0, 0.2) is Intent.STOP
    assert interp.update(0.0, 0.0, 0.3) is Intent.NONE


def test_nan_reading_is_a_stop():
    interp = TiltInterpreter(settings(dwell_s=0.0))
    interp.update(-20.0, 0.0, 0.0)
    assert interp.update(float("nan"), 0.0, 0.01) is Intent.STOP


def test_settings_refuse_release_above_threshold():
    with pytest.raises(ConfigError, match="release_deg"):
        from_mapping(TiltSettings, {"threshold_deg": 10, "release_deg": 12})
    with pytest.raises(ConfigError, match="priority"):
        from_mapping(RiderSettings, {"priority": ["tilt", "tilt", "keyboard"]})


def drive_tilt(mux: RiderMux, roll: float, pitch: float, t0: float, t1: float) -> None:
    for t in np.arange(t0, t1, 0.01):
        mux.on_tilt(Tilt(roll, pitch, float(t)))


def test_mux_tilt_drives_and_goes_stale():
    mux = RiderMux(RiderSettings(tilt=settings(dwell_s=0.1, timeout_s=0.2)))
    assert mux.decide(0.0).reason == "tilt_stale"  # never heard from
    drive_tilt(mux, -20.0, 0.0, 0.0, 0.5)
    d = mux.decide(0.5)
    assert d.moving and d.forward > 0 and d.source == "tilt"
    d = mux.decide(0.75)  # last reading at 0.49 s: 0.26 s of silence
    assert d.stop and d.reason == "tilt_stale"


def test_mux_keyboard_press_holds_then_expires():
    mux = RiderMux(RiderSettings(tilt=TiltSettings(enabled=False)))
    mux.on_key("up", 1.0)
    assert mux.decide(1.2).forward > 0
    assert not mux.decide(1.6).moving  # hold_s 0.5 elapsed
    mux.on_key("left", 2.0)
    assert mux.decide(2.1).turn > 0
    mux.on_key("right", 2.2)
    assert mux.decide(2.3).turn < 0
    with pytest.raises(ValueError):
        mux.on_key("jump", 3.0)


def test_mux_any_stop_wins_over_higher_priority_motion():
    mux = RiderMux(
        RiderSettings(tilt=settings(dwell_s=0.0), joystick=JoystickSettings(enabled=True))
    )
    drive_tilt(mux, 20.0, 0.0, 0.0, 0.1)  # head back: stop
    mux.on_joystick(Stick(1.0, 0.0, 0.09))
    d = mux.decide(0.1)
    assert d.stop and d.reason == "tilt_stop"


def test_mux_priority_joystick_over_tilt_and_joystick_timeout():
    mux = RiderMux(
        RiderSettings(tilt=settings(dwell_s=0.0), joystick=JoystickSettings(enabled=True))
    )
    drive_tilt(mux, 0.0, 20.0, 0.0, 0.1)  # tilt asks left
    mux.on_joystick(Stick(0.55, 0.0, 0.09))
    d = mux.decide(0.1)
    assert d.source == "joystick" and d.forward == pytest.approx(0.5) and d.turn == 0.0
    mux.on_joystick(Stick(0.0, 0.05, 0.1))  # centred (dead zone): tilt's left is obeyed
    assert mux.decide(0.1).source == "tilt"
    drive_tilt(mux, 0.0, 20.0, 0.1, 0.5)
    d = mux.decide(0.5)  # joystick silent for 0.4 s > 0.2 s
    assert d.stop and d.reason == "joystick_stale"


def test_mux_joystick_nan_is_stop():
    mux = RiderMux(
        RiderSettings(tilt=TiltSettings(enabled=False), joystick=JoystickSettings(enabled=True))
    )
    mux.on_joystick(Stick(float("nan"), 0.0, 0.0))
    assert mux.decide(0.01).reason == "joystick_invalid"


def test_neutral_pose_is_measured_at_start_and_retaken_when_the_head_moves():
    interp = TiltInterpreter(settings(neutral_calibration_s=1.0))
    mux = RiderMux(RiderSettings(tilt=settings(neutral_calibration_s=1.0)))
    rng = np.random.default_rng(1)
    t = 0.0
    # the head wobbles by 6° during the first second: retaken; meanwhile the source asks stop
    for _ in range(105):
        interp.update(3.0 + 6.0 * np.sin(t * 9), -2.0, t)
        mux.on_tilt(Tilt(3.0 + 6.0 * np.sin(t * 9), -2.0, t))
        t += 0.01
    assert interp.calibrating and interp.calibrations_failed == 1
    assert mux.decide(t).reason == "tilt_calibrating" and mux.decide(t).stop
    # then it holds still (0.2° noise) around roll 3°, pitch −2°: that is the neutral
    for _ in range(110):
        assert interp.update(3.0 + rng.normal(0, 0.2), -2.0 + rng.normal(0, 0.2), t) is Intent.NONE
        t += 0.01
    assert not interp.calibrating
    assert interp.roll_offset_deg == pytest.approx(3.0, abs=0.1)
    assert interp.pitch_offset_deg == pytest.approx(-2.0, abs=0.1)
    # −10° roll is only 13° from this neutral... past the 12° threshold: forward after the dwell
    assert feed(interp, -10.0, -2.0, t, t + 0.5) is Intent.FORWARD


def test_a_head_held_in_a_command_pose_does_not_become_the_neutral():
    interp = TiltInterpreter(settings(neutral_calibration_s=0.5))
    feed(interp, -18.0, 0.0, 0.0, 1.5)  # held forward the whole time: beyond 10° from level
    assert interp.calibrating and interp.calibrations_failed >= 2


def test_after_a_gap_in_readings_the_dwell_starts_afresh():
    interp = TiltInterpreter(settings())
    assert feed(interp, -20.0, 0.0, 0.0, 0.5) is Intent.FORWARD
    # unplugged for 0.5 s (> timeout_s 0.2), the head still forward when readings resume
    assert interp.update(-20.0, 0.0, 1.0) is Intent.NONE
    assert feed(interp, -20.0, 0.0, 1.01, 1.2) is Intent.NONE  # dwell not yet over
    assert feed(interp, -20.0, 0.0, 1.2, 1.4) is Intent.FORWARD
