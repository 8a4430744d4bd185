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
