"""LogThrottle: one line per key per interval, the next one says how many were held back."""

from __future__ import annotations

import logging

from omnid.logs import LogThrottle


def test_one_record_per_key_per_interval_and_the_count_held_back(caplog):
    now = [0.0]
    t = LogThrottle(logging.getLogger("throttle-test"), interval_s=5.0, clock=lambda: now[0])
    caplog.set_level(logging.INFO, "throttle-test")
    for i in range(100):  # a fault flapping at 50 Hz for 2 s
        now[0] = i * 0.02
        t.warning("rx", "frame rejected (%d)", i)
    t.warning("other", "a rare message is not hidden behind a frequent one")
    now[0] = 5.0
    assert t.warning("rx", "frame rejected (%d)", 250)
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "frame rejected (0)",
        "a rare message is not hidden behind a frequent one",
        "frame rejected (250) (+99 more since)",
    ]
    assert t.suppressed == 99


def test_keys_are_bounded():
    t = LogThrottle(logging.getLogger("throttle-test"), interval_s=5.0, max_keys=8)
    for i in range(100):
        t.info(f"k{i}", "x")
    assert len(t._last) <= 8
