"""``RecordSettings``: the ``record`` section of ``etc/omnid.yaml`` (no heavy imports here)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from omnid.config import Settings, require, setting


@dataclass(frozen=True)
class RecordSettings(Settings):
    """Where and how much the daemon records (MCAP, docs/recording.md), and the live view.

    path              first segment's file; ``strftime`` codes (``%Y%m%d-%H%M%S``) are expanded
                      at each segment's start, so restarts never overwrite a ride; "" = off
    max_file_mb       a new segment starts past this size (0: no size limit)
    max_file_s        ... or past this age (0: no age limit)
    max_total_mb      the oldest segments of this path are deleted beyond this total (0: keep)
    capture_period_s  at most one camera capture (4 lossless PNGs) this often (0: none)
    map_period_s      the free-space map at most this often (0: never)
    queue_messages    the control loop hands records over through a queue this long; when the
                      writer falls behind, new records are dropped and counted, never waited for
    compression       MCAP chunk compression
    view              ``HOST:PORT`` of the live Foxglove WebSocket view ("" = off)
    """

    path: str = ""
    max_file_mb: float = setting(256.0, 0.0, 1e6)
    max_file_s: float = setting(600.0, 0.0, 1e6)
    max_total_mb: float = setting(2048.0, 0.0, 1e7)
    capture_period_s: float = setting(10.0, 0.0, 3600.0)
    map_period_s: float = setting(1.0, 0.0, 3600.0)
    queue_messages: int = setting(4000, 10, 1_000_000)
    compression: Literal["zstd", "lz4", "none"] = "zstd"
    view: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.max_total_mb == 0
            or self.max_file_mb == 0
            or self.max_total_mb >= 2 * self.max_file_mb,
            "max_total_mb",
            "must be at least twice max_file_mb (the open segment and one closed), or 0",
        )
        if self.view:
            host, _, port = self.view.rpartition(":")
            require(
                bool(host) and port.isdigit() and 0 < int(port) < 65536,
                "view",
                f"expected HOST:PORT (e.g. 127.0.0.1:8765), got {self.view!r}",
            )

    @property
    def enabled(self) -> bool:
        return bool(self.path)

    @property
    def view_address(self) -> tuple[str, int] | None:
        if not self.view:
            return None
        host, _, port = self.view.rpartition(":")
        return host, int(port)
