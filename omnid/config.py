"""Typed configuration: YAML read once into frozen dataclasses.

Each module owns the settings it needs as a frozen dataclass (``ControlUnitSettings``,
``SafetySettings``, ...), with units in the field names (``stop_distance_mm``, ``period_s``).
Every numeric field declares its valid range where it is defined, with :func:`setting`::

    rate_hz: float = setting(50.0, 1.0, 500.0)  # fixed control-loop rate

The dataclass default is THE default: ``etc/omnid.yaml`` lists the same values (a test proves
they agree), and an empty file means exactly the shipped configuration. Checks that tie several
fields together stay in ``__post_init__`` (raise :class:`~omnid.errors.ConfigError` via
:func:`require`). :func:`from_mapping` builds such a dataclass from plain data, recursing into
nested dataclasses, and refuses unknown keys, mistyped values and values outside their range
with the full dotted key in the message::

    ConfigError: safety.stop_distance_mm: expected a number, got 'far'
    ConfigError: safety.stop_distanse_mm: unknown key (known: approach_time_s, slow_distance_mm, ...)
    ConfigError: control.rate_hz: 1000000000.0 is outside [1, 500]

:func:`load_yaml` reads a file with limits (size, nesting, node count; no aliases, no duplicate
keys; YAML 1.2 exponents such as ``1.0e9`` are numbers) and reports every problem in one line
naming the file.

Adding a key: a field with a unit in its name and :func:`setting` (numbers) in the owning
settings dataclass, the same key and value with a comment in ``etc/omnid.yaml``;
``tests/daemon/test_daemon_config.py`` fails until both agree and the range is there.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import yaml

from omnid.errors import ConfigError

T = TypeVar("T")

#: the largest configuration file read, bytes (the shipped one is ~13 kB)
MAX_FILE_BYTES = 256 * 1024
#: the deepest nesting of mappings/lists accepted (the shipped file uses 3)
MAX_DEPTH = 8
#: the most YAML nodes (scalars, lists, mappings) in one file
MAX_NODES = 20_000


def setting(default: T, low: float, high: float) -> T:
    """A numeric settings field with its valid range ``[low, high]`` (inclusive; for a tuple,
    each element; ``None`` where the type allows it is not checked). Use as the field's default::

        period_s: float = setting(0.5, 0.01, 10.0)
    """
    if not low <= high:
        raise ValueError(f"setting: empty range [{low}, {high}]")
    return dataclasses.field(default=default, metadata={"range": (low, high)})


def setting_range(f: dataclasses.Field[Any]) -> tuple[float, float] | None:
    """The ``(low, high)`` a field declared with :func:`setting`, or ``None``."""
    rng = f.metadata.get("range")
    return None if rng is None else (float(rng[0]), float(rng[1]))


def _number(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def check_range(f: dataclasses.Field[Any], value: Any, key: str) -> None:
    """Raise ``ConfigError('key: ... outside [low, high]')`` unless ``value`` (or each element
    of a tuple value) lies in the field's declared range."""
    rng = setting_range(f)
    if rng is None or value is None:
        return
    low, high = rng
    items = value if isinstance(value, tuple | list) else (value,)
    for i, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, int | float):
            continue
        if not low <= v <= high:  # also false for NaN
            where = f"{key}[{i}]" if isinstance(value, tuple | list) else key
            raise ConfigError(
                f"{where}: {_describe(v)} is outside [{_number(low)}, {_number(high)}]"
            )


def check_ranges(obj: Any, key: str = "", recurse: bool = True) -> None:
    """Check every field declared with :func:`setting` in the settings dataclass ``obj``
    (``recurse``: and in nested ones); :class:`ConfigError` names the dotted key."""
    if not (dataclasses.is_dataclass(obj) and not isinstance(obj, type)):
        return
    prefix = f"{key}." if key else ""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        check_range(f, value, prefix + f.name)
        if recurse and dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_ranges(value, prefix + f.name)


class Settings:
    """Base of every settings dataclass: construction checks the :func:`setting` ranges, so a
    tree built in code is held to the same ranges as one read from a file. A subclass with its
    own ``__post_init__`` (checks tying fields together) calls ``super().__post_init__()`` first::

        @dataclass(frozen=True)
        class ZoneSettings(Settings):
            stop_distance_mm: float = setting(150.0, 10.0, 2000.0)
            slow_distance_mm: float = setting(600.0, 10.0, 5000.0)

            def __post_init__(self) -> None:
                super().__post_init__()
                require(self.slow_distance_mm >= self.stop_distance_mm, "slow_distance_mm", "...")
    """

    def __post_init__(self) -> None:
        check_ranges(self, recurse=False)


def require(condition: bool, key: str, message: str) -> None:
    """Raise ``ConfigError('key: message')`` unless ``condition`` holds (for ``__post_init__``)."""
    if not condition:
        raise ConfigError(f"{key}: {message}")


