"""Lint of the package, so that the tests enforce it like any other check. The type check
(mypy: 26-31 s of CPU without its cache, as in every fresh clone) is CI's own step after the
tests (``.ci/run``)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


# the test extra's tools, run by this interpreter (not whatever PATH finds, or nothing: a venv
# used without activating it would skip the checks and look green)
@pytest.mark.skipif(importlib.util.find_spec("ruff") is None, reason="ruff is not installed")
def test_ruff_clean():
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "ruff",
            "check",
            "--output-format",
            "concise",
            "omnid",
            "tests",
            "tools",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
