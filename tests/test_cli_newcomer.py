"""What a newcomer stumbled on (issue 12), each through the real console entry: one clear line
instead of a traceback or a wrong hint, help texts that say what the command does."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest

from omnid.cli import build_parser, main
from omnid.core.geometry import StereoRig
from omnid.sim.installation import installation_captures, write_capture

NAMES = ("mask1", "base1", "mask2", "base2")


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    folder = tmp_path_factory.mktemp("newcomer")
    floor_cap, _ = installation_captures(StereoRig.nominal(), seed=3)
    args = []
    for name in NAMES:
        assert cv2.imwrite(str(folder / f"{name}.png"), getattr(floor_cap, name))
        args += [f"--{name}", str(folder / f"{name}.png")]
    return folder, args


def extra_args(folder: Path) -> list[str]:
    """The installer's extra captures (a box, a wall) beside the floor, for calibrate --extra."""
    extras = installation_captures(StereoRig.nominal(), seed=3)[1]
    out = []
    for name, cap in extras.items():
        out += ["--extra", str(write_capture(cap, folder / f"extra_{name}"))]
    return out


def one_error_line(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"omnid {command}: error: "), err
    assert "Traceback" not in err[0]
    return err[0]


def test_calibration_given_a_png_is_one_line(floor, capsys) -> None:
    folder, images = floor
    assert main(["perceive", "--calib", str(folder / "mask1.png"), *images]) == 2
    line = one_error_line(capsys, "perceive")
    assert "mask1.png" in line and "not a text" in line


def test_calibrate_to_a_missing_folder_names_the_file_asked_for(floor, capsys) -> None:
    folder, images = floor
    out = "/nonexistent-omnid/c.yaml"
    argv = ["calibrate", *images, *extra_args(folder), "--floor-depth-mm", "1100", "--out", out]
    assert main(argv) == 2
    line = one_error_line(capsys, "calibrate")
    assert out in line and ".tmp" not in line


def test_scene_without_out_says_its_name_once(capsys) -> None:
    assert main(["scene", "three_boxes"]) == 2
    line = one_error_line(capsys, "scene")
    assert line.count("omnid scene") == 1 and "--out" in line


def test_perceive_with_mask_equal_to_base_is_refused_with_a_hint(floor, tmp_path, capsys) -> None:
    folder, images = floor
    calib = tmp_path / "calib.yaml"
    argv = ["calibrate", *images, *extra_args(folder), "--floor-depth-mm", "1100"]
    assert main([*argv, "--out", str(calib)]) == 0
    capsys.readouterr()
    same = [a if not a.endswith("base1.png") else str(folder / "mask1.png") for a in images]
    assert main(["perceive", "--calib", str(calib), *same]) == 2
    line = one_error_line(capsys, "perceive")
    assert "--mask1 and --base1 are the same picture" in line
    # a capture without dots (laser off in both) is answered, with a hint on stderr
    swap = {"base1.png": "mask2.png", "base2.png": "mask1.png"}
    dark = [str(folder / swap[Path(a).name]) if Path(a).name in swap else a for a in images]
    assert main(["perceive", "--calib", str(calib), *dark]) == 0
    assert "no laser dots found" in capsys.readouterr().err
    # files are written as the umask says (0644 under 022), not 0600
    old = os.umask(0o022)
    try:
        argv = ["calibrate", *images, *extra_args(folder), "--floor-depth-mm", "1100"]
        assert main([*argv, "--out", str(calib)]) == 0
    finally:
        os.umask(old)
    assert calib.stat().st_mode & 0o777 == 0o644


def subparser(name: str):  # type: ignore[no-untyped-def]
    parser = build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return action.choices[name]


def test_help_texts_say_the_truth_without_markup() -> None:
    run_help = subparser("run").format_help()
    assert "/etc/omnid/omnid.yaml" in " ".join(run_help.split())
    demo = subparser("demo")
    assert demo.get_default("default_duration_s") == 130.0
    assert "(130)" in demo.format_help() and "(45)" not in demo.format_help()
    parser = build_parser()
    action = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, sub in action.choices.items():
        assert "`" not in sub.format_help(), name
    assert "`" not in parser.format_help()


def test_teleop_without_a_terminal_says_so(tmp_path) -> None:
    with open(os.devnull) as devnull:
        p = subprocess.run(
            [sys.executable, "-m", "omnid.cli", "teleop", "--socket", str(tmp_path / "s")],
            stdin=devnull,
            capture_output=True,
            text=True,
            timeout=30,
        )
    assert p.returncode == 2
    assert "standard input is not a terminal" in p.stderr and "Errno" not in p.stderr


def test_emulator_removes_its_link_when_terminated(tmp_path) -> None:
    link = tmp_path / "ttyCU"
    p = subprocess.Popen(
        [sys.executable, "-m", "omnid.cli", "emulate", "control-unit", "--link", str(link)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert p.stdout is not None
        assert p.stdout.readline().strip() == str(link)
        assert link.is_symlink()
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=20) == 0
    finally:
        if p.poll() is None:
            p.kill()
    deadline = time.monotonic() + 1.0
    while link.is_symlink() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not link.is_symlink() and not os.path.lexists(link)


@pytest.mark.parametrize(
    "argv, option",
    [
        (["perceive", "--rig-x-offset-mm", "nan"], "--rig-x-offset-mm"),
        (["perceive", "--half-width-mm", "-5"], "--half-width-mm"),
        (["calibrate", "--floor-depth-mm", "inf"], "--floor-depth-mm"),
        (["calibrate", "--floor-depth-mm", "400", "--baseline-mm", "0"], "--baseline-mm"),
        (["simulate", "--duration-s", "nan"], "--duration-s"),
        (["demo", "--duration-s", "-1"], "--duration-s"),
        (["bench", "--duration-s", "nan"], "--duration-s"),
        (["teleop", "--reply-timeout-s", "0"], "--reply-timeout-s"),
        (["experiment", "table72", "--grid-step-mm", "nan"], "--grid-step-mm"),
    ],
)
def test_a_number_that_is_no_number_is_refused_before_anything_runs(argv, option, capsys):
    """``nan`` passes ``float()`` and every comparison's negation: without the parser's check
    perceive drew its map at a NaN offset and bench ran 0 s and reported success."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]  # after argparse's usage: the one line that says why
    assert "error:" in last and option in last