def _describe(value: Any) -> str:
    if isinstance(value, int) and value.bit_length() > 200:  # repr fails beyond 4300 digits
        return f"an integer of {value.bit_length()} bits"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _convert(tp: Any, value: Any, key: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is typing.Union or origin is types.UnionType:
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(
            errors[0] if len(errors) == 1 else f"{key}: no allowed type fits {_describe(value)}"
        )
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise ConfigError(
                f"{key}: expected one of {', '.join(map(repr, allowed))}, got {_describe(value)}"
            )
        return value
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return from_mapping(tp, value, key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {_describe(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {_describe(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number, got {_describe(value)}")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond any float
            raise ConfigError(f"{key}: {_describe(value)} is too large for a number") from None
        if not math.isfinite(number):
            raise ConfigError(f"{key}: expected a finite number, got {_describe(value)}")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {_describe(value)}")
        return value
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {_describe(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key}: expected a list of {len(args)} items, got {len(value)}")
        return tuple(
            _convert(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if origin in (dict, Mapping) or tp is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping, got {_describe(value)}")
        args = get_args(tp) or (str, Any)
        return {
            _convert(args[0], k, f"{key}"): _convert(args[1], v, f"{key}.{k}")
            for k, v in value.items()
        }
    raise ConfigError(
        f"{key}: unsupported setting type {tp!r}"
    )  # a programming error, named anyway


def from_mapping(cls: type[T], data: Any, key: str = "") -> T:
    """Build the frozen dataclass ``cls`` from ``data``; missing keys take the field defaults.

    Raises :class:`ConfigError` naming the dotted key for unknown keys, wrong types, missing
    required values and failed range checks.
    """
    prefix = f"{key}." if key else ""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{key or '<top level>'}: expected a mapping, got {_describe(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    hints = get_type_hints(cls)
    unknown = [k for k in data if k not in fields]
    if unknown:
        known = ", ".join(sorted(fields))
        raise ConfigError(f"{prefix}{unknown[0]}: unknown key (known: {known})")
    kwargs: dict[str, Any] = {}
    for name, field in fields.items():
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], prefix + name)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{prefix}{name}: required key is missing")
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        if prefix and not str(exc).startswith(prefix):
            raise ConfigError(prefix + str(exc)) from None
        raise


def to_mapping(obj: Any) -> Any:
    """Plain-data form of a settings dataclass (tuples become lists), for writing YAML."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [to_mapping(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_mapping(v) for k, v in obj.items()}
    return obj


class _Refused(yaml.MarkedYAMLError):
    """A YAML construct a configuration file may not use (with where it is)."""

    def __init__(self, problem: str, mark: Any) -> None:
        super().__init__(problem=problem, problem_mark=mark)


# YAML 1.2 floats the 1.1 resolver misses: an exponent without sign or without a dot (1.0e9, 1e-3)
_FLOAT_12 = re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$")


class LimitedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` for configuration files: no aliases (no alias bombs), at most
    :data:`MAX_DEPTH` levels and :data:`MAX_NODES` nodes, a key twice in one mapping refused."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise _Refused(
                f"alias *{event.anchor} not allowed in a configuration file (write the value out)",
                event.start_mark,
            )
        self._nodes += 1
        if self._nodes > MAX_NODES:
            raise _Refused(f"more than {MAX_NODES} values", self.peek_event().start_mark)
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Refused(
                    f"nested deeper than {MAX_DEPTH} levels", self.peek_event().start_mark
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_object(self, node: Any, deep: bool = False) -> Any:
        # PyYAML's constructors raise plain exceptions for values they cannot build (a date
        # 2024-13-45, `!!float fast`, an integer of more than 4300 digits): a finding with its
        # place, like any other malformed YAML
        try:
            return super().construct_object(node, deep=deep)
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as exc:
            value = node.value if isinstance(node, yaml.ScalarNode) else node.tag
            raise _Refused(
                f"cannot read {_describe(value)} as {node.tag.rsplit(':', 1)[-1]} "
                f"({type(exc).__name__}: {str(exc)[:80]})",
                node.start_mark,
            ) from None

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, Any] = {}
            for key_node, _ in node.value:
                k = self.construct_object(key_node, deep=True)
                try:
                    hash(k)
                except TypeError:
                    raise _Refused(
                        "a mapping key must be a plain value", key_node.start_mark
                    ) from None
                if k in first:
                    raise _Refused(
                        f"duplicate key {k!r} (first at line {first[k].line + 1})",
                        key_node.start_mark,
                    )
                first[k] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


LimitedLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789"))


def parse_yaml(text: str, name: str = "<text>") -> Any:
    """Parse configuration YAML with :class:`LimitedLoader`; :class:`ConfigError` in one line
    naming ``name`` and the line."""
    loader = LimitedLoader(text)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}:" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).replace("\n", " ")
        if isinstance(exc, _Refused):
            raise ConfigError(f"{name}:{where} {problem}") from None
        raise ConfigError(f"{name}:{where} not valid YAML ({problem})") from None
    except RecursionError:
        raise ConfigError(f"{name}: nested too deeply") from None
    finally:
        loader.dispose()


def load_yaml(path: str | Path) -> Any:
    """Read a YAML file with limits (:data:`MAX_FILE_BYTES`, UTF-8, :class:`LimitedLoader`);
    unreadable, oversized, mis-encoded or malformed files raise :class:`ConfigError` in one line
    naming the file."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read ({exc.strerror or exc})") from exc
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(
            f"{p}: larger than {MAX_FILE_BYTES // 1024} KiB; not a configuration file"
        )
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{p}: not a text (YAML) file: byte 0x{raw[exc.start]:02x} at offset {exc.start} "
            "is not UTF-8 (a picture or other binary?)"
        ) from None
    return parse_yaml(text, str(p))


def load(cls: type[T], path: str | Path, section: str | None = None) -> T:
    """Load ``cls`` from the YAML file ``path`` (optionally one top-level ``section`` of it)."""
    data = load_yaml(path)
    if section is not None:
        if not isinstance(data, Mapping):
            raise ConfigError(f"{path}: expected a mapping at the top level")
        data = data.get(section)
    try:
        return from_mapping(cls, data, section or "")
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
