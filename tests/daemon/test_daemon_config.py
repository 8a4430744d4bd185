"""OmnidConfig: the shipped file is complete and valid; errors name file and key; reload."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from pathlib import Path
from typing import Literal, get_args, get_origin, get_type_hints

import pytest
import yaml

from omnid.config import MAX_FILE_BYTES, from_mapping, setting_range, to_mapping
from omnid.daemon.config import ConfigHolder, OmnidConfig, load_config
from omnid.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "etc" / "omnid.yaml"


def keys(tree, prefix=""):
    out = set()
    for k, v in tree.items():
        out.add(prefix + k)
        if isinstance(v, dict):
            out |= keys(v, prefix + k + ".")
    return out


def test_shipped_file_is_the_built_in_defaults_and_lists_every_key(tmp_path):
    """One configuration: the shipped file, the dataclass defaults, an empty file and a
    comment-only file are the same tree; every key of the tree is written in the shipped file."""
    shipped = load_config(SHIPPED)
    assert shipped == OmnidConfig()
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    comments = tmp_path / "comments.yaml"
    comments.write_text("# nothing set\n\n# at all\n")
    assert load_config(empty) == shipped and load_config(comments) == shipped
    written = keys(yaml.safe_load(SHIPPED.read_text()))
    defaults = keys(to_mapping(OmnidConfig()))
    assert defaults == written


def _numeric(tp) -> bool:
    if tp in (int, float):
        return True
    args = [a for a in get_args(tp) if a is not type(None) and a is not Ellipsis]
    return bool(args) and get_origin(tp) is not Literal and all(_numeric(a) for a in args)


def _fields(cls, prefix=""):
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        inner = [a for a in get_args(tp) if a is not type(None)]
        sub = tp if dataclasses.is_dataclass(tp) else (inner[0] if len(inner) == 1 else None)
        if sub is not None and dataclasses.is_dataclass(sub):
            yield from _fields(sub, prefix + f.name + ".")
        else:
            yield prefix + f.name, f, tp


NUMERIC = [(k, f) for k, f, tp in _fields(OmnidConfig) if _numeric(tp)]


def test_every_numeric_key_has_a_range_holding_its_default():
    missing = [k for k, f in NUMERIC if setting_range(f) is None]
    assert not missing, f"numeric keys without setting(default, low, high): {missing}"
    assert len(NUMERIC) > 100
    for k, f in NUMERIC:
        low, high = setting_range(f)
        d = f.default
        for v in d if isinstance(d, tuple) else (d,):
            assert v is None or low <= v <= high, k


def _tree(key: str, value) -> dict:
    out: dict = {}
    node = out
    parts = key.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
    return out


@pytest.mark.parametrize(("key", "f"), NUMERIC, ids=[k for k, _ in NUMERIC])
def test_a_value_beyond_the_range_is_refused_naming_the_key(key, f):
    low, high = setting_range(f)
    default = f.default
    is_int = isinstance(default, int) or (
        isinstance(default, tuple) and isinstance(default[0], int)
    )
    step = 1 if is_int else max(abs(high - low) * 1e-3, 1e-6)
    owner: object = OmnidConfig()
    for part in key.split(".")[:-1]:
        cls = get_type_hints(type(owner))[part]
        owner = getattr(owner, part) or next(a for a in get_args(cls) if a is not type(None))()
    for bad in (high + step, low - step):
        value = [bad] * len(default) if isinstance(default, tuple) else bad
        with pytest.raises(ConfigError) as err:  # read from a file
            from_mapping(OmnidConfig, _tree(key, value))
        assert str(err.value).startswith(key), (key, bad, str(err.value))
        with pytest.raises(ConfigError) as err:  # built in code
            dataclasses.replace(
                owner, **{f.name: tuple(value) if isinstance(default, tuple) else value}
            )
        assert str(err.value).startswith(f.name), (key, bad, str(err.value))


def test_exponents_without_sign_are_numbers_and_huge_values_are_refused(tmp_path):
    p = tmp_path / "omnid.yaml"
    for text in ("1.0e9", "1.0e+9", "1e9", "1.0e+30"):
        p.write_text(f"safety:\n  perception_timeout_s: {text}\n")
        with pytest.raises(ConfigError, match=r"safety\.perception_timeout_s: .* is outside"):
            load_config(p)
    p.write_text("motion:\n  max_speed_mm_s: 2.0e2\n")
    assert load_config(p).motion.max_speed_mm_s == 200.0


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("control:\n  rate_hz: 100\n  rate_hz: 50\n", "line 3: duplicate key 'rate_hz'"),
        ("control:\n  rate_hz: 100\nsafety: {}\ncontrol: {}\n", "line 4: duplicate key 'control'"),
        ("a: &a [1, 2]\ncontrol:\n  rate_hz: *a\n", "alias *a not allowed"),
        ("control: " + "[" * 40 + "]" * 40 + "\n", "nested deeper than"),
    ],
)
def test_duplicate_keys_aliases_and_deep_nesting_are_refused(tmp_path, text, words):
    p = tmp_path / "omnid.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert str(p) in str(err.value) and words in str(err.value)
    assert "\n" not in str(err.value)


def test_an_alias_bomb_is_refused_at_once(tmp_path):
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, 9):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines) + "\ncontrol:\n  rate_hz: *a8\n")
    assert p.stat().st_size < 1000
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="alias"):
        load_config(p)
    assert time.monotonic() - t0 < 5.0  # generous: refused on the first alias


def test_encoding_errors_and_oversized_files_are_one_line_naming_the_file(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes("control:\n  rate_hz: 50 # Fu\xdf\n".encode("latin-1"))
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert str(err.value).startswith(f"{p}: not a text (YAML) file: byte 0xdf at offset 27 ")
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (MAX_FILE_BYTES + 10) + "\n")
    with pytest.raises(ConfigError, match="larger than"):
        load_config(big)


def test_control_period_must_not_exceed_the_command_period(tmp_path):
    p = tmp_path / "omnid.yaml"
    p.write_text("control:\n  rate_hz: 25\n")
    with pytest.raises(ConfigError, match="control.rate_hz"):
        load_config(p)
    p.write_text(
        "control:\n  rate_hz: 25\ncontrol_unit:\n  command_period_s: 0.04\n  unit_watchdog_s: 0.25\n"
    )
    assert load_config(p).control.rate_hz == 25.0


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
    p.write_text("control:\n  rate_hz: 100\n")
    holder = ConfigHolder(p)
    assert holder.config.control.rate_hz == 100.0
    p.write_text("control:\n  rate_hz: 100\n  typo: 1\n")
    ok, why = holder.reload()
    assert not ok and "control.typo" in why
    assert holder.config.control.rate_hz == 100.0
    p.write_text("control: [unclosed\n")
    assert holder.reload()[0] is False
    p.write_text("control:\n  rate_hz: 60\n")
    assert holder.reload() == (True, "reloaded")
    assert holder.config.control.rate_hz == 60.0


@pytest.mark.parametrize("text", ["", "\n", "# all commented out\n", "{}\n"])
def test_a_file_emptied_before_a_reload_is_refused_not_read_as_defaults(tmp_path, text):
    """At start an empty file is the shipped configuration; on SIGHUP an emptied one (an
    editor's truncated save) would silently reset a tuned footprint to the defaults."""
    p = tmp_path / "omnid.yaml"
    p.write_text("safety:\n  footprint_width_mm: 760\n")
    holder = ConfigHolder(p)
    p.write_text(text)
    ok, why = holder.reload()
    assert not ok and "empty" in why and str(p) in why
    assert holder.config.safety.footprint_width_mm == 760.0
    ok, why = asyncio.run(holder.reload_off_loop(2.0))
    assert not ok and "empty" in why
    holder.close()
    assert load_config(p).safety.footprint_width_mm != 760.0  # at start: the defaults


def test_missing_file_is_one_line_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")


@pytest.mark.parametrize(
    ("text", "words"),
    [
        # an integer too large for a float: OverflowError in the finite check
        ("control:\n  rate_hz: 1" + "0" * 400 + "\n", "control.rate_hz: "),
        # more digits than Python converts (ValueError inside PyYAML's constructor)
        ("perception:\n  worker_nice: " + "1" * 5000 + "\n", "line 2:"),
        ("control:\n  rate_hz: " + "1" * 5000 + "\n", "line 2:"),
        ("record:\n  path: 2024-13-45\n", "line 2:"),  # a date that is no date
        ("control:\n  rate_hz: !!float fast\n", "line 2:"),
        ("perception:\n  worker_nice: !!int ten\n", "line 2:"),
        ("control:\n  rearm_after_fault: !!bool maybe\n", "line 2:"),
        ("record:\n  path: !!timestamp soon\n", "line 2:"),
        # hexadecimal has no digit limit: an int whose repr (in the message) fails
        ("perception:\n  worker_nice: 0x" + "f" * 5000 + "\n", "perception.worker_nice: "),
        ("control:\n  rate_hz: 0x" + "f" * 5000 + "\n", "control.rate_hz: "),
    ],
    ids=lambda v: v.split(":")[0] if ": " in v else None,
)
def test_values_yaml_cannot_build_are_one_line_naming_file_and_place(tmp_path, text, words):
    """A value PyYAML's constructors (or the number checks) choke on is a ConfigError in one
    line with the file and the line or key — it was a ValueError/OverflowError/KeyError, so
    `omnid run` printed a traceback and a SIGHUP logged 'reload failed' without the key."""
    p = tmp_path / "omnid.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(p)
    msg = str(err.value)
    assert msg.startswith(f"{p}: ") and words in msg and "\n" not in msg, msg
    assert len(msg) < 300, msg
    holder = ConfigHolder(SHIPPED)
    p.write_text(text)
    holder.path = p
    ok, why = holder.reload()
    assert not ok and words in why and holder.config == OmnidConfig()


def test_an_exposure_longer_than_a_frame_is_refused_by_the_loader_and_run_check(tmp_path, capsys):
    """camera.exposure_s must be shorter than a frame (1/camera.fps): the daemon's capture cycle
    needs it whether perception is on or not. The loader let it through, `omnid run --check`
    said ok (exit 0), and `omnid run` then refused to start with 'exposure_s: must be below
    the period' — neither the file nor the section named."""
    from omnid.cli import main

    p = tmp_path / "omnid.yaml"
    p.write_text(
        "perception:\n  enabled: false\ncontrol_unit:\n  port: loop://\n"
        "rider:\n  tilt:\n    enabled: false\n  keyboard:\n    enabled: false\n"
        "camera:\n  fps: 30.0\n  exposure_s: 0.05\n"
    )
    with pytest.raises(ConfigError) as err:
        load_config(p)
    assert str(err.value).startswith(f"{p}: camera.exposure_s: "), str(err.value)
    assert main(["run", "--check", "--config", str(p)]) == 2
    out = capsys.readouterr()
    assert "camera.exposure_s" in out.err and "\n" not in out.err.strip(), out
    p.write_text("camera:\n  fps: 15.0\n  exposure_s: 0.05\n")  # a slower clock: it fits
    assert load_config(p).camera.exposure_s == 0.05


@pytest.mark.parametrize(
    "text",
    [
        "freespace:\n  reanchor_distance_mm: 20000.0\n",
        "freespace:\n  grid:\n    x_max_mm: 20000.0\n",
        "freespace:\n  grid:\n    y_min_mm: -19500.0\n",
    ],
)
def test_a_map_the_daemon_cannot_build_is_refused_by_the_loader(tmp_path, text):
    """The remembered map keeps a square of ±(grid extent + reanchor_distance_mm + resolution)
    around its anchor, itself a grid held to ±20 m. Each key in its range, the loader took
    e.g. reanchor_distance_mm: 20000, `run --check` said ok, and `omnid run` refused with
    'x_min_mm: -24050.0 is outside [-20000, 20000]' — a key nobody wrote, no file, no section."""
    from omnid.daemon.run import Daemon

    p = tmp_path / "omnid.yaml"
    base = "perception:\n  enabled: false\ncontrol_unit:\n  port: loop://\n"
    p.write_text(base + text)
    try:
        holder = ConfigHolder(p)
    except ConfigError as err:
        assert str(err).startswith(f"{p}: freespace."), str(err)
        assert "reanchor_distance_mm" in str(err)
        return
    Daemon(holder)  # accepted: the daemon must then build its map
