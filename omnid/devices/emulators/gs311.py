"""GS311 head-tilt sensor emulator: answers ``0x50 0x50`` with the angles of a head-motion script.

The script is ``[(t_s, roll_deg, pitch_deg), ...]`` with angles linear in between (held at the
ends, or looped); ``t_s`` counts from the emulator's start. Faults for tests and bench use:
Gaussian noise on the angles (``noise_deg``), a share of requests left unanswered
(``drop_rate``) or answered with a corrupted byte (``corrupt_rate``), ``silent`` (stops
answering), and real disconnections (:meth:`Gs311Emulator.unplug` / :meth:`replug` of the pty,
or scheduled windows ``disconnect=[(t0_s, t1_s), ...]``).

Bench use::

    omnid emulate gs311 --pty [--script FILE] [--link /tmp/ttyTILT] [--noise-deg 0.2]

``FILE`` is YAML (a list of ``[t_s, roll_deg, pitch_deg]``) or text with one ``t_s roll_deg
pitch_deg`` triple per line (commas or spaces, ``#`` comments).
"""

from __future__ import annotations

import argparse
import logging
import random
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from omnid.devices import gs311_codec as codec
from omnid.errors import ConfigError

if TYPE_CHECKING:
    from omnid.devices.pty import PtyPort

log = logging.getLogger(__name__)

Script = Sequence[tuple[float, float, float]]


class HeadMotion:
    """A head-motion script, linear between points (thesis 4.2.2 roll/pitch), deg."""

    def __init__(self, script: Script, loop: bool = False) -> None:
        pts = np.asarray(script, dtype=float).reshape(-1, 3) if len(script) else np.zeros((0, 3))
        if len(pts) == 0:
            pts = np.zeros((1, 3))
        if not np.all(np.isfinite(pts)):
            raise ConfigError("gs311 script: values must be finite numbers")
        if np.any(np.diff(pts[:, 0]) < 0):
            raise ConfigError("gs311 script: times must not decrease")
        self.t = pts[:, 0]
        self.roll = pts[:, 1]
        self.pitch = pts[:, 2]
        self.loop = loop

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])

    def angles_at(self, t_s: float) -> tuple[float, float]:
        """(roll_deg, pitch_deg) at script time ``t_s``."""
        if self.loop and self.duration_s > self.t[0]:
            t_s = self.t[0] + (t_s - self.t[0]) % (self.duration_s - self.t[0])
        return (
            float(np.interp(t_s, self.t, self.roll)),
            float(np.interp(t_s, self.t, self.pitch)),
        )

    @classmethod
    def load(cls, path: str | Path, loop: bool = False) -> HeadMotion:
        """Read a script file (YAML list or text triples); ConfigError names the file and line."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        rows: list[tuple[float, float, float]] = []
        if p.suffix.lower() in (".yaml", ".yml"):
            from omnid.config import load_yaml

            data = load_yaml(p)
            if not isinstance(data, list):
                raise ConfigError(f"{p}: expected a list of [t_s, roll_deg, pitch_deg]")
            for i, item in enumerate(data):
                try:
                    t, r, q = (float(v) for v in item)
                except (TypeError, ValueError):
                    raise ConfigError(
                        f"{p}: item {i}: expected [t_s, roll_deg, pitch_deg]"
                    ) from None
                rows.append((t, r, q))
        else:
            for n, line in enumerate(text.splitlines(), 1):
                line = line.split("#", 1)[0].replace(",", " ").strip()
                if not line:
                    continue
                try:
                    t, r, q = (float(v) for v in line.split())
                except ValueError:
                    raise ConfigError(f"{p}: line {n}: expected 't_s roll_deg pitch_deg'") from None
                rows.append((t, r, q))
        try:
            return cls(rows, loop=loop)
        except ConfigError as exc:
            raise ConfigError(f"{p}: {exc}") from None


class Gs311Emulator:
    """The sensor side of the GS311 protocol, fed request bytes, answering with reply bytes.

    ``handle(data) -> bytes`` is the pure byte interface (in-process tests); :meth:`open_pty`
    serves it on a real pseudo-terminal (:class:`omnid.devices.pty.PtyPort`).
    """

    def __init__(
        self,
        script: Script | HeadMotion = (),
        fmt: codec.Gs311Format | None = None,
        noise_deg: float = 0.0,
        drop_rate: float = 0.0,
        corrupt_rate: float = 0.0,
        disconnect: Sequence[tuple[float, float]] = (),
        seed: int = 0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.motion = script if isinstance(script, HeadMotion) else HeadMotion(script)
        self.fmt = fmt or codec.Gs311Format()
        self.noise_deg = noise_deg
        self.drop_rate = drop_rate
        self.corrupt_rate = corrupt_rate
        self.disconnect = [(float(a), float(b)) for a, b in disconnect]
        self.silent = False
        self.clock = clock
        self.t0 = clock()
        self._rng = random.Random(seed)
        self._pending = b""
        self._lock = threading.Lock()
        self.requests = 0
        self.replies = 0
        self.port: PtyPort | None = None
        self._scheduler: threading.Thread | None = None
        self._stop = threading.Event()

    def elapsed_s(self) -> float:
        return self.clock() - self.t0

    def angles_now(self) -> tuple[float, float]:
        """The script's angles now, without noise, deg."""
        return self.motion.angles_at(self.elapsed_s())

    def handle(self, data: bytes) -> bytes:
        """Process request bytes; returns the reply bytes to send (may be empty)."""
        with self._lock:
            buf = self._pending + data
            out = bytearray()
            while True:
                i = buf.find(codec.READ_ANGLES_REQUEST)
                if i < 0:
                    # keep a trailing 0x50 (a request split across reads); drop other garbage
                    buf = buf[-1:] if buf.endswith(bytes((codec.CMD_READ_ANGLES,))) else b""
                    break
                buf = buf[i + 2 :]
                self.requests += 1
                out += self._reply()
            self._pending = buf
            return bytes(out)

    def _reply(self) -> bytes:
        if self.silent or self._rng.random() < self.drop_rate:
            return b""
        roll, pitch = self.angles_now()
        if self.noise_deg > 0:
            roll += self._rng.gauss(0.0, self.noise_deg)
            pitch += self._rng.gauss(0.0, self.noise_deg)
        pkt = bytearray(codec.encode_angles_reply(*self.fmt.deg_to_counts(roll, pitch), self.fmt))
        if self._rng.random() < self.corrupt_rate:
            pkt[self._rng.randrange(1, len(pkt))] ^= 1 << self._rng.randrange(8)
        self.replies += 1
        return bytes(pkt)

    # -- pty serving ---------------------------------------------------------------------
    def open_pty(self, link_path: str | None = None) -> str:
        """Serve on a new pty (at ``link_path`` if given, a re-pointed symlink); returns the path."""
        from omnid.devices.pty import PtyPort

        port = PtyPort(self._on_data, link_path=link_path, name="gs311")
        self.port = port
        path = port.open()
        if self.disconnect and self._scheduler is None:
            self._scheduler = threading.Thread(
                target=self._run_schedule, name="gs311-disconnect", daemon=True
            )
            self._scheduler.start()
        return path

    def _on_data(self, data: bytes) -> None:
        reply = self.handle(data)
        if reply and self.port is not None:
            self.port.write(reply)

    def unplug(self) -> None:
        """Pull the adapter: the driver's reads fail (EIO/EOF) and the path disappears."""
        if self.port is not None:
            self.port.unplug()

    def replug(self) -> str:
        """Plug it back: a fresh pty behind the same link path."""
        if self.port is None:
            raise ConfigError("gs311 emulator: replug before open_pty")
        with self._lock:
            self._pending = b""
        return self.port.replug()

    def _run_schedule(self) -> None:
        for t_off, t_on in sorted(self.disconnect):
            if self._stop.wait(max(0.0, t_off - self.elapsed_s())):
                return
            log.info("gs311 emulator: disconnected at t=%.2f s", self.elapsed_s())
            self.unplug()
            if self._stop.wait(max(0.0, t_on - self.elapsed_s())):
                return
            self.replug()
            log.info("gs311 emulator: reconnected at t=%.2f s", self.elapsed_s())

    def close(self) -> None:
        self._stop.set()
        if self._scheduler is not None:
            self._scheduler.join(timeout=1.0)
            self._scheduler = None
        if self.port is not None:
            self.port.close()


