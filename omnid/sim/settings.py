"""``SimSettings``: the rates and models of one simulated run (s, mm)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

from omnid.config import require
from omnid.sim.camera import CameraModel

PerceptionMode = Literal["truth", "pipeline", "off"]


@dataclass(frozen=True)
class SimSettings:
    """Rates and models of a simulated run (s, mm).

    ``perception``: ``truth`` (the cast laser dots with their true classes and Gaussian noise,
    fast), ``pipeline`` (rendered frames through ``omnid.core.pipeline.perceive`` with a
    calibration made from a rendered floor capture) or ``off`` (empty clouds). The capture
    cycle itself is always the daemon's (:mod:`omnid.daemon.capture`); the settings here model
    the hardware it talks to (frame timing, camera timeout) and, when None, take the cycle's
    own settings from the controller's configuration.
    """

    physics_dt_s: float = 0.01
    control_period_s: float | None = None  # None: the controller's control.rate_hz (else 0.05)
    tilt_period_s: float = 0.01
    perception_period_s: float | None = None  # None: the controller's perception.period_s (0.2)
    perception_latency_s: float = 0.1  # at least this long from capture to result
    # the daemon's (one) perception worker is busy at least this long per job: a slower
    # computer than this one; newer jobs supersede a waiting one (0: as measured)
    worker_period_s: float = 0.0
    # perceive's computing time charged as virtual time per cloud: None, as measured on the
    # wall clock (a slow or loaded computer reacts late, as the chair would); a number, that
    # long on any computer — the run is then the same however loaded the machine is (tests)
    perceive_time_s: float | None = None
    perception: PerceptionMode = "truth"
    control_unit: Literal["emulator", "direct"] = "emulator"
    truth_noise_mm: float = 3.0  # Gaussian noise on truth-mode points (per axis)
    watchdog_s: float = 0.25  # the control unit stops the motors after this silence
    stop_on_contact: bool = True  # end the run at the first fall (and collision, with "pass")
    # "block": a box stops the chair (wheels stall, the run goes on: omnid.sim.chair);
    # "pass": the chair drives through boxes and a collision is only recorded
    contact: Literal["block", "pass"] = "block"
    record_period_s: float = 0.05
    seed: int = 0
    rig: Literal["misaligned", "nominal"] = "misaligned"  # the cameras as installed
    tilt_link: Literal["emulator", "direct"] = "emulator"  # head script through the GS311 codec
    tilt_noise_deg: float = 0.0  # Gaussian noise of the emulated sensor (head jitter)
    # the cameras' timing and scene; None: the controller's camera.fps, exposures 80 % of its
    # camera.exposure_s (the longest the capture cycle plans for)
    camera: CameraModel | None = None
    # the control unit's laser switch: command → light, s, plus a uniform 0 … jitter per
    # switch: 8–12 ms, within perception.laser_switch_latency_s (18 ms with the command path),
    # so the stream capture at 30 frames/s switches between two exposures
    laser_delay_s: float = 0.008
    laser_jitter_s: float = 0.004
    laser_timeout_s: float | None = None  # None: the controller's perception.laser_timeout_s
    frame_timeout_s: float = 1.0  # without a controller config: the cycle's frame timeout
    record_seen: bool = True  # keep every non-floor point perception reported (off for soaks)
    story_rest_s: float = 1.0  # a reactive rider's run ends this long after its story ended

    def __post_init__(self) -> None:
        for name in (
            "physics_dt_s",
            "control_period_s",
            "tilt_period_s",
            "perception_period_s",
            "watchdog_s",
            "record_period_s",
            "laser_timeout_s",
        ):
            v = getattr(self, name)
            require(v is None or v > 0, name, "must be positive")
        require(self.perception_latency_s >= 0, "perception_latency_s", "must be ≥ 0")
        require(self.worker_period_s >= 0, "worker_period_s", "must be ≥ 0")
        require(
            self.perceive_time_s is None or self.perceive_time_s >= 0,
            "perceive_time_s",
            "must be ≥ 0 (or None: as measured)",
        )
        require(self.truth_noise_mm >= 0, "truth_noise_mm", "must be ≥ 0")
        require(self.tilt_noise_deg >= 0, "tilt_noise_deg", "must be ≥ 0")
        require(self.story_rest_s >= 0, "story_rest_s", "must be ≥ 0")
        require(self.frame_timeout_s > 0, "frame_timeout_s", "must be positive")
        require(self.laser_delay_s >= 0, "laser_delay_s", "must be ≥ 0")
        require(self.laser_jitter_s >= 0, "laser_jitter_s", "must be ≥ 0")

    def for_controller(self, controller: Any) -> SimSettings:
        """These settings with unset values taken from the controller's configuration (the
        daemon core's ``control.rate_hz``, ``perception.period_s`` and
        ``perception.laser_timeout_s``) or the defaults."""
        cfg = getattr(controller, "config", None)
        control = self.control_period_s
        if control is None:
            control = float(cfg.control.period_s) if cfg is not None else 0.05
        perception = self.perception_period_s
        if perception is None:
            perception = float(cfg.perception.period_s) if cfg is not None else 0.2
        laser = self.laser_timeout_s
        if laser is None:
            laser = float(cfg.perception.laser_timeout_s) if cfg is not None else 0.5
        camera = self.camera
        if camera is None:
            camera = (
                CameraModel(fps=float(cfg.camera.fps), exposure_s=0.8 * cfg.camera.exposure_s)
                if cfg is not None
                else CameraModel()
            )
        return dataclasses.replace(
            self,
            control_period_s=control,
            perception_period_s=perception,
            laser_timeout_s=laser,
            camera=camera,
        )

    def ticks(self, period_s: float | None) -> int:
        """A period as a whole number of physics ticks (at least 1)."""
        require(period_s is not None, "period", "must be resolved (for_controller)")
        assert period_s is not None
        return max(1, round(period_s / self.physics_dt_s))
