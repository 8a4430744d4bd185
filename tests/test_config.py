"""The typed configuration loader names the key of every error."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from omnid.config import from_mapping, load, require, to_mapping
from omnid.errors import ConfigError


@dataclass(frozen=True)
class Zone:
    stop_distance_mm: float = 300.0
    slow_distance_mm: float = 800.0

    def __post_init__(self) -> None:
        require(self.stop_distance_mm > 0, "stop_distance_mm", "must be positive")
        require(
            self.slow_distance_mm >= self.stop_distance_mm,
            "slow_distance_mm",
            "must not be below stop_distance_mm",
        )


@dataclass(frozen=True)
class Top:
    rate_hz: int = 50
    mode: Literal["tilt", "joystick"] = "tilt"
    offsets_deg: tuple[float, float] = (0.0, 0.0)
    device: str | None = None
    zone: Zone = field(default_factory=Zone)


def test_defaults_and_values():
    cfg = from_mapping(
        Top, {"rate_hz": 25, "zone": {"stop_distance_mm": 200}, "offsets_deg": [1, 2]}
    )
    assert cfg.rate_hz == 25 and cfg.zone.stop_distance_mm == 200.0
    assert cfg.offsets_deg == (1.0, 2.0) and cfg.mode == "tilt"
    assert from_mapping(Top, to_mapping(cfg)) == cfg


@pytest.mark.parametrize(
    ("data", "key"),
    [
        ({"rate_hz": "fast"}, "rate_hz"),
        ({"rate_hz": 2.5}, "rate_hz"),
        ({"rate_hz": True}, "rate_hz"),
        ({"mode": "voice"}, "mode"),
        ({"zone": {"stop_distanse_mm": 3}}, "zone.stop_distanse_mm"),
        ({"zone": {"stop_distance_mm": -3}}, "zone.stop_distance_mm"),
        ({"zone": {"slow_distance_mm": 10}}, "zone.slow_distance_mm"),
        ({"zone": {"stop_distance_mm": float("nan")}}, "zone.stop_distance_mm"),
        ({"offsets_deg": [1]}, "offsets_deg"),
        ({"zone": 5}, "zone"),
        ({"extra": 1}, "extra"),
    ],
)
def test_errors_name_the_key(data, key):
    with pytest.raises(ConfigError) as info:
        from_mapping(Top, data)
    assert str(info.value).startswith(key + ":")


def test_load_reports_file_and_line(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("rate_hz: [1,\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load(Top, bad)
    good = tmp_path / "good.yaml"
    good.write_text("top:\n  zone:\n    stop_distance_mm: 250\n")
    assert load(Top, good, section="top").zone.stop_distance_mm == 250.0
    with pytest.raises(ConfigError, match="missing.yaml"):
        load(Top, tmp_path / "missing.yaml")
