"""The recorder: records handed over by the control loop, written as MCAP by a writer thread.

The control loop (or the simulator) calls :meth:`Recorder.put` — a tuple appended to a bounded
``deque``, a few microseconds, never a lock wait, never I/O. When the queue is full the record
is dropped and counted (``/recorder.dropped``), never waited for. A writer thread wakes every
``poll_s``, encodes what is queued (:mod:`omnid.record.topics`), writes it with the ``mcap``
library and hands the same bytes to the live view (Foxglove WebSocket server of
``foxglove-sdk``) when one runs.

Segments: the file named by ``record.path`` (``strftime`` codes expanded) is closed and a new
one started past ``max_file_mb`` or ``max_file_s``; past ``max_total_mb`` the oldest segments
of the same path are deleted. An existing file is never overwritten: a taken name gets ``-1``,
``-2``... Each segment starts with the ``omnid`` metadata record (version, configuration,
calibration, rig) and the latched topics, so it can be replayed alone.

Failures: an error writing (disk full, permission, a removed folder) is logged once, the
segment is abandoned and records are dropped (counted) until a new segment opens — tried
every ``retry_s``; the chair is never stopped by it, and the daemon's own fault handling and
logs do not pass through here. A bug in an encoder drops that record (logged once per kind).

``threaded=False`` (the simulator's virtual clock): no thread; :meth:`pump` writes what is
queued, so a faster-than-real-time run loses nothing.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from omnid.errors import ConfigError
from omnid.record import topics as tp
from omnid.record.settings import RecordSettings

log = logging.getLogger(__name__)

MB = 1024 * 1024
#: the writer thread pauses after this many records (see :meth:`Recorder._drain`)
SLICE_RECORDS = 4
SLICE_PAUSE_S = 0.0002


def require_recording_libraries() -> None:
    """ConfigError with the install hint when the ``record`` extra is missing."""
    try:
        import foxglove  # noqa: F401
        import mcap  # noqa: F401
    except ImportError as exc:
        raise ConfigError(
            f"recording needs the 'record' extra ({exc.name} is not installed): "
            "pip install 'omnid[record]'"
        ) from None


class SegmentFiles:
    """Names of a recording's segments, and the budget over them (oldest deleted first)."""

    def __init__(self, pattern: str) -> None:
        p = Path(pattern)
        if "%" in str(p.parent):
            raise ConfigError(f"record.path: time codes only in the file name, not in {p.parent}")
        self.folder = p.parent
        self.stem, self.suffix = (p.name[: -len(p.suffix)], p.suffix) if p.suffix else (p.name, "")
        parts = re.split(r"(%.)", self.stem)
        body = "".join(".+?" if x.startswith("%") else re.escape(x) for x in parts)
        self._regex = re.compile(rf"^{body}(?:-\d+)?{re.escape(self.suffix)}$")

    def next_path(self) -> Path:
        """This moment's name (time codes expanded); ``-1``, ``-2``, ... if it is taken."""
        stem = time.strftime(self.stem)
        path = self.folder / f"{stem}{self.suffix}"
        k = 1
        while path.exists():
            path = self.folder / f"{stem}-{k}{self.suffix}"
            k += 1
        return path

    def existing(self) -> list[Path]:
        """Segments of this pattern in its folder, oldest first."""
        try:
            found = [f for f in self.folder.iterdir() if self._regex.match(f.name) and f.is_file()]
        except OSError:
            return []
        return sorted(found, key=lambda f: (f.stat().st_mtime, f.name))

    def enforce(self, max_total_bytes: float, keep: Path | None) -> list[Path]:
        """Delete the oldest segments (never ``keep``) until the total fits; returns them."""
        if max_total_bytes <= 0:
            return []
        files = self.existing()
        sizes = {f: f.stat().st_size for f in files}
        total = sum(sizes.values())
        gone = []
        for f in files:
            if total <= max_total_bytes:
                break
            if keep is not None and f == keep:
                continue
            with contextlib.suppress(OSError):
                f.unlink()
                total -= sizes[f]
                gone.append(f)
        return gone


