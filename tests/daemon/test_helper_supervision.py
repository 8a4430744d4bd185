"""The daemon's helper tasks (camera reader, perceiver) under :func:`run_supervised`: a helper
that raises or returns while the daemon runs is reported and started again, with a backoff;
a stop ends it; cancelling the supervisor cancels the helper."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import time

from omnid.daemon.run import run_supervised


def test_a_helper_that_raises_is_reported_and_restarted_until_the_stop():
    failures: list[tuple[str, str]] = []
    runs: list[float] = []
    stop = asyncio.Event()

    async def helper() -> None:
        runs.append(time.monotonic())
        if len(runs) <= 3:
            raise ValueError(f"bug {len(runs)}")
        await stop.wait()  # the fourth run lives until the stop

    async def go() -> None:
        task = asyncio.create_task(
            run_supervised(
                "perceiver", helper, stop.is_set, lambda n, e: failures.append((n, str(e))),
                backoff_s=0.02, max_backoff_s=0.05,
            )
        )  # fmt: skip
        for _ in range(200):
            if len(runs) == 4:
                break
            await asyncio.sleep(0.01)
        stop.set()
        await asyncio.wait_for(task, 1.0)

    asyncio.run(go())
    assert failures == [("perceiver", "bug 1"), ("perceiver", "bug 2"), ("perceiver", "bug 3")]
    assert len(runs) == 4
    gaps = [b - a for a, b in itertools.pairwise(runs)]
    assert gaps[0] >= 0.02 and gaps[1] >= 0.04 and gaps[2] >= 0.05  # doubling, capped


def test_a_helper_that_returns_while_the_daemon_runs_is_a_failure_too():
    failures: list[str] = []
    runs = 0
    stopping = False

    async def helper() -> None:
        nonlocal runs, stopping
        runs += 1
        stopping = runs == 2  # the second run returns because the daemon stops: not a failure

    asyncio.run(
        asyncio.wait_for(
            run_supervised("camera_reader", helper, lambda: stopping,
                           lambda n, e: failures.append(str(e)), backoff_s=0.01),
            1.0,
        )
    )  # fmt: skip
    assert runs == 2 and failures == ["returned while the daemon runs"]


def test_cancelling_the_supervisor_cancels_the_helper():
    cancelled = asyncio.Event()

    async def helper() -> None:
        try:
            await asyncio.sleep(10.0)
        except asyncio.CancelledError:
            cancelled.set()
            raise

    failures: list[str] = []

    async def go() -> None:
        task = asyncio.create_task(
            run_supervised("camera_reader", helper, lambda: False, lambda n, e: failures.append(n))
        )
        await asyncio.sleep(0.05)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(task, 1.0)
        assert cancelled.is_set() and task.cancelled()

    asyncio.run(go())
    assert failures == []  # a cancellation (the daemon stopping) is not a failure


def test_a_map_update_that_raises_costs_that_cloud_not_the_perceiver(tmp_path):
    """The perceiver (``Daemon._perceiver``) as the daemon runs it, under run_supervised, with a
    real worker process: a map update (``core.on_perception``) that raises is counted and
    logged as a perception error, that one cloud is lost, and the same task enters the next
    clouds — the supervisor sees no failure, so nothing waits out a restart backoff."""
    import numpy as np
    from daemon_helpers import faulty_perceive

    from omnid.daemon.capture import CaptureJob, Frame
    from omnid.daemon.config import ConfigHolder
    from omnid.daemon.perception_worker import PerceptionWorker
    from omnid.daemon.run import Daemon

    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        "perception:\n  enabled: false\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )
    entered: list[float] = []
    calls = 0

    def on_perception(cloud, t_s: float) -> None:  # the first update raises, as a bug would
        nonlocal calls
        calls += 1
        if calls == 1:
            raise RuntimeError("map update bug")
        entered.append(float(cloud.xyz[0, 0]))

    def job(x: int, t_s: float) -> CaptureJob:
        base = (np.full((48, 64), x, np.uint8), np.zeros((48, 64), np.uint8))
        mask = (np.zeros((48, 64), np.uint8), np.zeros((48, 64), np.uint8))
        return CaptureJob(Frame(t_s, base), (Frame(t_s - 0.03, mask),), started_s=t_s - 0.05)

    supervisor_failures: list[str] = []

    async def go() -> Daemon:
        d = Daemon(ConfigHolder(cfg), notifier=None)
        d.core.on_perception = on_perception  # type: ignore[method-assign]
        d.worker = PerceptionWorker(None, timeout_s=5.0, nice=0, fn=faulty_perceive)
        await d.worker.start()
        try:
            task = asyncio.create_task(
                run_supervised("perceiver", d._perceiver, d._stop.is_set,
                               lambda n, e: supervisor_failures.append(str(e)), backoff_s=1.0)
            )  # fmt: skip
            now = time.monotonic()
            for k, x in enumerate((11, 22, 33)):
                d._jobs.append(job(x, now + 0.01 * k))
            d._job_ready.set()
            t_end = time.monotonic() + 10.0
            while len(entered) < 2 and time.monotonic() < t_end:
                await asyncio.sleep(0.01)
            d._stop.set()
            d._job_ready.set()
            await asyncio.wait_for(task, 3.0)
        finally:
            await d.worker.close()
        return d

    d = asyncio.run(go())
    assert calls == 3 and entered == [22.0, 33.0]  # the first cloud lost, the next two entered
    assert supervisor_failures == []  # the task itself never failed
    assert d.stats.perception_errors == 1 and d.stats.perception_cycles == 2
