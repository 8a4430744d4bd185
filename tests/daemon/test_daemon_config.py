"""OmnidConfig: the shipped file is complete and valid; errors name file and key; reload."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from omnid.config import to_mapping
from omnid.daemon.config import ConfigHolder, OmnidConfig, load_config
from omnid.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "etc" / "omnid.yaml"
DAEMON_SECTIONS = (
    "control",
    "rider",
    "safety",
    "motion",
    "perception",
    "freespace",
    "control_unit",
    "camera",
    "teleop",
    "tilt_sensor",
    "joystick_device",
    "service",
)


def keys(tree, prefix=""):
    out = set()
    for k, v in tree.items():
        out.add(prefix + k)
        if isinstance(v, dict):
            out |= keys(v, prefix + k + ".")
    return out


def test_shipped_file_is_valid_and_lists_every_daemon_key():
    cfg = load_config(SHIPPED)
    # the file documents the defaults, except the devices' stable udev names, the neutral-pose
    # calibration at start and re-arming after a fault (on for a real rider; off for
    # clock-injected users)
    assert cfg.control_unit.port == "/dev/omnid-control-unit"
    assert cfg.camera.url == "v4l2:///dev/omnid-camera1,/dev/omnid-camera2"
    assert cfg.rider.tilt.neutral_calibration_s == 3.0
    d = OmnidConfig()
    assert (
        replace(
            cfg,
            control_unit=replace(cfg.control_unit, port=d.control_unit.port),
            camera=replace(cfg.camera, url=d.camera.url),
            rider=replace(cfg.rider, tilt=d.rider.tilt),
            control=replace(cfg.control, rearm_after_fault=False),
        )
        == d
    )
    assert cfg.control.rearm_after_fault
    assert replace(cfg.rider.tilt, neutral_calibration_s=0.0) == d.rider.tilt
    shipped = keys(yaml.safe_load(SHIPPED.read_text()))
    defaults = keys({s: to_mapping(getattr(OmnidConfig(), s)) for s in DAEMON_SECTIONS})
    assert defaults <= shipped


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("safety:\n  stop_distanse_mm: 100\n", "safety.stop_distanse_mm"),
        ("motion:\n  accel_mm_s2: fast\n", "motion.accel_mm_s2"),
        ("rider:\n  tilt:\n    threshold_deg: 90\n", "rider.tilt.threshold_deg"),
        ("perception:\n  method: magic\n", "perception.method"),
        ("control:\n  rate_hz: 0\n", "control.rate_hz"),
        ("bogus: 1\n", "bogus"),
    ],
)
def test_errors_name_file_and_key(tmp_path, text, key):
    p = tmp_path / "omnid.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert str(p) in str(err.value) and key in str(err.value)
    assert "\n" not in str(err.value)


def test_reload_keeps_old_config_when_new_is_invalid(tmp_path):
    p = tmp_path / "omnid.yaml"
    p.write_text("control:\n  rate_hz: 40\n")
    holder = ConfigHolder(p)
    assert holder.config.control.rate_hz == 40.0
    p.write_text("control:\n  rate_hz: 40\n  typo: 1\n")
    ok, why = holder.reload()
    assert not ok and "control.typo" in why
    assert holder.config.control.rate_hz == 40.0
    p.write_text("control: [unclosed\n")
    assert holder.reload()[0] is False
    p.write_text("control:\n  rate_hz: 25\n")
    assert holder.reload() == (True, "reloaded")
    assert holder.config.control.rate_hz == 25.0


def test_missing_file_is_one_line_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")