# -- omnid emulate gs311 -------------------------------------------------------------------


def _window(text: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected T0:T1 in seconds, got {text!r}") from None
    if not 0 <= a < b:
        raise argparse.ArgumentTypeError(f"expected 0 <= T0 < T1, got {text!r}")
    return a, b


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``omnid emulate gs311``."""
    parser.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal (default)")
    parser.add_argument("--link", help="stable symlink to the pty (survives replug)")
    parser.add_argument("--script", help="head-motion script file (YAML or 't roll pitch' lines)")
    parser.add_argument("--loop", action="store_true", help="repeat the script")
    parser.add_argument("--noise-deg", type=float, default=0.0, help="Gaussian noise, deg")
    parser.add_argument("--drop-rate", type=float, default=0.0, help="share of requests ignored")
    parser.add_argument(
        "--corrupt-rate", type=float, default=0.0, help="share of replies corrupted"
    )
    parser.add_argument(
        "--disconnect",
        type=_window,
        action="append",
        default=[],
        metavar="T0:T1",
        help="unplug from T0 to T1 s after start (repeatable)",
    )
    parser.add_argument("--byte-order", choices=["big", "little"], default="big")
    parser.add_argument("--deg-per-count", type=float, default=90.0 / 4096.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration-s", type=float, default=None, help="stop after this long")


def run(args: argparse.Namespace) -> int:
    """Serve until interrupted (or ``--duration-s``); prints the path to open."""
    from omnid.config import from_mapping

    motion = HeadMotion.load(args.script, loop=args.loop) if args.script else HeadMotion([])
    fmt = from_mapping(
        codec.Gs311Format, {"byte_order": args.byte_order, "deg_per_count": args.deg_per_count}
    )
    for name in ("drop_rate", "corrupt_rate"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            raise ConfigError(f"--{name.replace('_', '-')}: must be in [0, 1]")
    emu = Gs311Emulator(
        motion,
        fmt,
        noise_deg=args.noise_deg,
        drop_rate=args.drop_rate,
        corrupt_rate=args.corrupt_rate,
        disconnect=args.disconnect,
        seed=args.seed,
    )
    path = emu.open_pty(args.link)
    print(path, flush=True)
    try:
        end = None if args.duration_s is None else time.monotonic() + args.duration_s
        while end is None or time.monotonic() < end:
            time.sleep(0.05 if end is None else max(0.0, min(0.05, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
        print(f"gs311 emulator: {emu.requests} requests, {emu.replies} replies", flush=True)
    return 0
