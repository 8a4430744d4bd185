"""The recorder: never blocks, drops and counts when full, rotates and budgets its segments,
never overwrites, survives a failing disk (logged once), and does not change the ride."""

from __future__ import annotations

import argparse
import logging
import resource
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from omnid.errors import ConfigError
from omnid.record.reader import read_recording
from omnid.record.recorder import Recorder, SegmentFiles
from omnid.record.settings import RecordSettings

MB = 1024 * 1024


def grid_records(rec: Recorder, n: int, t0: float = 0.0) -> None:
    rng = np.random.default_rng(0)
    for i in range(n):  # incompressible maps: the file grows by about 40 kB per record
        states = rng.integers(0, 3, (200, 200)).astype(np.int8)
        rec.put("map", t0 + 0.01 * i, (states, -2000.0, -3000.0, 50.0))


def test_put_never_waits_and_counts_what_it_drops(tmp_path: Path) -> None:
    rec = Recorder(
        RecordSettings(path=str(tmp_path / "r.mcap"), queue_messages=10), {}, threaded=False
    )
    t0 = time.perf_counter()
    accepted = [rec.put("fault", 0.0, ("x", "event", str(i))) for i in range(1000)]
    took = time.perf_counter() - t0
    assert accepted.count(True) == 10 and rec.dropped == 990
    assert took < 0.5  # 1000 calls; a blocking put would hang here (no writer runs)
    rec.start()
    rec.close()
    faults = read_recording([tmp_path / "r.mcap"]).topic("/faults")
    assert [m.doc["detail"] for m in faults] == [str(i) for i in range(10)]
    stats = read_recording([tmp_path / "r.mcap"]).topic("/recorder")
    assert stats[-1].doc["dropped"] == 990


def test_segments_rotate_by_size_and_the_oldest_go_first(tmp_path: Path) -> None:
    settings = RecordSettings(
        path=str(tmp_path / "ride.mcap"), max_file_mb=0.3, max_total_mb=1.0, max_file_s=0.0
    )
    rec = Recorder(settings, {"source": "test"}, threaded=False)
    rec.start()
    for k in range(12):
        grid_records(rec, 10, t0=k)
        rec.pump()
    rec.close()
    made = rec.segments
    assert len(made) >= 4 and made[0].name == "ride.mcap" and made[1].name == "ride-1.mcap"
    left = SegmentFiles(settings.path).existing()
    assert left[-1] == made[-1] and made[0] not in left  # oldest deleted, newest kept
    assert sum(f.stat().st_size for f in left) <= 1.0 * MB + 0.45 * MB  # budget + open segment
    for f in left:  # every segment stands alone: metadata and readable maps
        r = read_recording([f])
        assert r.metadata["source"] == "test" and not r.truncated
        assert r.topic("/map") or f == left[-1]  # the last may hold only the closing stats


def test_segments_rotate_by_age(tmp_path: Path) -> None:
    settings = RecordSettings(path=str(tmp_path / "r-%H%M%S.mcap"), max_file_s=0.2)
    rec = Recorder(settings, {}, threaded=False)
    rec.start()
    for k in range(3):
        grid_records(rec, 2, t0=k)
        rec.pump()
        time.sleep(0.25)
    rec.pump()
    rec.close()
    assert len(rec.segments) >= 3 and all(read_recording([p]).metadata for p in rec.segments)


def test_an_existing_file_is_never_overwritten(tmp_path: Path) -> None:
    old = tmp_path / "ride.mcap"
    old.write_bytes(b"last ride")
    rec = Recorder(RecordSettings(path=str(old)), {}, threaded=False)
    rec.start()
    rec.close()
    assert old.read_bytes() == b"last ride" and rec.segments == [tmp_path / "ride-1.mcap"]
    pattern = SegmentFiles(str(tmp_path / "ride-%Y%m%d.mcap"))
    assert pattern.next_path().name == time.strftime("ride-%Y%m%d.mcap")


