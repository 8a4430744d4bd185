"""`omnid calibrate` and `omnid perceive` through the real console entry, on rendered PNGs."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from match_helpers import misaligned_rig

from omnid.cli import main
from omnid.core.types import StereoCapture
from omnid.sim.installation import render_world, write_installation
from omnid.sim.laser import LaserProjector
from omnid.sim.render import render_capture
from omnid.sim.world import Box, RigMount, World

H = 1100.0


def write_capture(cap: StereoCapture, folder: Path, prefix: str) -> list[str]:
    """Write the capture as PNGs; returns the four --mask1 ... --base2 arguments."""
    args = []
    for name in ("mask1", "base1", "mask2", "base2"):
        path = folder / f"{prefix}_{name}.png"
        assert cv2.imwrite(str(path), getattr(cap, name))
        args += [f"--{name}", str(path)]
    return args


def install(folder: Path, rig) -> list[str]:
    """The installer's captures (floor + extras) in ``folder``; the calibrate arguments."""
    extras = write_installation(rig, folder, seed=1)
    args = [
        a
        for n in ("mask1", "base1", "mask2", "base2")
        for a in (f"--{n}", str(folder / f"floor_{n}.png"))
    ]
    return args + [a for e in extras for a in ("--extra", str(e))]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("cli")
    rig = misaligned_rig()
    out = folder / "calib.yaml"
    assert (
        main(["calibrate", *install(folder, rig), "--floor-depth-mm", "1100", "--out", str(out)])
        == 0
    )
    # a scene: floor with a raised block ahead (box top 300 mm high)
    m = RigMount()
    box = Box(m.x_offset_mm + 700, m.x_offset_mm + 1300, -350.0, 350.0, 300.0)
    scene = render_world(rig, LaserProjector(), World((box,)), m, seed=2)
    write_capture(scene, folder, "scene")
    return folder, out


def scene_args(folder: Path, prefix: str = "scene") -> list[str]:
    return [
        a
        for n in ("mask1", "base1", "mask2", "base2")
        for a in (f"--{n}", str(folder / f"{prefix}_{n}.png"))
    ]


@pytest.mark.parametrize("method", ["best", "thesis"])
def test_perceive_json(calibrated, capsys: pytest.CaptureFixture[str], method: str) -> None:
    folder, calib = calibrated
    capsys.readouterr()
    argv = ["perceive", "--calib", str(calib), *scene_args(folder), "--method", method, "--json"]
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)  # exactly one JSON object
    pts = doc["points"]
    assert len(pts) > (180 if method == "best" else 20)
    for p in pts:
        assert set(p) >= {"x", "y", "z", "h", "r1", "c1", "r2", "c2", "class"}
        assert p["class"] in ("floor", "obstacle", "dropoff")
        assert p["h"] == pytest.approx(H - p["z"])
    if method == "best":
        obstacles = [p for p in pts if p["class"] == "obstacle"]
        floor = [p for p in pts if p["class"] == "floor"]
        assert len(obstacles) > 15 and len(floor) > 120
        assert doc["calibration_health"]["ok"] and doc["calibration_health"]["explained"] > 0.8
        assert np.median([p["h"] for p in obstacles]) == pytest.approx(300.0, abs=10.0)
        assert np.median([abs(p["h"]) for p in floor]) < 5.0


def test_calibrate_refuses_a_capture_without_dots(tmp_path: Path, capsys) -> None:
    cap = render_capture(misaligned_rig(), np.zeros((0, 3)), seed=3)
    args = write_capture(cap, tmp_path, "dark")
    out = tmp_path / "calib.yaml"
    code = main(["calibrate", *args, "--floor-depth-mm", "1100", "--out", str(out)])
    err = capsys.readouterr().err
    assert code != 0 and not out.exists()
    assert "dots" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def _bad_perceive(calibrated, tmp_path: Path, capsys, replace: str, content: bytes | np.ndarray):
    folder, calib = calibrated
    args = scene_args(folder)
    bad = tmp_path / "bad.png"
    if isinstance(content, bytes):
        bad.write_bytes(content)
    else:
        cv2.imwrite(str(bad), content)
    args[args.index(f"--{replace}") + 1] = str(bad)
    code = main(["perceive", "--calib", str(calib), *args, "--json"])
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert code != 0
    assert captured.out == ""
    assert "Traceback" not in err and len(err.splitlines()) == 1
    assert str(bad) in err
    return err