class McapSegment:
    """One open MCAP file: channels registered on first use."""

    def __init__(self, path: Path, compression: str, metadata: dict[str, str]) -> None:
        from mcap.writer import CompressionType, Writer

        kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}.get(
            compression, CompressionType.NONE
        )
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self.stream: BinaryIO = open(path, "xb")  # noqa: SIM115 - closed in close()
        self.writer = Writer(self.stream, chunk_size=256 * 1024, compression=kind)
        from omnid import __version__

        self.writer.start(profile="", library=f"omnid {__version__}")
        self.writer.add_metadata("omnid", metadata)
        self.channels: dict[str, int] = {}
        self.sequence = 0
        self.opened_s = time.monotonic()

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        ch = self.channels.get(topic)
        if ch is None:
            s = tp.schema_of(topic)
            sid = self.writer.register_schema(s.schema_name, s.schema_encoding, s.schema_data)
            ch = self.writer.register_channel(topic, s.message_encoding, sid)
            self.channels[topic] = ch
        self.sequence += 1
        self.writer.add_message(ch, log_time_ns, data, log_time_ns, self.sequence)

    @property
    def size_bytes(self) -> int:
        return self.stream.tell()

    def close(self) -> None:
        try:
            self.writer.finish()
        finally:
            self.stream.close()


class LiveView:
    """The Foxglove WebSocket server (``foxglove-sdk``) fed with the recorder's bytes."""

    def __init__(self, host: str, port: int) -> None:
        import foxglove

        self._foxglove = foxglove
        self.context = foxglove.Context()
        self.server = foxglove.start_server(
            name="omnid", host=host, port=port, context=self.context
        )
        self.channels: dict[str, Any] = {}
        self.port = int(getattr(self.server, "port", port))

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        ch = self.channels.get(topic)
        if ch is None:
            fg = self._foxglove
            s = tp.schema_of(topic)
            ch = fg.Channel(
                topic,
                schema=fg.Schema(
                    name=s.schema_name, encoding=s.schema_encoding, data=s.schema_data
                ),
                message_encoding=s.message_encoding,
                context=self.context,
            )
            self.channels[topic] = ch
        ch.log(data, log_time=log_time_ns)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.server.stop()


