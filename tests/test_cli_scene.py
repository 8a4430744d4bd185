"""`omnid scene` → `omnid calibrate` → `omnid perceive` (--ply, --png, summary) and
`omnid experiment table74`, all through the console entry ``omnid.cli.main``."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnid.cli import main
from omnid.core.export import parse_ply

CAPTURE = ("mask1", "base1", "mask2", "base2")


def capture_args(folder: Path, prefix: str = "") -> list[str]:
    return [a for n in CAPTURE for a in (f"--{n}", str(folder / f"{prefix}{n}.png"))]


def make_scene(folder: Path, name: str, *extra: str) -> Path:
    """Render ``name`` (a plausible real laser) into ``folder`` with an installer's extra
    captures of a wall and a box, and calibrate on them; returns CALIB.yaml."""
    argv = ["scene", name, "--out", str(folder), "--laser", "default", *extra]
    assert main([*argv, "--extra", "wall", "--extra", "box"]) == 0
    calib = folder / "calib.yaml"
    argv = ["calibrate", *capture_args(folder, "floor_"), "--floor-depth-mm", "1100"]
    argv += ["--extra", str(folder / "extra1"), "--extra", str(folder / "extra2")]
    assert main([*argv, "--out", str(calib)]) == 0
    return calib


@pytest.fixture(scope="module")
def boxes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("three_boxes")
    return folder, make_scene(folder, "three_boxes", "--misaligned", "--seed", "3")


def test_scene_writes_captures_and_truth(boxes) -> None:
    folder, _ = boxes
    for prefix in ("", "floor_"):
        for n in CAPTURE:
            img = cv2.imread(str(folder / f"{prefix}{n}.png"), cv2.IMREAD_UNCHANGED)
            assert img is not None and img.shape == (480, 640) and img.dtype == np.uint8
    truth = json.loads((folder / "truth.json").read_text())
    assert truth["scene"] == "three_boxes" and truth["misaligned"] is True
    dots = truth["dots"]
    assert truth["visible_both"] == sum(d["visible1"] and d["visible2"] for d in dots) > 150
    boxes_seen = [d for d in dots if d["class"] == "obstacle" and d["visible1"] and d["visible2"]]
    # the three boxes are 150, 250 and 100 mm high; their tops carry dots
    assert {round(d["h"]) for d in boxes_seen} >= {100, 150, 250}
    assert truth["rig"]["cam1"]["rotation_rad"] != 0.0


def test_round_trip_json_ply_png(boxes, capsys: pytest.CaptureFixture[str]) -> None:
    folder, calib = boxes
    ply, png = folder / "cloud.ply", folder / "top.png"
    capsys.readouterr()
    argv = ["perceive", "--calib", str(calib), *capture_args(folder), "--json"]
    assert main([*argv, "--ply", str(ply), "--png", str(png)]) == 0
    doc = json.loads(capsys.readouterr().out)
    truth = json.loads((folder / "truth.json").read_text())
    pts = doc["points"]
    assert doc["detector"] == "best"
    assert len(pts) >= 0.95 * truth["visible_both"]
    obstacles = [p for p in pts if p["class"] == "obstacle"]
    h = np.array([p["h"] for p in obstacles])
    assert np.all((h > 10.0) & (h < 260.0))  # box tops and sides, nothing above the boxes
    for top in (100.0, 150.0, 250.0):  # each box top is seen at its height within 5 mm
        assert np.sum(np.abs(h - top) < 5.0) >= 3
    # the nearest box ahead within ±350 mm: the left box's near side, 600 mm ahead
    assert doc["nearest_obstacle_mm"] == pytest.approx(600.0, abs=15.0)
    assert doc["nearest_dropoff_mm"] is None
    # the PLY holds the same points and classes
    rec = parse_ply(ply.read_bytes())
    assert len(rec) == len(pts)
    assert np.allclose(rec["x"], [p["x"] for p in pts], atol=0.01)
    assert int((rec["class"] == 1).sum()) == len(obstacles)
    # the picture: a BGR image with obstacle-red and floor-green dots drawn over the map
    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert img is not None and img.ndim == 3 and img.shape[0] > 100
    assert np.any(np.all(img == (40, 40, 230), axis=2))  # obstacle dot (BGR of 230, 40, 40)
    assert np.any(np.all(img == (60, 200, 40), axis=2))  # floor dot
    assert not list(folder.glob(".*.tmp"))  # atomic writes leave no temporaries


def test_summary_for_a_person(boxes, capsys: pytest.CaptureFixture[str]) -> None:
    folder, calib = boxes
    capsys.readouterr()
    assert main(["perceive", "--calib", str(calib), *capture_args(folder)]) == 0
    out = capsys.readouterr().out
    assert "obstacle" in out and "matched" in out
    line = next(x for x in out.splitlines() if x.startswith("nearest obstacle"))
    assert float(line.rsplit(":", 1)[1].split()[0]) == pytest.approx(600.0, abs=15.0)
    assert "nearest drop-off ahead (within ±350 mm): none seen" in out


def test_dropoff_is_reported_ahead(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    calib = make_scene(tmp_path, "dropoff")
    capsys.readouterr()
    assert main(["perceive", "--calib", str(calib), *capture_args(tmp_path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    # the floor ends 1000 mm ahead; lowered dots' rays cross floor level just beyond the edge
    assert 1000.0 <= doc["nearest_dropoff_mm"] <= 1150.0
    assert doc["counts"]["dropoff"] > 50


def test_method_thesis_runs_the_thesis_detector(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--method thesis = the thesis' 8x8 detector (whole-pixel centres), matching and
    triangulation; on an aligned rig its floor comes out at floor level."""
    calib = make_scene(tmp_path, "horizontal_1100")
    capsys.readouterr()
    argv = ["perceive", "--calib", str(calib), *capture_args(tmp_path), "--json"]
    assert main([*argv, "--method", "thesis"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["detector"] == "thesis" and doc["matched_fraction"] > 0.9
    px = np.array([[p["r1"], p["c1"], p["r2"], p["c2"]] for p in doc["points"]])
    assert len(px) > 150 and np.array_equal(px, np.rint(px))  # the 8x8 model's integer centres
    h = np.array([p["h"] for p in doc["points"]])
    assert np.median(np.abs(h)) < 30.0
    # the best detector, when asked for, gives sub-pixel centres to the same matcher
    assert main([*argv, "--method", "thesis", "--detect", "best"]) == 0
    doc = json.loads(capsys.readouterr().out)
    px = np.array([[p["r1"], p["c1"]] for p in doc["points"]])
    assert doc["detector"] == "best" and not np.array_equal(px, np.rint(px))


def test_unwritable_png_is_one_line(boxes, tmp_path: Path, capsys) -> None:
    folder, calib = boxes
    bad = tmp_path / "no" / "such" / "dir" / "top.png"
    capsys.readouterr()
    code = main(["perceive", "--calib", str(calib), *capture_args(folder), "--png", str(bad)])
    err = capsys.readouterr().err.strip()
    assert code != 0 and str(bad) in err and len(err.splitlines()) == 1
    assert "Traceback" not in err


def test_scene_list_and_unknown_name(tmp_path: Path, capsys) -> None:
    assert main(["scene", "--list"]) == 0
    out = capsys.readouterr().out
    assert "three_boxes" in out and "vertical_1750" in out and "dropoff" in out
    assert main(["scene", "no_such_scene", "--out", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip()
    assert "no_such_scene" in err and len(err.splitlines()) == 1
    assert main(["scene", "three_boxes"]) != 0  # --out is needed
    assert "--out" in capsys.readouterr().err


def test_scene_with_a_random_rig_laser_and_spots_and_extra_captures(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--rig/--laser/--spots random, --extra: truth.json describes what drew the images well
    enough to render another capture of the same rig and laser, and to score perception."""
    from omnid.sim import specs

    out = tmp_path / "a"
    argv = ["scene", "three_boxes", "--out", str(out), "--seed", "5"]
    argv += ["--rig", "random", "--laser", "random", "--spots", "saturated"]
    assert main([*argv, "--extra", "wall", "--extra", "vertical_750"]) == 0
    truth = json.loads((out / "truth.json").read_text())
    rig = specs.rig_from_spec(str(out / "truth.json"))
    laser = specs.laser_from_spec(str(out / "truth.json"))
    assert laser == specs.laser_from_spec("random", 5)  # the same draw for the same seed
    assert rig == specs.rig_from_spec("random", 5)
    assert truth["spots"]["kind"] == "saturated" and truth["spots"]["shading"] is True
    rays = laser.rays()
    for key in ("dots", "floor_dots"):
        dots = truth[key]
        assert [d["beam"] for d in dots] == list(range(len(rays)))
        xyz = np.array([[d["x"], d["y"], d["z"]] for d in dots])
        px = np.array([[d["r1"], d["c1"], d["r2"], d["c2"]] for d in dots], dtype=float)
        np.testing.assert_allclose(px, rig.project(xyz), atol=1e-9)
        # every dot lies on its beam from the laser's source
        u = xyz - np.array(laser.source_mm)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        np.testing.assert_allclose(u, rays.directions, atol=1e-9)
    assert {d["class"] for d in truth["dots"]} >= {"floor", "obstacle"}
    assert all(d["z"] == pytest.approx(1100.0) for d in truth["floor_dots"])
    for k, name in ((1, "wall"), (2, "vertical_750")):
        extra = json.loads((out / f"extra{k}" / "truth.json").read_text())
        assert extra["scene"] == name and extra["laser"] == truth["laser"]
        assert extra["off_floor_both"] > 20  # dots on something other than the floor
        for n in CAPTURE:
            img = cv2.imread(str(out / f"extra{k}" / f"{n}.png"), cv2.IMREAD_UNCHANGED)
            assert img is not None and img.shape == (480, 640)
    base = cv2.imread(str(out / "floor_base1.png"), cv2.IMREAD_UNCHANGED)
    assert (base == 255).sum() > 100  # saturated spots
    # Another capture of the same rig and laser, one field changed (in degrees).
    again = tmp_path / "b"
    argv = ["scene", "passage", "--out", str(again), "--rig", str(out / "truth.json")]
    argv += ["--laser", str(out / "truth.json"), "--laser-param", "axis_tilt_deg=38"]
    assert main(argv) == 0
    other = json.loads((again / "truth.json").read_text())
    assert other["rig"] == truth["rig"]
    assert other["laser"]["axis_tilt_rad"] == pytest.approx(np.radians(38.0))
    assert other["laser"]["source_mm"] == truth["laser"]["source_mm"]


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--laser", "hologram"], "laser 'hologram'"),
        (["--laser-param", "pitch_u=-1"], "pitch_u"),
        (["--laser-param", "colour=green"], "laser.colour: unknown key"),
        (["--spots", "fuzzy"], "spots 'fuzzy'"),
        (["--spot-param", "sigma_px=oops"], "spots.sigma_px"),
        (["--rig", "bent"], "rig 'bent'"),
        (["--extra", "no_such_scene"], "no_such_scene"),
        (["--laser", "no/such/laser.json"], "cannot read"),
    ],
)
def test_bad_scene_options_are_one_line(tmp_path: Path, capsys, args, words) -> None:
    assert main(["scene", "floor", "--out", str(tmp_path / "x"), *args]) != 0
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_experiment_table74(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["experiment", "table74", "--planes", "vertical_1450"]) == 0
    out = capsys.readouterr().out
    assert "Misaligned rig" in out
    assert "[2.17]" in out and "[51]" in out  # the thesis' own numbers beside ours
    row = next(x for x in out.splitlines() if x.startswith("| vertical_1450 | best |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert float(cells[4].split()[0]) < 0.5  # mean X error of best on the plane, %
    assert float(cells[7]) >= 95.0 and float(cells[8]) < 0.5  # matched %, wrong %


def test_scene_that_cannot_write_its_truth_writes_no_capture(tmp_path: Path, capsys) -> None:
    # truth.json cannot be written (a folder is in its place): the eight PNGs must not be left
    # behind without it, and the refusal is one line with a non-zero exit
    out = tmp_path / "scene"
    (out / "truth.json").mkdir(parents=True)
    code = main(["scene", "floor", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert "truth.json" in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["truth.json"]
