"""sd_notify over a real AF_UNIX datagram socket."""

from __future__ import annotations

import os
import socket

from omnid.daemon.service import Notifier


def test_ready_watchdog_status_arrive(tmp_path):
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    srv.settimeout(1.0)
    try:
        n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
        assert n.enabled and n.watchdog_s == 2.0
        assert n.ready("driving disabled until perception")
        assert srv.recv(256) == b"READY=1\nSTATUS=driving disabled until perception"
        assert n.watchdog()
        assert srv.recv(256) == b"WATCHDOG=1"
        assert n.status("line1\nline2")
        assert srv.recv(256) == b"STATUS=line1 line2"
        n.close()
    finally:
        srv.close()


def test_abstract_namespace_socket():
    name = f"omnid-test-{os.getpid()}"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind("\0" + name)
    srv.settimeout(1.0)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.stopping()
        assert srv.recv(64) == b"STOPPING=1"
    finally:
        srv.close()


def test_no_socket_is_a_noop_and_dead_socket_does_not_raise(tmp_path):
    assert Notifier({}).ready() is False
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock"), "WATCHDOG_PID": "1"})
    assert n.watchdog_s is None  # the watchdog is meant for another process
    assert n.watchdog() is False and n.errors == 1
