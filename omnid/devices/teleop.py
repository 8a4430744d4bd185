"""Keyboard teleoperation: a line protocol over a local Unix socket (thesis 4.2.1).

The daemon runs :class:`TeleopServer`; ``omnid teleop --socket PATH`` (the client) reads arrow
keys from a terminal and sends one line per key press. Protocol, one ASCII line each way::

    client → server:  forward | left | right | stop | ping
    server → client:  ok | pong | error <reason>

Each accepted line becomes a :class:`KeyCommand` stamped with the server's monotonic clock and
handed to ``on_command`` (the daemon's ``ControlCore.on_key``) and kept as ``latest``. Nothing is
sent on key release or while no key is pressed: the daemon's mux times out a silent source, so a
terminal that hangs stops the chair within ``keyboard.hold_s``; a client that disconnects while
its motion key is the newest command stops it at once (the server hands on a ``stop``).

Access control is by file permission: the socket is created under a temporary name, given mode
``mode`` (default 0660) and group ``group`` (when set), and only then renamed to its final path,
so it is never reachable with looser permissions. Each client's uid is logged (SO_PEERCRED,
rate-limited).

Fair limits: at most ``max_clients`` at a time; a client silent for ``idle_timeout_s`` is
disconnected (the client sends ``ping`` to stay connected), and when all places are taken a new
client takes the place of the one idle longest if that one has been silent for
``evict_idle_s`` — a client that is driving sends key repeats and is never idle that long.
Each client may send at most ``max_lines_per_s`` lines a second (a burst of a second's worth);
lines beyond that are answered ``error rate limit`` and do nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import grp
import logging
import os
import socket
import stat
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from omnid.config import Settings, require, setting
from omnid.errors import ConfigError, DeviceError
from omnid.logs import LogThrottle

log = logging.getLogger(__name__)

Command = Literal["forward", "left", "right", "stop"]
COMMANDS: tuple[Command, ...] = ("forward", "left", "right", "stop")


@dataclass(frozen=True)
class KeyCommand:
    """A rider's discrete command and the monotonic time it arrived, s."""

    command: Command
    timestamp_s: float

    def __post_init__(self) -> None:
        if self.command not in COMMANDS:
            raise ValueError(f"KeyCommand.command must be one of {COMMANDS}, got {self.command!r}")


@dataclass(frozen=True)
class TeleopSettings(Settings):
    """Teleop socket settings."""

    socket_path: str = "/run/omnid/teleop.sock"
    group: str | None = None  # group allowed to drive (with mode 0660); None = daemon's group
    mode: int = setting(0o660, 0, 0o777)
    max_clients: int = setting(4, 1, 64)
    max_line_bytes: int = setting(64, 16, 4096)
    idle_timeout_s: float = setting(30.0, 1.0, 3600.0)  # a silent client is disconnected
    evict_idle_s: float = setting(2.0, 0.1, 3600.0)  # full: a client this idle makes room
    max_lines_per_s: float = setting(50.0, 1.0, 1000.0)  # per client; beyond: refused

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.mode & 0o007 == 0, "mode", "must not grant access to others (e.g. 0660, octal)"
        )


