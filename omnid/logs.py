"""Rate-limited logging for messages that can repeat (a flapping link, a noisy bus).

A fault that comes and goes 50 times a second must not write 50 lines a second: the journal
would fill, and the one line that matters would scroll away. :class:`LogThrottle` lets one
record per *key* through every ``interval_s`` and appends to the next one how many were held
back::

    throttle = LogThrottle(log, interval_s=5.0)
    throttle.warning("rx_error", "control unit rejected a frame (%d so far)", n)
    # ... at most one line per 5 s for "rx_error"; the next says "(+12 more since)"

Keys are independent, so a rare message is never hidden behind a frequent one. The clock is
monotonic and injectable.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

__all__ = ["LogThrottle"]


class LogThrottle:
    """At most one record per key every ``interval_s`` seconds (see the module docstring)."""

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
        max_keys: int = 256,
    ) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self.clock = clock
        self.max_keys = max_keys
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self.suppressed = 0

    def log(self, key: str, level: int, msg: str, *args: Any) -> bool:
        """Log ``msg % args`` at ``level`` unless ``key`` logged within ``interval_s``; returns
        whether it was written."""
        now = self.clock()
        last = self._last.get(key)
        if last is not None and now - last < self.interval_s:
            self._held[key] = self._held.get(key, 0) + 1
            self.suppressed += 1
            return False
        if key not in self._last and len(self._last) >= self.max_keys:
            oldest = min(self._last, key=self._last.__getitem__)  # bounded: drop the oldest key
            del self._last[oldest]
            self._held.pop(oldest, None)
        self._last[key] = now
        held = self._held.pop(key, 0)
        if held:
            msg = f"{msg} (+{held} more since)"
        self.logger.log(level, msg, *args)
        return True

    def warning(self, key: str, msg: str, *args: Any) -> bool:
        return self.log(key, logging.WARNING, msg, *args)

    def info(self, key: str, msg: str, *args: Any) -> bool:
        return self.log(key, logging.INFO, msg, *args)

    def error(self, key: str, msg: str, *args: Any) -> bool:
        return self.log(key, logging.ERROR, msg, *args)
