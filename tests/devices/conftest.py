"""Fixtures for device tests: an echo device served on a real pty with a stable link path."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from omnid.devices.pty import PtyPort


@pytest.fixture
def echo_pty(tmp_path: Path) -> Iterator[PtyPort]:
    """A pty whose 'device' echoes every byte back, reachable at ``tmp_path / 'ttyECHO'``."""
    port: PtyPort

    def echo(data: bytes) -> None:
        port.write(data)

    port = PtyPort(echo, link_path=tmp_path / "ttyECHO", name="echo")
    port.open()
    try:
        yield port
    finally:
        port.close()
