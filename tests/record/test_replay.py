"""``omnid replay`` and ``omnid report`` on recordings, and one line for every bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from omnid.cli import main

DATA = Path(__file__).resolve().parent.parent / "data" / "recordings"
RECORDINGS = sorted(DATA.glob("*.mcap"))
REGENERATE = (
    "this build decides otherwise than when the recording was made; if that is intended, "
    "regenerate with `python tools/make_recordings.py` and say why in the commit"
)


def replay_json(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict]:
    capsys.readouterr()
    rc = main(["replay", *argv, "--json"])
    return rc, json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("path", RECORDINGS, ids=[p.stem for p in RECORDINGS])
def test_this_build_decides_as_recorded(path: Path, capsys) -> None:
    rc, doc = replay_json(capsys, str(path))
    assert doc["compared"] > 100
    assert doc["differing"] == [] and doc["perception_diffs"] == [], REGENERATE
    assert rc == 0
    if path.stem.startswith("pipeline"):
        assert doc["captures"] >= 1  # this build's perception ran on the recorded pixels


def test_a_changed_setting_shows_where_decisions_differ(capsys) -> None:
    demo = DATA / "demo_truth.mcap"
    capsys.readouterr()
    assert main(["replay", str(demo), "--set", "safety.slow_distance_mm=1500"]) == 1
    out = capsys.readouterr().out
    assert "decisions differ in" in out and "slow_zone" in out
    rc, doc = replay_json(capsys, str(demo), "--set", "safety.slow_distance_mm=1500")
    # the first cycle the slow zone slows (while the chair still speeds up to the cap, the
    # cycles differ by the reason only)
    first = next(d for d in doc["differing"] if d["replayed"][0] != d["recorded"][0])
    assert rc == 1 and "slow_zone" in first["replayed"][2]
    assert abs(first["replayed"][0]) < abs(first["recorded"][0])  # slower than recorded


def test_faults_and_warnings_are_recorded(capsys) -> None:
    from omnid.record.reader import read_recording

    rec = read_recording([DATA / "faults_truth.mcap"])
    started = {m.doc["name"] for m in rec.topic("/faults") if m.doc["event"] == "start"}
    assert {"status_stale", "input_stale"} <= started
    assert any(m.doc.level == 3 for m in rec.topic("/log"))  # warnings on /log


def one_line(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def test_bad_recordings_give_one_line(tmp_path: Path, capsys) -> None:
    demo = (DATA / "demo_truth.mcap").read_bytes()
    png = tmp_path / "picture.mcap"
    cv2.imwrite(str(tmp_path / "p.png"), (255 * (cv2.UMat(8, 8, cv2.CV_8U).get() * 0)))
    png.write_bytes((tmp_path / "p.png").read_bytes())
    assert "not an MCAP file" in one_line(capsys, ["replay", str(png)])
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(demo[:2000])
    assert "truncated" in one_line(capsys, ["replay", str(stub)])
    # a foreign MCAP (someone else's topics, no omnid metadata)
    from mcap.writer import Writer

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        ch = w.register_channel("/velodyne_points", "json", sid)
        w.add_message(ch, 1, b"{}", 1)
        w.finish()
    assert "not an omnid recording" in one_line(capsys, ["replay", str(foreign)])
    # another format version
    other = tmp_path / "future.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata(
            "omnid", {"format": "omnid-recording", "format_version": "7", "omnid_version": "9.0"}
        )
        w.finish()
    line = one_line(capsys, ["replay", str(other)])
    assert "format version 7" in line and "omnid 9.0" in line
    assert "No such file" in one_line(capsys, ["replay", str(tmp_path / "none.mcap")])


def test_a_recording_cut_short_replays_what_is_complete(tmp_path: Path, capsys) -> None:
    data = (DATA / "demo_truth.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    capsys.readouterr()
    assert main(["replay", str(cut)]) == 0
    out = capsys.readouterr().out
    assert "cut short" in out and "every compared cycle as recorded" in out


def test_another_rig_is_refused(tmp_path: Path, capsys) -> None:
    from omnid.core.calibration import calibrate_from_capture
    from omnid.core.geometry import StereoRig
    from omnid.sim.installation import installation_captures

    rig = StereoRig.nominal(floor_depth_mm=700.0)
    cap = installation_captures(rig, seed=1)[0]  # the empty floor, the simulator's laser
    calib = tmp_path / "other.yaml"
    calibrate_from_capture(cap, 700.0, 200.0).save(calib)
    line = one_line(capsys, ["replay", str(DATA / "pipeline_capture.mcap"), "--calib", str(calib)])
    assert "recorded with another rig" in line


def test_report_draws_the_top_view_and_the_timeline(tmp_path: Path, capsys) -> None:
    assert main(["report", str(DATA / "demo_truth.mcap"), "--out", str(tmp_path)]) == 0
    top = cv2.imread(str(tmp_path / "top.png"))
    timeline = cv2.imread(str(tmp_path / "timeline.png"))
    assert top is not None and timeline is not None
    assert timeline.shape[1] == 1400 and timeline.shape[0] > 600
    # the path is drawn in its colour (blue), and the reasons' bands are there (slow zone)
    assert ((top[:, :, 0] > 150) & (top[:, :, 2] < 60)).sum() > 200
    assert (
        (timeline[:, :, 1] > 180) & (timeline[:, :, 2] > 200) & (timeline[:, :, 0] < 40)
    ).sum() > 50