class TeleopServer:
    """Asyncio Unix-socket server turning lines into :class:`KeyCommand` (see module docstring)."""

    def __init__(
        self,
        settings: TeleopSettings | None = None,
        on_command: Callable[[KeyCommand], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings or TeleopSettings()
        self.on_command = on_command
        self.clock = clock
        self.latest: KeyCommand | None = None
        self.commands = 0
        self.errors = 0
        self._server: asyncio.Server | None = None
        self._clients: dict[asyncio.Task[None], _Client] = {}
        self._holder: _Client | None = None  # whose motion key is the newest command
        self._throttle = LogThrottle(log, interval_s=5.0, clock=clock)
        self.refused = 0
        self.evicted = 0
        self.rate_limited = 0

    @property
    def path(self) -> Path:
        return Path(self.settings.socket_path)

    async def start(self) -> None:
        """Create the socket (mode and group applied before it appears at its path) and serve."""
        s = self.settings
        gid = -1
        if s.group is not None:
            try:
                gid = grp.getgrnam(s.group).gr_gid
            except KeyError:
                raise ConfigError(f"teleop.group: no such group {s.group!r}") from None
        path = self.path
        with contextlib.suppress(FileNotFoundError):
            if not stat.S_ISSOCK(path.lstat().st_mode):
                raise ConfigError(f"teleop.socket_path: {path} exists and is not a socket")
            path.unlink()  # a stale socket left by a previous run
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            sock.bind(str(tmp))
            os.chmod(tmp, s.mode)
            if gid != -1:
                os.chown(tmp, -1, gid)
            sock.listen(s.max_clients)
            os.rename(tmp, path)
        except OSError as exc:
            sock.close()
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise DeviceError(f"teleop socket {path}: cannot create ({exc.strerror})") from exc
        self._server = await asyncio.start_unix_server(
            self._serve, sock=sock, limit=s.max_line_bytes
        )
        log.info("teleop socket %s (mode %o, group %s)", path, s.mode, s.group or "default")

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            for client in list(self._clients.values()):
                client.writer.close()  # ends its read: the task finishes by itself
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
            self._server = None
            with contextlib.suppress(OSError):
                self.path.unlink()

    def handle_line(self, line: str, client: _Client | None = None) -> str:
        """Process one protocol line (from ``client``, when served); returns the reply line
        (without newline)."""
        word = line.strip().lower()
        if word == "ping":
            return "pong"
        if word in COMMANDS:
            self._deliver(KeyCommand(word, self.clock()))
            self._holder = client if word != "stop" else None
            return "ok"
        self.errors += 1
        shown = word[:20] + ("..." if len(word) > 20 else "")
        return f"error unknown command {shown!r} (known: {', '.join(COMMANDS)}, ping)"

    def _deliver(self, cmd: KeyCommand) -> None:
        self.latest = cmd
        self.commands += 1
        if self.on_command is not None:
            self.on_command(cmd)

    def _release(self, client: _Client) -> None:
        """``client`` is gone: if the newest command was its motion key, stop now rather than
        let the press hold for ``keyboard.hold_s`` with nobody left to let go of it."""
        if self._holder is client:
            self._holder = None
            log.warning("teleop client (uid %s) left while driving: stop", client.uid)
            self._deliver(KeyCommand("stop", self.clock()))

    def _make_room(self) -> bool:
        """All places taken: evict the client idle longest if it has been idle long enough."""
        s = self.settings
        if len(self._clients) < s.max_clients:
            return True
        now = self.clock()
        idlest = min(self._clients.values(), key=lambda c: c.last_s)
        if now - idlest.last_s < s.evict_idle_s:
            return False
        self.evicted += 1
        self._throttle.info(
            "evict",
            "teleop client (uid %s) idle %.0f s: disconnected to make room",
            idlest.uid,
            now - idlest.last_s,
        )
        with contextlib.suppress(Exception):
            idlest.writer.write(b"error idle: disconnected to make room\n")
        idlest.writer.close()
        self._clients = {t: c for t, c in self._clients.items() if c is not idlest}
        return True

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        s = self.settings
        peer = _peer_uid(writer)
        if task is None or not self._make_room():
            self.refused += 1
            self._throttle.warning("full", "teleop client (uid %s) refused: too many clients", peer)
            writer.write(b"error too many clients\n")
            writer.close()
            return
        client = _Client(writer, peer, self.clock(), s.max_lines_per_s)
        self._clients[task] = client
        self._throttle.info("connect", "teleop client connected (uid %s)", peer)
        try:
            while True:
                try:
                    async with asyncio.timeout(s.idle_timeout_s):
                        raw = await reader.readuntil(b"\n")
                except TimeoutError:
                    writer.write(b"error idle timeout\n")
                    break
                except asyncio.LimitOverrunError:
                    self.errors += 1
                    writer.write(b"error line too long\n")
                    break
                except asyncio.IncompleteReadError:
                    break
                if len(raw) > s.max_line_bytes:
                    self.errors += 1
                    writer.write(b"error line too long\n")
                    break
                now = self.clock()
                client.last_s = now
                line = raw.decode("ascii", errors="replace")
                # a stop is never rate-limited: after a burst of key repeats it is the one
                # line that must get through (it takes no token, and can move nothing)
                if line.strip().lower() == "stop" or client.take(now):
                    reply = self.handle_line(line, client)
                else:
                    self.rate_limited += 1
                    reply = "error rate limit"
                writer.write(reply.encode() + b"\n")
                await writer.drain()
        except (ConnectionError, OSError) as exc:
            self._throttle.info("dropped", "teleop client (uid %s) dropped: %s", peer, exc)
        except asyncio.CancelledError:
            pass  # the server stops: end quietly (a cancelled handler is logged as an error)
        finally:
            self._throttle.info("disconnect", "teleop client disconnected (uid %s)", peer)
            self._release(client)
            writer.close()
            self._clients.pop(task, None)


class _Client:
    """One connected client: its writer, uid, last activity and line budget (token bucket)."""

    def __init__(
        self, writer: asyncio.StreamWriter, uid: int | None, now_s: float, rate: float
    ) -> None:
        self.writer = writer
        self.uid = uid
        self.last_s = now_s
        self.rate = rate
        self.tokens = rate  # a second's worth of lines as the burst
        self._t = now_s

    def take(self, now_s: float) -> bool:
        """Spend one line of the budget; False when it is used up."""
        self.tokens = min(self.rate, self.tokens + (now_s - self._t) * self.rate)
        self._t = now_s
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


def _peer_uid(writer: asyncio.StreamWriter) -> int | None:
    sock = writer.get_extra_info("socket")
    if sock is None or not hasattr(socket, "SO_PEERCRED"):
        return None
    try:
        creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    except OSError:
        return None
    return int(struct.unpack("3i", creds)[1])


# --- client side: keystrokes → commands -----------------------------------------------------

Key = Literal["forward", "left", "right", "stop", "quit"]

_ARROWS: dict[bytes, Key] = {b"A": "forward", b"B": "stop", b"C": "right", b"D": "left"}


class KeyDecoder:
    """Terminal bytes → keys: arrows (``ESC [ X`` or ``ESC O X``) up/left/right/down =
    forward/left/right/stop (thesis 4.2.1); space also stops; ``q`` or Ctrl-C quits.
    Anything else is ignored. Fed bytes incrementally (an escape sequence may be split)."""

    def __init__(self) -> None:
        self._buf = b""

    def feed(self, data: bytes) -> list[Key]:
        buf = self._buf + data
        out: list[Key] = []
        i = 0
        while i < len(buf):
            b = buf[i : i + 1]
            if b == b"\x1b":
                if len(buf) - i < 3:
                    if buf[i + 1 : i + 2] in (b"", b"[", b"O"):
                        break  # wait for the rest of the sequence
                    i += 1
                    continue
                if buf[i + 1 : i + 2] in (b"[", b"O") and buf[i + 2 : i + 3] in _ARROWS:
                    out.append(_ARROWS[buf[i + 2 : i + 3]])
                    i += 3
                    continue
                i += 1
                continue
            if b in (b"q", b"Q", b"\x03", b"\x04"):
                out.append("quit")
            elif b == b" ":
                out.append("stop")
            i += 1
        self._buf = buf[i:]
        return out


async def run_client(
    socket_path: str,
    input_fd: int,
    echo: Callable[[str], None] = print,
    reply_timeout_s: float = 1.0,
    keepalive_s: float = 10.0,
) -> int:
    """Send the keys read from ``input_fd`` to the teleop server; returns an exit code.

    Without a key for ``keepalive_s`` it sends ``ping`` (the server disconnects silent clients).
    Ends on ``q`` (0), end of input (0), or a lost/unanswering server (1).
    """
    try:
        reader, writer = await asyncio.open_unix_connection(socket_path)
    except OSError as exc:
        raise DeviceError(f"teleop socket {socket_path}: cannot connect ({exc.strerror})") from exc
    loop = asyncio.get_running_loop()
    ready = asyncio.Event()
    loop.add_reader(input_fd, ready.set)
    decoder = KeyDecoder()
    try:
        while True:
            try:
                await asyncio.wait_for(ready.wait(), keepalive_s)
            except TimeoutError:
                keys: list[str] = ["ping"]
            else:
                ready.clear()
                try:
                    data = os.read(input_fd, 256)
                except BlockingIOError:
                    continue
                if not data:
                    return 0
                keys = list(decoder.feed(data))
            for key in keys:
                if key == "quit":
                    return 0
                writer.write(key.encode() + b"\n")
                try:
                    await writer.drain()
                    reply = await asyncio.wait_for(reader.readline(), reply_timeout_s)
                except (OSError, TimeoutError) as exc:
                    echo(f"teleop: server lost ({exc or 'no reply'})")
                    return 1
                if not reply:
                    echo("teleop: server closed the connection")
                    return 1
                if key != "ping":
                    echo(f"{key}: {reply.decode(errors='replace').strip()}")
    finally:
        loop.remove_reader(input_fd)
        writer.close()
