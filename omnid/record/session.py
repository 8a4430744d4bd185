"""Setting a recording up for ``omnid run`` and for the simulator (metadata, the tap)."""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path
from typing import Any

from omnid.record.recorder import Recorder, RecorderLogHandler, require_recording_libraries
from omnid.record.settings import RecordSettings
from omnid.record.tap import RecordingCore

log = logging.getLogger(__name__)

DEFAULT_VIEW = "127.0.0.1:8765"


def config_json(config: Any) -> str:
    """The configuration as JSON (``omnid replay`` rebuilds it with ``from_mapping``)."""
    return json.dumps(dataclasses.asdict(config), default=str)


def rig_metadata(calibration: Any) -> dict[str, Any]:
    """What identifies the rig a recording was made with (``omnid replay`` checks it)."""
    if calibration is None:
        return {}
    rig = calibration.rig
    return {
        "image_shape": list(rig.cam1.image_shape),
        "floor_depth_mm": float(calibration.floor_depth_mm),
        "baseline_mm": float(rig.baseline_mm),
    }


def metadata(config: Any, source: str, calibration: Any, calibration_text: str) -> dict[str, str]:
    from omnid import __version__

    return {
        "omnid_version": __version__,
        "source": source,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "config": config_json(config),
        "calibration": calibration_text,
        "rig": json.dumps(rig_metadata(calibration)),
    }


def calibration_yaml(calibration: Any) -> str:
    if calibration is None:
        return ""
    import yaml

    return str(yaml.safe_dump(calibration.to_mapping(), sort_keys=False))


def with_overrides(settings: RecordSettings, path: str | None, view: str | None) -> RecordSettings:
    """The ``record`` section with the command line's ``--record`` / ``--view`` applied."""
    changes: dict[str, Any] = {}
    if path:
        changes["path"] = path
    if view:
        changes["view"] = view
    return dataclasses.replace(settings, **changes) if changes else settings


class DaemonRecording:
    """The recorder of ``omnid run``: a writer thread, the log handler, the tapped core."""

    def __init__(self, config: Any, calibration: Any) -> None:
        require_recording_libraries()
        self.settings = config.record
        text = ""
        path = Path(config.perception.calibration_path)
        if calibration is not None and path.is_file():
            text = path.read_text(encoding="utf-8", errors="replace")
        self.recorder = Recorder(
            self.settings, metadata(config, "daemon", calibration, text), threaded=True
        )
        self.height_mm = float(calibration.floor_depth_mm) if calibration is not None else 1100.0
        self.handler = RecorderLogHandler(self.recorder)
        self.tap: Any = None

    def wrap(self, core: Any) -> RecordingCore:
        """``core`` recorded (at start, and again for the new core of a reload)."""
        self.tap = RecordingCore(core, self.recorder, rig_height_mm=self.height_mm)
        return self.tap

    def on_capture(self, capture: Any) -> None:
        self.tap.on_capture(capture)

    def on_fault(self, name: str, detail: str, now_s: float | None = None) -> None:
        self.tap.on_fault(name, detail, now_s)

    def start(self) -> None:
        self.recorder.start()
        logging.getLogger("omnid").addHandler(self.handler)

    def close(self) -> None:
        logging.getLogger("omnid").removeHandler(self.handler)
        self.recorder.close()


class SimRecording:
    """A recording of a simulated run on its virtual clock (no thread, nothing dropped), or
    the live view of it paced to real time."""

    def __init__(
        self,
        controller: Any,
        record_path: str | None,
        view: str | None,
        pace: bool = False,
        capture_period_s: float = 2.0,
    ) -> None:
        require_recording_libraries()
        if not hasattr(controller, "last_report"):
            from omnid.errors import InputError

            raise InputError("--record/--view record the daemon core's decisions: not with --drive")
        settings = RecordSettings(
            path=record_path or "",
            view=view or "",
            capture_period_s=capture_period_s,
            max_file_mb=0.0,
            max_file_s=0.0,
            max_total_mb=0.0,
            queue_messages=1_000_000,
        )
        self.sim: Any = None
        self.pace = pace
        self._wall0 = time.monotonic()
        self.recorder = Recorder(
            settings,
            {},
            clock=lambda: self.sim.now_s if self.sim is not None else 0.0,
            clock_offset_ns=time.time_ns(),
            threaded=False,
        )
        self.core = RecordingCore(controller, self.recorder)
        self.handler = RecorderLogHandler(self.recorder)

    def attach(self, sim: Any) -> None:
        """Metadata from the built simulator (its calibration), start, and the truth topics."""
        self.sim = sim
        cal = getattr(sim, "calibration", None)
        object.__setattr__(self.core, "_rig", (0.0, float(sim.mount.height_mm)))
        self.recorder.metadata.update(
            metadata(self.core.config, "simulator", cal, calibration_yaml(cal))
        )
        self.recorder.metadata["sim"] = json.dumps(
            {
                "course": sim.course.name,
                "perception": sim.settings.perception,
                "seed": sim.settings.seed,
                "rig_x_offset_mm": float(sim.mount.x_offset_mm),
            }
        )
        self.recorder.start()
        logging.getLogger("omnid").addHandler(self.handler)
        self.core.attach_simulator(sim)
        if self.pace:
            inner = self.core.step
            wall0 = time.monotonic()

            def paced(now_s: float) -> Any:
                ahead = now_s - (time.monotonic() - wall0)
                if ahead > 0:
                    time.sleep(ahead)
                return inner(now_s)

            object.__setattr__(self.core, "step", paced)

    def close(self) -> list[Path]:
        logging.getLogger("omnid").removeHandler(self.handler)
        self.recorder.close()
        return self.recorder.segments
