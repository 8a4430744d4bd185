"""Rigs, lasers and spot models named on a command line: a preset, a random draw, or a file.

One grammar for all three (``omnid scene --rig/--laser/--spots``, and any tool that wants the
same choices)::

    SPEC  = a preset name                    e.g. ideal | default | random (laser)
          | a YAML or JSON file              its mapping of fields, or the ``rig`` / ``laser`` /
                                             ``spots`` entry of a truth.json written by
                                             ``omnid scene`` (so another capture of the same
                                             rig, laser or spots can be rendered)
    PARAM = key=value                        overrides one field of the chosen spec; values are
                                             YAML (``law=angle``, ``source_mm=[0,0,-120]``);
                                             a key ending ``_deg`` sets the ``_rad`` field in
                                             degrees (``axis_tilt_deg=38``)

Random draws take their generator from a seed and a fixed stream number per kind of thing
(:func:`stream`), so the laser drawn for ``--seed 3`` is the same whatever rig is chosen.
Every value is validated by the dataclass it builds; a wrong key or value is a
:class:`~omnid.errors.ConfigError` naming it.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from omnid.config import from_mapping, load_yaml, to_mapping
from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.errors import ConfigError
from omnid.sim.laser import LaserProjector, ideal_lattice, random_laser
from omnid.sim.render import SPOT_KINDS, RenderOptions, SpotModel, random_spots
from omnid.sim.rigs import misaligned_rig, random_rig

T = TypeVar("T")

#: Stream numbers: one independent generator per kind of random thing drawn from one seed.
STREAMS = {"rig": 1, "laser": 2, "spots": 3, "extra": 4}

RIG_PRESETS = ("nominal", "misaligned", "random")
LASER_PRESETS = ("ideal", "default", "random")
SPOT_PRESETS = ("clean", "realistic", "random", *SPOT_KINDS)


def stream(seed: int, what: str, index: int = 0) -> np.random.Generator:
    """The generator of ``what`` (a key of :data:`STREAMS`) for ``seed`` (and an ``index``)."""
    return np.random.default_rng([int(seed), STREAMS[what], int(index)])


def parse_params(items: Sequence[str]) -> dict[str, Any]:
    """``["key=value", ...]`` → a mapping; values parsed as YAML; ``*_deg`` keys → ``*_rad``."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{item!r}: expected key=value")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ConfigError(f"{key}: value {text!r} is not valid YAML") from exc
        if key.endswith("_deg"):
            key = key[: -len("_deg")] + "_rad"
            value = _radians(value, key)
        out[key] = value
    return out


def _radians(value: Any, key: str) -> Any:
    if isinstance(value, list | tuple):
        return [_radians(v, key) for v in value]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{key}: expected a number of degrees, got {value!r}")
    return math.radians(value)


def _file_mapping(spec: str, entry: str) -> Mapping[str, Any] | None:
    """The mapping a spec file holds (its ``entry`` if it is a truth.json), None if ``spec`` is
    not a file name."""
    path = Path(spec)
    if not (path.suffix.lower() in (".yaml", ".yml", ".json") or path.is_file()):
        return None
    if path.suffix.lower() == ".json":  # a truth.json is large: plain JSON, not the YAML loader
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from exc
        except ValueError as exc:
            raise ConfigError(f"{path}: not valid JSON ({exc})") from None
    else:
        data = load_yaml(path)
    if isinstance(data, Mapping) and entry in data and isinstance(data[entry], Mapping):
        data = data[entry]
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: expected a mapping of {entry} fields")
    return data


def _with_params(base: T, params: Mapping[str, Any], what: str) -> T:
    if not params:
        return base
    data = to_mapping(base)
    data.update(params)
    return from_mapping(type(base), data, what)


def laser_from_spec(
    spec: str = "ideal", seed: int = 0, params: Mapping[str, Any] | None = None
) -> LaserProjector:
    """``ideal`` (the old regular slope lattice from the rig origin), ``default`` (the
    :class:`LaserProjector` defaults: a plausible real laser), ``random`` (drawn with
    :func:`random_laser`) or a file; then ``params`` override single fields."""
    mapping = _file_mapping(spec, "laser")
    if mapping is not None:
        base = from_mapping(LaserProjector, mapping, "laser")
    elif spec == "ideal":
        base = ideal_lattice()
    elif spec == "default":
        base = LaserProjector()
    elif spec == "random":
        base = random_laser(stream(seed, "laser"))
    else:
        raise ConfigError(f"laser {spec!r}: unknown (known: {', '.join(LASER_PRESETS)}, or a file)")
    return _with_params(base, params or {}, "laser")


def spots_from_spec(
    spec: str = "clean", seed: int = 0, params: Mapping[str, Any] | None = None
) -> SpotModel:
    """``clean`` (round Gaussian dots), ``realistic`` (plus speckled halos and ghosts),
    ``random`` (a family at random), a family name of :data:`SPOT_KINDS` (drawn from it with
    :func:`random_spots`) or a file; then ``params`` override single fields."""
    mapping = _file_mapping(spec, "spots")
    if mapping is not None:
        base = from_mapping(SpotModel, mapping, "spots")
    elif spec == "clean":
        base = SpotModel()
    elif spec == "realistic":
        base = SpotModel.realistic()
    elif spec == "random" or spec in SPOT_KINDS:
        base = random_spots(stream(seed, "spots"), None if spec == "random" else spec)  # type: ignore[arg-type]
    else:
        raise ConfigError(f"spots {spec!r}: unknown (known: {', '.join(SPOT_PRESETS)}, or a file)")
    return _with_params(base, params or {}, "spots")


def rig_from_spec(
    spec: str = "nominal", seed: int = 0, floor_depth_mm: float = 1100.0
) -> StereoRig:
    """``nominal``, ``misaligned`` (the README example's rig), ``random`` (drawn with
    :func:`random_rig`) or a truth.json / YAML file holding ``cam1`` and ``cam2`` (fields of
    :class:`MirrorCamera`) and optionally ``floor_depth_mm``."""
    mapping = _file_mapping(spec, "rig")
    if mapping is not None:
        cams = []
        for key in ("cam1", "cam2"):
            if key not in mapping:
                raise ConfigError(f"{spec}: rig.{key}: required key is missing")
            try:
                cams.append(from_mapping(MirrorCamera, mapping[key], f"rig.{key}"))
            except ValueError as exc:  # MirrorCamera checks its own values
                raise ConfigError(f"{spec}: rig.{key}: {exc}") from None
        depth = mapping.get("floor_depth_mm", floor_depth_mm)
        try:
            return StereoRig(cams[0], cams[1], float(depth))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{spec}: rig: {exc}") from None
    if spec == "nominal":
        return StereoRig.nominal(floor_depth_mm=floor_depth_mm)
    if spec == "misaligned":
        return misaligned_rig(floor_depth_mm)
    if spec == "random":
        return random_rig(stream(seed, "rig"), floor_depth_mm)
    raise ConfigError(f"rig {spec!r}: unknown (known: {', '.join(RIG_PRESETS)}, or a file)")


def rig_mapping(rig: StereoRig) -> dict[str, Any]:
    """The plain-data form of a rig that :func:`rig_from_spec` reads back."""
    return {
        "cam1": to_mapping(rig.cam1),
        "cam2": to_mapping(rig.cam2),
        "floor_depth_mm": rig.floor_depth_mm,
    }


def sensor_mapping(options: RenderOptions) -> dict[str, Any]:
    """The sensor and scene part of render options (everything but the spots), plain data."""
    return {
        f.name: getattr(options, f.name) for f in dataclasses.fields(options) if f.name != "spots"
    }
