"""Reading a recording back: every message in order, with one-line errors for bad input.

A file that is not MCAP, an MCAP file that is not an omnid recording, a recording of another
format version, or a file cut short (the chair lost power) each give one line naming the file
— :class:`~omnid.errors.InputError`, which the command line prints without a traceback. A
truncated file still yields every complete chunk before the cut; :attr:`Recording.truncated`
says so and where.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omnid.errors import InputError
from omnid.record import topics as tp

log = logging.getLogger(__name__)


@dataclass
class Message:
    """One recorded message: ``doc`` is the decoded JSON (omnid topics) or the decoded
    protobuf object (Foxglove schemas); ``log_time_ns`` as recorded."""

    topic: str
    log_time_ns: int
    doc: Any


@dataclass
class Recording:
    """The messages of one or more segments of a recording, in file order."""

    paths: list[Path]
    metadata: dict[str, str]
    messages: list[Message] = field(default_factory=list)
    truncated: str = ""  # why reading stopped early ("" = read to the end)

    @property
    def source(self) -> str:
        return self.metadata.get("source", "?")

    @property
    def config_data(self) -> Any:
        return json.loads(self.metadata.get("config") or "{}")

    @property
    def rig(self) -> dict[str, Any]:
        return dict(json.loads(self.metadata.get("rig") or "{}"))

    @property
    def clock_offset_ns(self) -> int:
        return int(self.metadata.get("clock_offset_ns", "0"))

    def topic(self, name: str) -> list[Message]:
        return [m for m in self.messages if m.topic == name]

    def topics(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for m in self.messages:
            out[m.topic] = out.get(m.topic, 0) + 1
        return out

    def t_s(self, m: Message) -> float:
        """A message's time on the recording's own clock (the daemon's monotonic clock, or
        the simulator's virtual time), s."""
        return (m.log_time_ns - self.clock_offset_ns) / 1e9


def read_recording(paths: Iterable[str | Path], topics: set[str] | None = None) -> Recording:
    """Read the segments ``paths`` (in the order given) — every message, or only ``topics``."""
    files = [Path(p) for p in paths]
    if not files:
        raise InputError("no recording given")
    rec: Recording | None = None
    for path in files:
        seg = _read_one(path, topics)
        if rec is None:
            rec = seg
        else:
            ours, theirs = rec.metadata, seg.metadata
            for key in ("omnid_version", "source", "config"):
                if ours.get(key) != theirs.get(key):
                    raise InputError(f"{path}: not a segment of the same recording as {files[0]}")
            rec.paths.append(path)
            rec.messages.extend(seg.messages)
            rec.truncated = rec.truncated or seg.truncated
    assert rec is not None
    return rec


def _read_one(path: Path, topics: set[str] | None) -> Recording:
    try:
        from mcap.exceptions import McapError
        from mcap.records import Channel, Metadata, Schema
        from mcap.records import Message as McapMessage
        from mcap.stream_reader import StreamReader
        from mcap_protobuf.decoder import DecoderFactory
    except ImportError as exc:
        raise InputError(
            f"reading recordings needs the 'record' extra ({exc.name} is not installed): "
            "pip install 'omnid[record]'"
        ) from None
    try:
        f = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    with f:
        head = f.read(8)
        if head != b"\x89MCAP0\r\n":
            raise InputError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
        f.seek(0)
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        decoders: dict[int, Any] = {}
        factory = DecoderFactory()
        meta: dict[str, str] | None = None
        messages: list[Message] = []
        truncated = ""
        try:
            for r in StreamReader(f, skip_magic=False).records:
                if isinstance(r, Schema):
                    schemas[r.id] = r
                elif isinstance(r, Channel):
                    channels[r.id] = r
                elif isinstance(r, Metadata) and r.name == "omnid":
                    meta = meta or dict(r.metadata)
                elif isinstance(r, McapMessage):
                    ch = channels.get(r.channel_id)
                    if ch is None or (topics is not None and ch.topic not in topics):
                        continue
                    messages.append(
                        Message(ch.topic, r.log_time, _decode(r, ch, schemas, decoders, factory))
                    )
        except (McapError, EOFError, OSError, ValueError, KeyError, IndexError) as exc:
            truncated = f"{type(exc).__name__} {exc}".strip()
        except Exception as exc:  # a corrupted chunk can fail inside a decompressor
            truncated = f"{type(exc).__name__} {exc}".strip()
    if meta is None:
        names = sorted({c.topic for c in channels.values()})[:5]
        what = f"topics {', '.join(names)}" if names else "no omnid metadata"
        if truncated and not channels:
            raise InputError(f"{path}: a damaged or truncated MCAP file ({truncated})")
        raise InputError(f"{path}: an MCAP file, but not an omnid recording ({what})")
    if meta.get("format") != tp.FORMAT:
        raise InputError(f"{path}: not an omnid recording (format {meta.get('format')!r})")
    if meta.get("format_version") != str(tp.FORMAT_VERSION):
        raise InputError(
            f"{path}: recording format version {meta.get('format_version')}, made by omnid "
            f"{meta.get('omnid_version', '?')}; this omnid reads version {tp.FORMAT_VERSION}"
        )
    if truncated:
        t = messages[-1].log_time_ns if messages else None
        where = f"after {len(messages)} messages" + (
            f" (t = {(t - int(meta.get('clock_offset_ns', '0'))) / 1e9:.2f} s)" if t else ""
        )
        truncated = f"{path}: cut short {where}"
    return Recording([path], meta, messages, truncated)


def _decode(
    r: Any, ch: Any, schemas: dict[int, Any], decoders: dict[int, Any], factory: Any
) -> Any:
    if ch.message_encoding == "json":
        return json.loads(r.data)
    dec = decoders.get(ch.id)
    if dec is None:
        dec = factory.decoder_for(ch.message_encoding, schemas.get(ch.schema_id))
        if dec is None:
            raise ValueError(f"no decoder for {ch.topic} ({ch.message_encoding})")
        decoders[ch.id] = dec
    return dec(r.data)