@pytest.mark.parametrize(
    ("replace", "content"),
    [
        ("base2", b""),  # empty file
        ("mask1", b"this is not a PNG"),  # not an image
        ("base1", np.zeros((240, 320), np.uint8)),  # wrong size
        ("mask2", np.zeros((480, 600), np.uint8)),  # mismatched with the others
    ],
)
def test_bad_input_is_one_line_naming_the_file(calibrated, tmp_path, capsys, replace, content):
    _bad_perceive(calibrated, tmp_path, capsys, replace, content)


def test_missing_file_named(calibrated, tmp_path: Path, capsys) -> None:
    folder, calib = calibrated
    args = scene_args(folder)
    args[args.index("--base1") + 1] = str(tmp_path / "nope.png")
    assert main(["perceive", "--calib", str(calib), *args]) != 0
    assert "nope.png" in capsys.readouterr().err


def test_all_black_capture_gives_zero_points(calibrated, tmp_path: Path, capsys) -> None:
    _, calib = calibrated
    black = np.zeros((480, 640), np.uint8)
    args = []
    for name in ("mask1", "base1", "mask2", "base2"):
        p = tmp_path / f"{name}.png"
        cv2.imwrite(str(p), black)
        args += [f"--{name}", str(p)]
    capsys.readouterr()
    assert main(["perceive", "--calib", str(calib), *args, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["points"] == []


def test_bad_calibration_file_names_key(calibrated, tmp_path: Path, capsys) -> None:
    folder, calib = calibrated
    bad = tmp_path / "calib.yaml"
    bad.write_text(calib.read_text().replace("format_version: 2", "format_version: 9"))
    assert main(["perceive", "--calib", str(bad), *scene_args(folder)]) != 0
    err = capsys.readouterr().err
    assert "format_version" in err and str(bad) in err


def _one_line_refusal(capsys, code: int, out: Path | None = None) -> str:
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    if out is not None:
        assert not out.exists()
    return err


def test_calibrate_on_the_floor_alone_notes_the_unknown_source_and_perceive_works(
    calibrated, capsys
) -> None:
    """Floor only: written, with a note on what an --extra capture adds; perceive reads the
    floor, places the source from the scene's own box when it can (else counts its dots as
    not understood) and never reports a wrong floor there."""
    folder, _ = calibrated
    out = folder / "floor_only.yaml"
    floor = [
        a
        for n in ("mask1", "base1", "mask2", "base2")
        for a in (f"--{n}", str(folder / f"floor_{n}.png"))
    ]
    capsys.readouterr()
    assert main(["calibrate", *floor, "--floor-depth-mm", "1100", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "source unknown" in captured.out
    assert "--extra" in captured.err and "box or a wall" in captured.err
    assert main(["perceive", "--calib", str(out), *scene_args(folder), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    pts = doc["points"]
    h = np.array([p["h"] for p in pts])
    floor_pts = np.array([p["class"] == "floor" for p in pts])
    assert floor_pts.sum() > 100 and np.all(np.abs(h[floor_pts]) < 30.0)
    # the box (300 mm high): read from its own dots, or left not understood
    placed = doc["source_estimate"] is not None
    tops = np.sum(np.abs(h - 300.0) < 10.0)
    assert (placed and tops > 20 and doc["not_understood"] < 5) or (
        not placed and doc["not_understood"] > 20
    )


def test_calibrate_refuses_extras_with_nothing_off_the_floor(calibrated, tmp_path, capsys) -> None:
    folder, _ = calibrated
    floor = [
        a
        for n in ("mask1", "base1", "mask2", "base2")
        for a in (f"--{n}", str(folder / f"floor_{n}.png"))
    ]
    flat = tmp_path / "flat"
    flat.mkdir()
    for n in ("mask1", "base1", "mask2", "base2"):
        (flat / f"{n}.png").write_bytes((folder / f"floor_{n}.png").read_bytes())
    out = tmp_path / "calib.yaml"
    code = main(
        ["calibrate", *floor, "--extra", str(flat), "--floor-depth-mm", "1100", "--out", str(out)]
    )
    assert "off the floor" in _one_line_refusal(capsys, code, out)


def test_calibrate_refuses_extras_of_another_rig(calibrated, tmp_path, capsys) -> None:
    folder, _ = calibrated
    other = tmp_path / "other"
    other.mkdir()
    from omnid.sim.laser import random_laser
    from omnid.sim.rigs import random_rig

    extras = write_installation(random_rig(5), other, random_laser(5), seed=4)
    floor = [
        a
        for n in ("mask1", "base1", "mask2", "base2")
        for a in (f"--{n}", str(folder / f"floor_{n}.png"))
    ]
    out = tmp_path / "calib.yaml"
    code = main(
        [
            "calibrate",
            *floor,
            "--extra",
            str(extras[1]),
            "--floor-depth-mm",
            "1100",
            "--out",
            str(out),
        ]
    )
    _one_line_refusal(capsys, code, out)


def test_perceive_refuses_captures_that_do_not_fit_the_calibration(
    calibrated, tmp_path, capsys
) -> None:
    """The rig knocked after calibration (camera 2 turned by 1°): one line, nothing written."""
    from dataclasses import replace

    _, calib = calibrated
    rig = misaligned_rig()
    knocked = replace(
        rig, cam2=replace(rig.cam2, rotation_rad=rig.cam2.rotation_rad + np.radians(1.0))
    )
    m = RigMount()
    write_capture(render_world(knocked, LaserProjector(), World(), m, seed=5), tmp_path, "k")
    png = tmp_path / "top.png"
    code = main(["perceive", "--calib", str(calib), *scene_args(tmp_path, "k"), "--png", str(png)])
    assert "does NOT fit the calibration" in _one_line_refusal(capsys, code, png)


def test_old_calibration_file_says_recalibrate(calibrated, tmp_path, capsys) -> None:
    folder, calib = calibrated
    old = tmp_path / "old.yaml"
    old.write_text(calib.read_text().replace("format_version: 2", "format_version: 1"))
    code = main(["perceive", "--calib", str(old), *scene_args(folder)])
    assert "recalibrate" in _one_line_refusal(capsys, code)


def test_perceive_writes_neither_output_when_one_cannot_be_written(calibrated, tmp_path, capsys):
    # --ply writable, --png in a folder that does not exist: the refusal leaves no PLY behind
    folder, calib = calibrated
    ply = tmp_path / "cloud.ply"
    png = tmp_path / "missing" / "top.png"
    code = main(
        [
            "perceive",
            "--calib",
            str(calib),
            *scene_args(folder),
            "--ply",
            str(ply),
            "--png",
            str(png),
        ]
    )
    assert str(png) in _one_line_refusal(capsys, code, png)
    assert not ply.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no temporary file left either


def test_perceive_refuses_an_output_that_is_one_of_its_inputs(calibrated, tmp_path, capsys):
    folder, calib = calibrated
    own = tmp_path / "calib.yaml"
    own.write_bytes(calib.read_bytes())
    before = own.read_bytes()
    code = main(["perceive", "--calib", str(own), *scene_args(folder), "--png", str(own)])
    assert "--calib" in _one_line_refusal(capsys, code)
    assert own.read_bytes() == before  # the calibration is not replaced by a picture
    same = tmp_path / "both.out"
    code = main(
        [
            "perceive",
            "--calib",
            str(calib),
            *scene_args(folder),
            "--ply",
            str(same),
            "--png",
            str(same),
        ]
    )
    assert "--ply" in _one_line_refusal(capsys, code, same)


def test_calibrate_refuses_to_write_over_its_own_capture(calibrated, tmp_path, capsys):
    folder, _ = calibrated
    args = scene_args(folder, "floor")
    mask1 = tmp_path / "mask1.png"
    mask1.write_bytes((folder / "floor_mask1.png").read_bytes())
    before = mask1.read_bytes()
    args[args.index("--mask1") + 1] = str(mask1)
    code = main(
        [
            "calibrate",
            *args,
            "--floor-depth-mm",
            "1100",
            "--out",
            str(mask1),
            "--extra",
            str(folder / "extra_box"),
        ]
    )
    assert "--mask1" in _one_line_refusal(capsys, code)
    assert mask1.read_bytes() == before  # the installer's capture is still a picture
