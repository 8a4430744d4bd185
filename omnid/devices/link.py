"""The base of the polled device links: one task, a period grid, reconnect with back-off.

STYLE.md point 2: "each device sits behind a small interface whose base class owns deadlines,
validation and the open/closed state; backends implement only the raw read/write". The links
that poll a device half-duplex (the control unit, the GS311 tilt sensor) share all of this:

- :meth:`PolledLink.start` / :meth:`PolledLink.stop` of one asyncio task (stop waits at most
  :attr:`PolledLink.stop_timeout_s` for the task, then cancels it; a task that failed is logged);
- the run loop: open the transport → one :meth:`PolledLink._exchange` every ``period_s`` on the
  event loop's monotonic clock (an overrun of more than a period restarts the grid instead of
  bursting to catch up) → on a port error (:class:`~omnid.errors.DeviceError`) or an unexpected
  exception drop the transport and reopen it with exponential back-off (``reconnect_initial_s``
  doubling up to ``reconnect_max_s``, back to the start as soon as the device answers). Every
  failure backs off before the next attempt, so a port that opens but fails at once cannot spin
  the event loop;
- the wake-up event (:meth:`PolledLink._wake_up`): ends the current wait early (stop, an urgent
  command) without moving the period grid; a wake-up set during an exchange is not lost;
- the shared health fields (:class:`LinkHealth`: connected, port_errors, reconnects,
  last_error), and rate-limited logging of what can repeat (``_throttle``).

A link implements only :meth:`~PolledLink._on_open` (reset its parser), :meth:`~PolledLink._exchange`
(one request → reply and its bookkeeping; returns whether the device answered) and, where it
needs them, the hooks :meth:`~PolledLink._port_lost`, :meth:`~PolledLink._check_stale`,
:meth:`~PolledLink._farewell` and :meth:`~PolledLink._on_stopped`. Fail-safe decisions (when a
reading or status turns ``None``) stay with each link: they differ per device.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Generic, TypeVar

from omnid.config import require
from omnid.devices.transport import Transport
from omnid.errors import DeviceError
from omnid.logs import LogThrottle

__all__ = ["LinkHealth", "PolledLink", "require_reconnect"]


def require_reconnect(reconnect_initial_s: float, reconnect_max_s: float) -> None:
    """Validate a link's back-off keys (for settings' ``__post_init__``): initial > 0 s, max ≥
    initial; raises :class:`~omnid.errors.ConfigError` naming the key."""
    require(reconnect_initial_s > 0, "reconnect_initial_s", "must be > 0")
    require(
        reconnect_max_s >= reconnect_initial_s, "reconnect_max_s", "must be ≥ reconnect_initial_s"
    )


@dataclass
class LinkHealth:
    """Health fields every polled link keeps (links subclass this with their own counters)."""

    connected: bool = False
    port_errors: int = 0
    reconnects: int = 0
    last_error: str = ""


H = TypeVar("H", bound=LinkHealth)


class PolledLink(Generic[H]):
    """One asyncio task polling a device through a :class:`Transport` (see module docstring).

    ``transport_factory`` opens the port (raises :class:`DeviceError` when it cannot);
    ``health`` is the link's own health record, whose shared fields this class keeps.
    """

    #: how logs name the device ("control unit", "tilt sensor")
    device_name: ClassVar[str] = "device"
    #: the asyncio task's name
    task_name: ClassVar[str] = "polled-link"
    #: the logger the link's messages go to (each link's module logger)
    _log: ClassVar[logging.Logger] = logging.getLogger(__name__)
    #: how long :meth:`stop` waits for the task before cancelling it, s
    stop_timeout_s: ClassVar[float] = 1.0

    def __init__(
        self,
        transport_factory: Callable[[], Transport],
        health: H,
        *,
        period_s: float,
        reconnect_initial_s: float,
        reconnect_max_s: float,
    ) -> None:
        self._factory = transport_factory
        self._health = health
        self._period_s = period_s
        self._reconnect_initial_s = reconnect_initial_s
        self._reconnect_max_s = reconnect_max_s
        self._transport: Transport | None = None
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self._wake = asyncio.Event()
        #: repeating messages (a flapping port) at most once per 5 s each
        self._throttle = LogThrottle(self._log, interval_s=5.0)

    # -- public API ----------------------------------------------------------------------
    async def start(self) -> None:
        """Start the link task (returns at once; it opens the port in the background)."""
        if self._task is not None:
            return
        self._stopping = False
        self._task = asyncio.create_task(self._run(), name=self.task_name)

    async def stop(self) -> None:
        """End the task (waiting at most ``stop_timeout_s``), say goodbye, close the port."""
        self._stopping = True
        self._before_stop()
        task = self._task
        if task is not None and task.done():
            if not task.cancelled() and task.exception() is not None:
                self._log.error("%s link task had failed: %r", self.device_name, task.exception())
        elif task is not None:
            self._wake.set()
            try:
                async with asyncio.timeout(self.stop_timeout_s):
                    await task
            except TimeoutError:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
            except Exception:
                self._log.exception("%s link task had failed", self.device_name)
        self._task = None
        t = self._transport
        if t is not None and t.is_open:
            await self._farewell(t)
        if t is not None:
            t.close()
        self._transport = None
        self._health.connected = False
        self._on_stopped()

    @property
    def running(self) -> bool:
        """The link's task exists and has not ended (what the daemon's watchdog vouches for)."""
        return self._task is not None and not self._task.done()

    # -- hooks for the links -------------------------------------------------------------
    def _on_open(self) -> None:
        """Called after the port opened (reset parsers)."""

    async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
        """One request → reply on ``self._transport`` with its bookkeeping.

        Returns whether the device answered (which resets the reconnect back-off). A port
        error is raised as :class:`DeviceError`; the run loop then drops and reopens the port.
        """
        raise NotImplementedError

    def _port_error_reason(self, exc: DeviceError) -> str:
        """What ``last_error`` says after a port error."""
        return str(exc)

    def _port_lost(self, port_name: str, reason: str) -> None:
        """Called after the port was dropped for ``reason`` (log, mark unhealthy)."""
        self._throttle.warning(
            "port lost", "%s port %s lost: %s", self.device_name, port_name, reason
        )

    def _check_stale(self) -> None:
        """Called by the task after every exchange and failed open (log staleness even if
        nobody asks)."""

    def _before_stop(self) -> None:
        """Called first thing in :meth:`stop`, before the task ends."""

    async def _farewell(self, transport: Transport) -> None:
        """Last words to the device before :meth:`stop` closes an open port (best effort)."""

    def _on_stopped(self) -> None:
        """Called at the end of :meth:`stop` (forget readings, mark unhealthy)."""

    # -- the machinery -------------------------------------------------------------------
    def _wake_up(self) -> None:
        """End the task's current wait now (the period grid stays)."""
        self._wake.set()

    def _connect(self) -> bool:
        try:
            self._transport = self._factory()
        except DeviceError as exc:
            self._health.last_error = str(exc)
            return False
        self._on_open()
        self._health.connected = True
        self._throttle.info("port open", "%s port %s open", self.device_name, self._transport.name)
        return True

    def _drop_transport(self, reason: str) -> None:
        t = self._transport
        self._transport = None
        self._health.connected = False
        if t is None:
            return
        t.close()
        self._health.port_errors += 1
        self._health.last_error = reason
        self._port_lost(t.name, reason)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        backoff = self._reconnect_initial_s
        ever_connected = False
        next_t = loop.time()
        while not self._stopping:
            if self._transport is None:
                if self._connect():
                    if ever_connected:
                        self._health.reconnects += 1
                    ever_connected = True
                    next_t = loop.time()
                else:
                    self._check_stale()
                    await self._sleep(backoff)
                    backoff = min(backoff * 2, self._reconnect_max_s)
                    continue
            try:
                answered = await self._exchange(loop)
            except Exception as exc:
                if isinstance(exc, DeviceError):
                    self._drop_transport(self._port_error_reason(exc))
                else:  # a bug must not leave a stale value looking valid, nor kill the task
                    if self._throttle.error(
                        "internal", "%s link: unexpected error %r", self.device_name, exc
                    ):
                        self._log.debug("unexpected error", exc_info=True)
                    self._drop_transport(f"internal error: {exc!r}")
                # back off before reopening: a port that opens but fails at once must not
                # spin the event loop
                await self._sleep(backoff)
                backoff = min(backoff * 2, self._reconnect_max_s)
                continue
            self._check_stale()
            if answered:
                backoff = self._reconnect_initial_s  # the device answered: a fresh back-off
            now = loop.time()
            if now >= next_t:  # the grid's exchange: on to the next grid point
                next_t += self._period_s
            # else a wake-up (urgent command) ran it early: the grid stays, the next regular
            # exchange is still due at next_t (advancing here pushed it one period further for
            # every urgent exchange, so a burst of them silenced the link)
            delay = next_t - now
            if delay < -self._period_s:  # overran (loop blocked): restart the grid
                next_t = loop.time()
                delay = 0.0
            await self._sleep(max(delay, 0.0))

    async def _sleep(self, delay_s: float) -> None:
        # cleared after waking, so a wake-up set during an exchange (urgent command) is not lost
        if self._stopping:
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(delay_s):
                await self._wake.wait()
        self._wake.clear()
