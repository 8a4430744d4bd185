"""A SIGHUP reload is all or nothing. What the daemon built at start from its file — the
control-unit link and its command period, the control loop's rate, the camera, the perception
worker, the map, the rider devices it opened — cannot take a new value while it runs; a reload
changing one of those keys is refused, naming the key, and the old configuration keeps running
whole. It was "reloaded": the new core took e.g. control_unit.command_period_s while the link
kept sending at the old one, so a loop stall the link had already put zero on the wire for
was not seen as a stall and the chair drove on without the rider's new input."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
import pytest
import yaml
from chair_helpers import Chair, FreeFloor
from test_stale_command_fault import DT, ride

from omnid.daemon.config import ConfigHolder, restart_only_refusal
from omnid.daemon.core import ControlCore
from omnid.daemon.run import Daemon
from omnid.devices.joystick import JoystickReading

BASE = {
    "perception": {"enabled": False},
    "rider": {"tilt": {"enabled": False}, "joystick": {"enabled": True}},
}


def merged(change: dict) -> dict:
    out = yaml.safe_load(yaml.safe_dump(BASE))
    for section, values in change.items():
        node = out.setdefault(section, {})
        for k, v in values.items():
            if isinstance(v, dict):
                node.setdefault(k, {}).update(v)
            else:
                node[k] = v
    return out


def daemon(tmp_path, change: dict | None = None) -> Daemon:
    path = tmp_path / "omnid.yaml"
    path.write_text(yaml.safe_dump(merged(change or {})))
    d = Daemon(ConfigHolder(path), notifier=None)
    d.core = ControlCore(d.holder.config, world_map=FreeFloor(d.holder.config.freespace.grid))
    return d


# a valid command period of 0.1 s needs a unit watchdog of at least two of them
SLOW_LINK = {"control_unit": {"command_period_s": 0.1, "unit_watchdog_s": 0.25}}


def test_after_a_stall_the_unit_braked_through_the_chair_starts_from_rest_after_a_reload(
    tmp_path,
):
    """The link sends the unit the watchdog it was started with (250 ms): a longer loop stall
    and the unit has stopped the wheels by itself. The core must then ramp up from rest — with
    the reloaded unit_watchdog_s (1 s) it believed the wheels kept going and put the pre-stall
    speed straight back on a standing chair (a lurch to full duty)."""
    d = daemon(tmp_path)
    d.core.on_joystick(JoystickReading(0.0, 0.0, -0.02))
    d.core.step(-0.02)
    chair = Chair()
    ride(d.core, chair, 0.0, 3.0, 1.0)
    assert d.core.motion.ramp.v_mm_s > 200.0  # at full speed, the rider holds the stick
    d.holder.path.write_text(yaml.safe_dump(merged({"control_unit": {"unit_watchdog_s": 1.0}})))
    asyncio.run(d.reload())
    # the loop stalls 0.5 s; the unit's own watchdog (the link's: 250 ms) stops the wheels
    t = float(np.arange(0.0, 3.0, DT)[-1]) + 0.5
    cmds = ride(d.core, chair, t, t + 0.1, 1.0)
    top = max(max(c.left_duty, c.right_duty) for c in cmds)
    assert top < 0.3, (
        f"0.1 s after the unit stopped the wheels the chair is driven at duty {top:.2f} (core "
        f"unit_watchdog_s {d.core.config.control_unit.unit_watchdog_s} s, link "
        f"{d.link.settings.unit_watchdog_s} s)"
    )
    assert d.core.config.control_unit == d.link.settings


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (SLOW_LINK, "control_unit.command_period_s"),
        ({"control": {"rate_hz": 100.0}}, "control.rate_hz"),
        ({"motion": {"mm_per_clock": 40.0}}, "motion.mm_per_clock"),
        ({"motion": {"track_mm": 600.0}}, "motion.track_mm"),
        ({"freespace": {"obstacle_inflation_mm": 100.0}}, "freespace.obstacle_inflation_mm"),
        ({"freespace": {"grid": {"resolution_mm": 25.0}}}, "freespace.grid.resolution_mm"),
        ({"perception": {"enabled": True}}, "perception.enabled"),
        ({"detection": {"best_snr": 4.0}}, "detection.best_snr"),
        ({"rider": {"tilt": {"enabled": True}}}, "rider.tilt.enabled"),
        ({"rider": {"joystick": {"enabled": False}}}, "rider.joystick.enabled"),
        ({"camera": {"frame_latency_s": 0.01}}, "camera.frame_latency_s"),
        ({"tilt_sensor": {"port": "/dev/ttyUSB7"}}, "tilt_sensor.port"),
        ({"joystick_device": {"stale_after_s": 0.5}}, "joystick_device.stale_after_s"),
        ({"teleop": {"max_clients": 2}}, "teleop.max_clients"),
        (
            {"control_unit": {"rs485": {"rts_level_for_tx": True}}},
            "control_unit.rs485",
        ),
        # the recorder and its live view are opened at start: "reloaded" kept the old ones
        ({"record": {"max_file_mb": 64.0}}, "record.max_file_mb"),
        ({"record": {"view": "127.0.0.1:8770"}}, "record.view"),
    ],
    ids=lambda v: v if isinstance(v, str) else None,
)
def test_a_reload_changing_what_only_a_restart_applies_is_refused_naming_the_key(
    tmp_path, caplog, change, key
):
    d = daemon(tmp_path)
    core, config = d.core, d.holder.config
    d.holder.path.write_text(yaml.safe_dump(merged({**change, "safety": {"margin_mm": 80.0}})))
    with caplog.at_level(logging.ERROR):
        assert asyncio.run(d.reload()) is False
    assert d.core is core and d.holder.config == config  # the old one, whole
    assert d.config.safety.margin_mm == 50.0  # the live part waits too: nothing half applied
    refused = [r.getMessage() for r in caplog.records if "reload refused" in r.getMessage()]
    assert refused and key in refused[0] and "restart" in refused[0], refused
    assert "\n" not in refused[0]


def test_a_reload_of_live_settings_still_applies(tmp_path):
    d = daemon(tmp_path)
    d.holder.path.write_text(
        yaml.safe_dump(
            merged(
                {
                    "safety": {"margin_mm": 80.0},
                    "motion": {"max_speed_mm_s": 200.0},
                    "control": {"status_timeout_s": 0.3},
                    "rider": {"keyboard": {"hold_s": 0.4}},
                    "service": {"status_period_s": 2.0},
                }
            )
        )
    )
    assert asyncio.run(d.reload()) is True
    cfg = d.config
    assert cfg.safety.margin_mm == 80.0 and cfg.motion.max_speed_mm_s == 200.0
    assert cfg.control.status_timeout_s == 0.3 and cfg.rider.keyboard.hold_s == 0.4
    assert d.holder.config == cfg


def test_a_reloaded_speed_window_reaches_the_kept_odometry(tmp_path):
    """The odometry outlives a reload (pose, clock reference); its motion settings must be the
    new ones: it kept the start file's speed_window_s, so the wheel PI went on measuring over
    the old window after 'reloaded'."""
    d = daemon(tmp_path)
    d.core.on_joystick(JoystickReading(0.0, 0.0, -0.02))
    d.core.step(-0.02)
    chair = Chair()
    ride(d.core, chair, 0.0, 2.0, 1.0)
    pose = d.core.odometry.pose.copy()
    d.holder.path.write_text(yaml.safe_dump(merged({"motion": {"speed_window_s": 0.2}})))
    assert asyncio.run(d.reload()) is True
    assert (d.core.odometry.pose == pose).all()  # kept
    assert d.core.odometry.settings == d.core.config.motion, (
        f"odometry measures over {d.core.odometry.settings.speed_window_s} s after the reload"
    )
    ride(d.core, chair, 2.0, 2.3, 1.0)  # and goes on from where it was (no jump)
    assert 0.0 < d.core.odometry.pose[0] - pose[0] < 0.3 * 260.0


def test_the_command_lines_recording_outlives_a_reload_and_is_no_change(tmp_path):
    """``omnid run --record FILE`` overrides ``record.path``: a reload is compared with the
    override applied to the new file too, so it neither counts as a change of the
    restart-only ``record`` section (every reload refused) nor drops the override."""
    import dataclasses

    path = tmp_path / "omnid.yaml"
    path.write_text(yaml.safe_dump(merged({})))

    def cli(cfg):
        return dataclasses.replace(cfg, record=dataclasses.replace(cfg.record, path="ride.mcap"))

    holder = ConfigHolder(path, cli)
    assert holder.config.record.path == "ride.mcap"
    path.write_text(yaml.safe_dump(merged({"safety": {"margin_mm": 80.0}})))
    assert holder.reload(check=restart_only_refusal) == (True, "reloaded")
    assert holder.config.record.path == "ride.mcap" and holder.config.safety.margin_mm == 80.0
    path.write_text(yaml.safe_dump(merged({"record": {"max_file_mb": 64.0}})))
    ok, why = holder.reload(check=restart_only_refusal)
    assert not ok and "record.max_file_mb" in why
    assert holder.config.record.max_file_mb == 256.0 and holder.config.safety.margin_mm == 80.0
