"""The live view: the recorder's topics over the Foxglove WebSocket protocol, read by a plain
RFC 6455 client on the loopback (what Foxglove's "open connection" does)."""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
from collections.abc import Iterator

from omnid.record.recorder import Recorder
from omnid.record.settings import RecordSettings


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Client:
    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                "GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                "Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1\r\n\r\n"
            ).encode()
        )
        buf = b""
        while b"\r\n\r\n" not in buf:
            buf += self.sock.recv(4096)
        head, self.buf = buf.split(b"\r\n\r\n", 1)
        assert head.startswith(b"HTTP/1.1 101"), head
        assert b"sec-websocket-protocol: foxglove" in head.lower()

    def _need(self, n: int) -> None:
        while len(self.buf) < n:
            self.buf += self.sock.recv(65536)

    def frames(self) -> Iterator[tuple[int, bytes]]:
        while True:
            self._need(2)
            op, n, i = self.buf[0] & 0x0F, self.buf[1] & 0x7F, 2
            if n == 126:
                self._need(4)
                n, i = struct.unpack(">H", self.buf[2:4])[0], 4
            elif n == 127:
                self._need(10)
                n, i = struct.unpack(">Q", self.buf[2:10])[0], 10
            self._need(i + n)
            data, self.buf = self.buf[i : i + n], self.buf[i + n :]
            yield op, data

    def send_text(self, doc: dict) -> None:
        payload = json.dumps(doc).encode()
        mask = os.urandom(4)
        head = (
            bytes([0x81, 0x80 | len(payload)])
            if len(payload) < 126
            else bytes([0x81, 0x80 | 126]) + struct.pack(">H", len(payload))
        )
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))


def test_the_view_advertises_and_streams_the_topics() -> None:
    port = free_port()
    rec = Recorder(RecordSettings(view=f"127.0.0.1:{port}"), {}, threaded=True, poll_s=0.01)
    rec.start()
    try:
        rec.put("fault", time.monotonic(), ("control_unit_link", "event", "lost"))
        time.sleep(0.2)
        client = Client(port)
        frames = client.frames()
        info = json.loads(next(frames)[1])
        assert info["op"] == "serverInfo" and info["name"] == "omnid"
        channels: dict[str, dict] = {}
        while "/faults" not in channels:
            op, data = next(frames)
            doc = json.loads(data)
            if doc["op"] == "advertise":
                channels.update({c["topic"]: c for c in doc["channels"]})
        faults = channels["/faults"]
        assert faults["schemaName"] == "omnid.Fault" and faults["encoding"] == "json"
        assert "/recorder" in channels  # the recorder's own stats, once a second
        client.send_text(
            {"op": "subscribe", "subscriptions": [{"id": 7, "channelId": faults["id"]}]}
        )
        time.sleep(0.2)
        rec.put("fault", time.monotonic(), ("control_unit_link", "event", "back"))
        while True:
            op, data = next(frames)
            if op == 2 and data[0] == 0x01:  # binary messageData: op, subscription, time
                sub, _t = struct.unpack("<IQ", data[1:13])
                assert sub == 7
                assert json.loads(data[13:])["detail"] == "back"
                break
    finally:
        rec.close()


def test_the_layout_names_only_recorded_topics() -> None:
    import re
    from pathlib import Path

    from omnid.record import topics as tp

    layout = Path(__file__).resolve().parents[2] / "docs" / "foxglove" / "omnid-layout.json"
    doc = json.loads(layout.read_text())
    known = set(tp.JSON_SCHEMAS) | set(tp.PROTO_TOPICS)
    named = set(re.findall(r'"(/[a-z0-9_/]+)', json.dumps(doc)))
    assert named and named <= known, named - known
    for path in re.findall(r'"(/[a-z0-9_/]+\.[a-z_]+)"', json.dumps(doc)):
        topic, field = path.split(".")
        if topic in tp.JSON_SCHEMAS:  # plotted fields are in the topic's schema
            assert field in tp.JSON_SCHEMAS[topic][1]["properties"], path
