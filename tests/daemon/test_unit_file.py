"""systemd/omnid.service agrees with what the daemon does: the system calls it needs are
allowed, memory and file descriptors are bounded, `systemd-analyze verify` finds nothing and
the exposure stays ≤ 1.0 (where systemd-analyze exists)."""

from __future__ import annotations

import functools
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from omnid.daemon.config import OmnidConfig

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "systemd" / "omnid.service"
ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze not installed")


def directives(name: str) -> list[str]:
    return re.findall(rf"^{name}=(.*)$", UNIT.read_text(), re.M)


@functools.cache
def expand(group: str) -> frozenset[str]:
    out = subprocess.run(
        [ANALYZE or "systemd-analyze", "syscall-filter", group],
        capture_output=True,
        text=True,
        timeout=30,
    )
    names: set[str] = set()
    for line in out.stdout.splitlines()[1:]:
        word = line.strip()
        if not word or word.startswith("#"):
            continue
        names |= expand(word) if word.startswith("@") else {word}
    return frozenset(names)


def allowed_syscalls() -> set[str]:
    """The allow list the unit's SystemCallFilter= lines build, in order (systemd.exec: the
    first line sets the mode, later ones add or, with ~, remove)."""
    allowed: set[str] = set()
    for value in directives("SystemCallFilter"):
        remove = value.startswith("~")
        for word in value.lstrip("~").split():
            names = expand(word) if word.startswith("@") else {word}
            allowed = allowed - names if remove else allowed | names
    return allowed


def test_limits_are_set_and_consistent():
    assert directives("MemoryMax") and directives("LimitNOFILE")
    assert int(directives("LimitNOFILE")[0]) >= 4 * 64  # the teleop range's most clients
    assert directives("WatchdogSec") == ["2"] and directives("Type") == ["notify"]
    assert "setpriority" in " ".join(directives("SystemCallFilter"))


def test_only_the_control_loop_runs_real_time():
    """FIFO for the process systemd starts (the event loop's thread), reset on fork so that the
    perception worker and the threads it starts compute at the normal policy, and no way for the
    process to raise itself further."""
    assert directives("CPUSchedulingPolicy") == ["fifo"]
    assert 1 <= int(directives("CPUSchedulingPriority")[0]) <= 49  # below the kernel's threads
    assert directives("CPUSchedulingResetOnFork") == ["yes"]
    assert directives("RestrictRealtime") == ["yes"]


@needs_analyze
def test_the_syscalls_the_daemon_makes_are_allowed():
    allowed = allowed_syscalls()
    d = OmnidConfig()
    if d.perception.worker_nice > 0:
        assert "setpriority" in allowed  # os.nice in the perception worker
    assert {"chown", "fchown", "fchownat"} <= allowed  # teleop.group
    assert {"clone", "execve", "socket", "bind", "sendto"} <= allowed  # worker, teleop, notify
    assert "reboot" not in allowed and "mount" not in allowed


@needs_analyze
def test_verify_is_clean_and_exposure_at_most_1(tmp_path):
    omnid = Path(sys.executable).with_name("omnid")
    unit = tmp_path / "omnid.service"
    # verify checks that ExecStart exists: point it at this environment's console script
    unit.write_text(UNIT.read_text().replace("/usr/bin/omnid", str(omnid)))
    out = subprocess.run(
        [ANALYZE or "", "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stdout + out.stderr
    sec = subprocess.run(
        [ANALYZE or "", "security", "--offline=true", str(UNIT)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", sec.stdout + sec.stderr)
    if m is None:
        pytest.skip("this systemd-analyze has no --offline security")
    assert float(m.group(1)) <= 1.0, sec.stdout[-2000:]