class Recorder:
    """See the module docstring. ``clock``: the caller's clock (monotonic, or the simulator's
    virtual time); ``clock_offset_ns`` maps it to MCAP log times (ns since the epoch)."""

    def __init__(
        self,
        settings: RecordSettings,
        metadata: dict[str, str],
        clock: Callable[[], float] = time.monotonic,
        clock_offset_ns: int | None = None,
        threaded: bool = True,
        write_file: bool = True,
        poll_s: float = 0.05,
        retry_s: float = 10.0,
    ) -> None:
        self.settings = settings
        self.metadata = {
            "format": tp.FORMAT,
            "format_version": str(tp.FORMAT_VERSION),
            **metadata,
        }
        self.clock = clock
        if clock_offset_ns is None:
            clock_offset_ns = time.time_ns() - round(clock() * 1e9)
        self.clock_offset_ns = int(clock_offset_ns)
        self.metadata["clock_offset_ns"] = str(self.clock_offset_ns)
        self.threaded = threaded
        self.write_file = write_file and settings.enabled
        self.poll_s = poll_s
        self.retry_s = retry_s
        self._queue: collections.deque[tuple[str, float, Any]] = collections.deque()
        self._max = settings.queue_messages
        self.dropped = 0
        self.written = 0
        self.bytes_written = 0
        self.failed: str | None = None
        self._failed_at = -math.inf
        self.busy_s = 0.0  # writer time spent encoding and writing
        self.slice_max_s = 0.0  # its longest stretch without a GIL hand-back
        self.slices_over_half_ms = 0
        self._files = SegmentFiles(settings.path) if self.write_file else None
        self.segment: McapSegment | None = None
        self.segments: list[Path] = []
        self.view: LiveView | None = None
        self._latched: dict[str, tuple[int, bytes]] = {}
        self._bad_kinds: set[str] = set()
        self._last_stats_s = -math.inf
        self._dropped_logged = 0
        self._drop_log_s = -math.inf
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._writer_lock = threading.Lock()
        self._last_capture_s = -math.inf
        self._last_map_s = -math.inf

    # -- control-loop side (cheap, never blocks) ---------------------------------------------
    def put(self, kind: str, t_s: float, payload: Any) -> bool:
        """Queue one record; False (and counted) when the queue is full."""
        if len(self._queue) >= self._max:
            self.dropped += 1
            return False
        self._queue.append((kind, t_s, payload))
        return True

    def wants_capture(self, t_s: float) -> bool:
        """Whether a capture taken at ``t_s`` is due (``capture_period_s`` rate limit)."""
        p = self.settings.capture_period_s
        if p <= 0 or t_s - self._last_capture_s < p:
            return False
        self._last_capture_s = t_s
        return True

    def wants_map(self, t_s: float) -> bool:
        p = self.settings.map_period_s
        if p <= 0 or t_s - self._last_map_s < p:
            return False
        self._last_map_s = t_s
        return True

    # -- life cycle ------------------------------------------------------------------------
    def start(self) -> None:
        """Open the first segment and the live view (failures logged, never raised), then
        start the writer thread."""
        require_recording_libraries()
        _warm_up()  # imports and first calls here, not on the writer thread mid-ride
        if self.write_file:
            self._open_segment()
        addr = self.settings.view_address
        if addr is not None:
            try:
                self.view = LiveView(*addr)
                log.info("live view: Foxglove WebSocket on ws://%s:%d", addr[0], self.view.port)
            except Exception as exc:
                log.error("live view on %s:%d not started: %s", addr[0], addr[1], exc)
        if self.threaded:
            self._thread = threading.Thread(target=self._run, name="omnid-recorder", daemon=True)
            self._thread.start()

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued, close the segment and the view."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            if self._thread.is_alive():
                log.warning("recorder: writer did not finish within %.0f s", timeout_s)
                return
        else:
            self.pump()
        with self._writer_lock:
            self._stats(force=True)
            if self.segment is not None:
                self._close_segment()
            if self.view is not None:
                self.view.close()
                self.view = None
        if self.dropped:
            log.warning(
                "recorder: %d records dropped in all (queue full or not writable)", self.dropped
            )

    def pump(self) -> None:
        """Write everything queued now (the simulator's synchronous mode)."""
        with self._writer_lock:
            self._drain()
            self._housekeeping()

    def _run(self) -> None:
        while True:
            stopping = self._stop.wait(self.poll_s)
            try:
                with self._writer_lock:
                    self._drain()
                    self._housekeeping()
            except Exception as exc:  # the writer thread must not die silently
                log.error("recorder: writer error %r; recording continues", exc)
            if stopping:
                return

    # -- writer side -----------------------------------------------------------------------
    def _drain(self) -> None:
        q = self._queue
        handlers = _HANDLERS
        n = 0
        clock = time.perf_counter
        t_slice = clock()
        while q:
            n += 1
            if self.threaded and n % SLICE_RECORDS == 0:
                # hand the GIL back between slices: a control cycle waking now waits for at
                # most one slice, not for the whole batch
                now = clock()
                self._note_slice(now - t_slice)
                time.sleep(SLICE_PAUSE_S)
                t_slice = clock()
            kind, t_s, payload = q.popleft()
            t_ns = round(t_s * 1e9) + self.clock_offset_ns
            if kind == "capture":  # PNG encoding releases the GIL: not a stretch that holds it
                t_cap = clock()
                self._note_slice(t_cap - t_slice)
            try:
                out = handlers[kind](self, t_ns, t_s, payload)
            except Exception as exc:
                if kind not in self._bad_kinds:
                    self._bad_kinds.add(kind)
                    log.error(
                        "recorder: cannot encode a %r record (%r); such records dropped", kind, exc
                    )
                self.dropped += 1
                continue
            if kind == "capture":
                for topic, data in out:
                    self._emit(topic, t_ns, data)
                t_slice = clock()
                self.busy_s += t_slice - t_cap
                continue
            for topic, data in out:
                self._emit(topic, t_ns, data)
        if n:
            self._note_slice(clock() - t_slice)

    def _note_slice(self, seconds: float) -> None:
        """Writer time between two GIL hand-backs (PNG encoding of captures, which releases
        the GIL itself, excluded; zstd of a finished chunk included): about the most a control
        cycle can wait for the writer."""
        self.busy_s += seconds
        self.slice_max_s = max(self.slice_max_s, seconds)
        if seconds > 0.0005:
            self.slices_over_half_ms += 1

    def _emit(self, topic: str, t_ns: int, data: bytes) -> None:
        if topic in tp.LATCHED:
            self._latched[topic] = (t_ns, data)
        if self.view is not None:
            try:
                self.view.write(topic, t_ns, data)
            except Exception as exc:
                log.error("live view stopped: %s", exc)
                self.view.close()
                self.view = None
        if not self.write_file:
            return
        seg = self.segment
        if seg is None:
            self.dropped += 1
            return
        try:
            seg.write(topic, t_ns, data)
        except Exception as exc:
            self._fail(exc)
            self.dropped += 1
            return
        self.written += 1
        self.bytes_written += len(data)

    def _housekeeping(self) -> None:
        now = time.monotonic()
        if self.dropped > self._dropped_logged and now - self._drop_log_s >= 10.0:
            log.warning(
                "recorder: %d records dropped so far (queue full or not writable)", self.dropped
            )
            self._dropped_logged, self._drop_log_s = self.dropped, now
        self._stats()
        if not self.write_file:
            return
        seg = self.segment
        if seg is None:
            if now - self._failed_at >= self.retry_s:
                self._open_segment()
            return
        s = self.settings
        try:
            too_big = s.max_file_mb > 0 and seg.size_bytes >= s.max_file_mb * MB
            too_old = s.max_file_s > 0 and now - seg.opened_s >= s.max_file_s
            if too_big or too_old:
                self._close_segment()
                self._open_segment()
            else:
                seg.stream.flush()
        except Exception as exc:
            self._fail(exc)

    def _stats(self, force: bool = False) -> None:
        t = self.clock()
        if not force and t - self._last_stats_s < 1.0:
            return
        self._last_stats_s = t
        doc = {
            "t_s": t,
            "queued": len(self._queue),
            "dropped": self.dropped,
            "written": self.written,
            "bytes": self.bytes_written,
            "segment": str(self.segment.path) if self.segment is not None else "",
            "failed": self.failed or "",
            "busy_s": self.busy_s,
            "slice_max_ms": 1e3 * self.slice_max_s,
            "slices_over_half_ms": self.slices_over_half_ms,
        }
        self._emit(tp.RECORDER, round(t * 1e9) + self.clock_offset_ns, tp.json_bytes(doc))

    def _open_segment(self) -> None:
        assert self._files is not None
        path = None
        try:
            path = self._files.next_path()
            meta = dict(self.metadata, segment=str(len(self.segments)))
            self.segment = McapSegment(path, self.settings.compression, meta)
            for topic, (t_ns, data) in self._latched.items():
                self.segment.write(topic, t_ns, data)
        except Exception as exc:
            self.segment = None
            self._fail(exc, path)
            return
        self.segments.append(path)
        if self.failed is not None:
            log.warning("recording resumed in %s", path)
            self.failed = None
        else:
            log.info("recording to %s", path)
        gone = self._files.enforce(self.settings.max_total_mb * MB, keep=path)
        for f in gone:
            log.info("recording budget: deleted the oldest segment %s", f)

    def _close_segment(self) -> None:
        seg, self.segment = self.segment, None
        if seg is None:
            return
        try:
            seg.close()
        except Exception as exc:
            self._fail(exc, seg.path)

    def _fail(self, exc: BaseException, path: Path | None = None) -> None:
        where = path or (self.segment.path if self.segment is not None else self.settings.path)
        first = self.failed is None
        self.failed = f"{where}: {exc}"
        self._failed_at = time.monotonic()
        seg, self.segment = self.segment, None
        if seg is not None:
            with contextlib.suppress(Exception):
                seg.stream.close()
        if first:
            log.error(
                "recording stopped (%s); the chair works on, records are dropped; retrying "
                "every %.0f s",
                self.failed,
                self.retry_s,
            )