def test_a_full_disk_is_logged_once_and_recording_resumes(tmp_path: Path, caplog) -> None:
    caplog.set_level(logging.WARNING, "omnid.record")
    rec = Recorder(
        RecordSettings(path=str(tmp_path / "r.mcap"), max_file_mb=0.0, max_file_s=0.0),
        {},
        threaded=False,
        retry_s=0.0,
    )
    rec.start()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a signal
    resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, hard))
    try:
        for k in range(10):
            grid_records(rec, 5, t0=k)
            rec.pump()  # never raises
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)
    stops = [r for r in caplog.records if "recording stopped" in r.getMessage()]
    assert len(stops) == 1 and rec.dropped > 0
    grid_records(rec, 3, t0=20)
    rec.pump()
    rec.close()
    assert rec.failed is None and len(rec.segments) >= 2  # a new segment after the failure
    assert read_recording([rec.segments[-1]]).topic("/map")


def test_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="max_total_mb"):
        RecordSettings(path="x.mcap", max_file_mb=100, max_total_mb=150)
    with pytest.raises(ConfigError, match="view"):
        RecordSettings(view="8765")
    with pytest.raises(ConfigError, match="time codes"):
        SegmentFiles("/var/%Y/ride.mcap")


def sim_args(tmp_path: Path, record: str | None) -> argparse.Namespace:
    return argparse.Namespace(
        course="builtin",
        duration_s=6.0,
        perception="truth",
        seed=0,
        out=str(tmp_path / "out"),
        quiet=True,
        record=record,
        view=None,
    )


def test_recording_does_not_change_the_ride_even_when_it_fails(tmp_path: Path, caplog) -> None:
    from omnid.sim import scenario
    from omnid.sim.simulator import Simulator

    runs = {}
    original = Simulator.run

    def keep(self, duration_s):  # type: ignore[no-untyped-def]
        result = original(self, duration_s)
        runs[len(runs)] = result
        return result

    Simulator.run = keep  # type: ignore[method-assign]
    try:
        for record in (None, str(tmp_path / "r.mcap"), "/proc/no/such/folder/r.mcap"):
            assert scenario.run_and_report(sim_args(tmp_path, record), None, "t") == 0
    finally:
        Simulator.run = original  # type: ignore[method-assign]
    plain, recorded, failed = runs[0], runs[1], runs[2]
    assert np.array_equal(plain.commands, recorded.commands)
    assert np.array_equal(plain.commands, failed.commands)
    assert plain.distance_mm > 100.0
    assert sum("recording stopped" in r.getMessage() for r in caplog.records) == 1


def test_a_recorder_that_raises_costs_the_recording_not_the_input(tmp_path: Path, caplog) -> None:
    """A bug in the recorder (its ``put`` raising) after the core took an input used to raise
    into the caller: the tilt link's callback, the perceiver (every cloud lost with its
    capture). The input reaches the core; the recording says once that it failed."""
    from omnid.daemon.config import OmnidConfig
    from omnid.daemon.core import ControlCore
    from omnid.devices.tilt import TiltReading
    from omnid.record.tap import RecordingCore

    class BrokenRecorder(Recorder):
        def put(self, topic, t_s, payload):  # type: ignore[no-untyped-def]
            raise RuntimeError(f"a bug recording {topic}")

        def wants_capture(self, t_s):  # type: ignore[no-untyped-def]
            raise RuntimeError("a bug in the capture rate limit")

    rec = BrokenRecorder(RecordSettings(path=str(tmp_path / "r.mcap")), {}, threaded=False)
    core = ControlCore(OmnidConfig())
    tap = RecordingCore(core, rec)
    tap.on_tilt(TiltReading(1.0, -2.0, 0.5))
    tap.on_key("forward", 0.5)
    tap.on_input_lost("joystick", 0.5)
    tap.on_fault("camera", "lost", 0.5)
    tap.on_capture(argparse.Namespace(timestamp_s=0.5))
    tap.step(0.52)
    assert core.mux.tilt.last_timestamp_s == 0.5  # the reading reached the core
    assert core.mux.input_time_s("keyboard") == 0.5
    assert sum("recording failed" in r.getMessage() for r in caplog.records) == 1