# -- record kinds → topics (writer thread) ---------------------------------------------------

Out = list[tuple[str, bytes]]


def _cycle(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    """A control cycle: (seq, report, sources, flags, age, pose, rig)."""
    seq, report, sources, flags, age, pose, rig = p
    capturing, laser, link_ok, halt, camera_ok = flags
    d, dec, cmd = report.demand, report.decision, report.command
    demand = {
        "seq": seq,
        "t_s": t_s,
        "forward": d.forward,
        "turn": d.turn,
        "stop": d.stop,
        "source": d.source,
        "reason": d.reason,
        "sources": {
            name: None
            if s is None
            else {"forward": s.forward, "turn": s.turn, "stop": s.stop, "reason": s.reason}
            for name, s in sources.items()
        },
    }
    safety = {
        "seq": seq,
        "t_s": t_s,
        "v_mm_s": None if dec is None else dec.v_mm_s,
        "omega_rad_s": None if dec is None else dec.omega_rad_s,
        "scale": None if dec is None else dec.scale,
        "clearance_mm": None if dec is None else dec.clearance_mm,
        "reasons": [r.value for r in report.reasons],
        "perception_age_s": age,
        "capturing": capturing,
        "link_ok": link_ok,
        "camera_ok": camera_ok,
        "halt": halt,
    }
    command = {
        "seq": seq,
        "t_s": t_s,
        "left_duty": cmd.left_duty,
        "right_duty": cmd.right_duty,
        "laser_on": cmd.laser_on,
        "enable": cmd.enable,
        "laser_requested": laser,
    }
    x, y, th = pose
    off_mm, height_mm = rig
    tf = [
        tp.transform(t_ns, "odom", "base_link", x / 1000, y / 1000, 0.0, tp._quat_yaw(th)),
        tp.transform(
            t_ns, "base_link", "rig", off_mm / 1000, 0.0, height_mm / 1000, tp.rig_rotation()
        ),
    ]
    return [
        (tp.DEMAND, tp.json_bytes(demand)),
        (tp.SAFETY, tp.json_bytes(safety)),
        (tp.COMMAND, tp.json_bytes(command)),
        (tp.TF, tp.frame_transforms(tf)),
        (tp.POSE, tp.pose_in_frame(t_ns, "odom", x, y, th)),
    ]


def _tilt(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    seq, r = p
    doc = {"seq": seq, "t_s": r.timestamp_s, "roll_deg": r.roll_deg, "pitch_deg": r.pitch_deg}
    return [(tp.TILT, tp.json_bytes(doc))]


def _joystick(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    seq, r = p
    doc = {"seq": seq, "t_s": r.timestamp_s, "forward": r.forward, "turn": r.turn}
    return [(tp.JOYSTICK, tp.json_bytes(doc))]


def _key(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    seq, command = p
    return [(tp.KEY, tp.json_bytes({"seq": seq, "t_s": t_s, "command": command}))]


def _input_lost(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    seq, source = p
    return [(tp.INPUT_LOST, tp.json_bytes({"seq": seq, "t_s": t_s, "source": source}))]


def _status(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    seq, st = p
    doc = {
        "seq": seq,
        "t_s": st.timestamp_s,
        "unit_seq": int(getattr(st, "seq", 0)),
        "left_clocks": int(st.left_clocks),
        "right_clocks": int(st.right_clocks),
        "laser_on": bool(st.laser_on),
        "faults": int(st.faults),
        "left_applied_duty": float(getattr(st, "left_applied_duty", 0.0)),
        "right_applied_duty": float(getattr(st, "right_applied_duty", 0.0)),
    }
    return [(tp.STATUS, tp.json_bytes(doc))]


def _cloud(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    """A perception result as it enters the core: (seq, cloud, capture_time_s)."""
    seq, cloud, t_cap = p
    cls = np.asarray(cloud.classes)
    doc = {
        "seq": seq,
        "t_s": t_s,
        "capture_time_s": t_cap,
        "points": len(cloud),
        "floor": int((cls == 0).sum()),
        "obstacle": int((cls == 1).sum()),
        "dropoff": int((cls == 2).sum()),
        "floor_depth_mm": float(cloud.floor_depth_mm),
        "calibration_fit": float(cloud.calibration_fit),  # null: not measured
        "not_understood": int(cloud.not_understood),
    }
    cap_ns = round(t_cap * 1e9) + rec.clock_offset_ns
    return [
        (tp.PERCEPTION, tp.json_bytes(doc)),
        (tp.CLOUD, tp.point_cloud(cap_ns, np.asarray(cloud.xyz, dtype=np.float64), cls)),
    ]


def _capture(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    """A stereo capture (rate-limited by the caller with :meth:`Recorder.wants_capture`):
    four lossless PNGs, so ``omnid replay`` can run perception on exactly these pixels."""
    import cv2

    cap = p
    out = []
    for (what, cam), topic in tp.CAMERA_TOPICS.items():
        img = getattr(cap, f"{what}{cam}")
        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if ok:
            out.append((topic, tp.compressed_image(t_ns, f"camera{cam}", buf.tobytes())))
    return out


def _map(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    states, x_min, y_min, res = p
    return [(tp.MAP, tp.grid(t_ns, states, x_min, y_min, res))]


def _fault(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    name, event, detail = p
    doc = {"t_s": t_s, "name": name, "event": event, "detail": detail}
    return [(tp.FAULTS, tp.json_bytes(doc))]


def _log(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    level, name, message, file, line = p
    return [(tp.LOG, tp.log_message(t_ns, level, name, message, file, line))]


def _sim(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    """The simulator's truth: (pose, speeds, clearance, contacts, faults, start pose)."""
    (x, y, th), (vl, vr), clearance, contacts, faults, (sx, sy, sth) = p
    doc = {
        "t_s": t_s,
        "x_mm": x,
        "y_mm": y,
        "theta_rad": th,
        "left_speed_mm_s": vl,
        "right_speed_mm_s": vr,
        "clearance_mm": clearance,
        "contacts": contacts,
        "faults": ",".join(faults),
    }
    tf = [
        tp.transform(t_ns, "world", "sim_chair", x / 1000, y / 1000, 0.0, tp._quat_yaw(th)),
        tp.transform(t_ns, "world", "odom", sx / 1000, sy / 1000, 0.0, tp._quat_yaw(sth)),
    ]
    return [
        (tp.SIM_TRUTH, tp.json_bytes(doc)),
        (tp.SIM_TF, tp.frame_transforms(tf)),
        (tp.SIM_POSE, tp.pose_in_frame(t_ns, "world", x, y, th)),
    ]


def _world(rec: Recorder, t_ns: int, t_s: float, p: Any) -> Out:
    boxes, drops = p
    return [(tp.SIM_WORLD, tp.world_scene(t_ns, boxes, drops))]


_HANDLERS: dict[str, Callable[[Recorder, int, float, Any], Out]] = {
    "cycle": _cycle,
    "tilt": _tilt,
    "joystick": _joystick,
    "key": _key,
    "input_lost": _input_lost,
    "status": _status,
    "cloud": _cloud,
    "capture": _capture,
    "map": _map,
    "fault": _fault,
    "log": _log,
    "sim": _sim,
    "world": _world,
}


def _warm_up() -> None:
    """Import and run every encoder once (the first call of foxglove's message types and of
    OpenCV's PNG encoder costs tens of ms with the GIL held)."""
    import cv2
    import mcap.writer  # noqa: F401

    tp.compressed_image(0, "camera1", cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
    tp.point_cloud(0, np.zeros((1, 3)), np.zeros(1, np.uint8))
    tp.grid(0, np.zeros((2, 2), np.int8), 0.0, 0.0, 50.0)
    tp.frame_transforms([tp.transform(0, "a", "b", 0.0, 0.0, 0.0, tp.rig_rotation())])
    tp.pose_in_frame(0, "odom", 0.0, 0.0, 0.0)
    tp.log_message(0, logging.INFO, "omnid", "", "", 0)
    tp.world_scene(0, [(0.0, 1.0, 0.0, 1.0, 1.0)], [])
    for topic in (*tp.JSON_SCHEMAS, *tp.PROTO_TOPICS):
        tp.schema_of(topic)


class RecorderLogHandler(logging.Handler):
    """Hands omnid's log records to the recorder (``/log``); never raises, never blocks."""

    def __init__(self, recorder: Recorder, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.recorder = recorder

    def emit(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(Exception):  # logging must never fail the caller
            self.recorder.put(
                "log",
                self.recorder.clock(),
                (record.levelno, record.name, record.getMessage(), record.pathname, record.lineno),
            )
