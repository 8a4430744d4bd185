"""The perception worker process: results come back, and an exception, a crash or a hang of
perceive costs one failed request (at most ``timeout_s``), never a stalled event loop."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest
from daemon_helpers import blas_threads_perceive, faulty_perceive, half_reply_perceive

from omnid.core.types import StereoCapture
from omnid.daemon.perception_worker import (
    PerceptionFailed,
    PerceptionWorker,
    blas_threads,
    decode_request,
    encode_request,
)


def capture(code: int, x: int, shape=(48, 64)) -> StereoCapture:
    imgs = [np.zeros(shape, np.uint8) for _ in range(4)]
    imgs[0][0, 0] = code
    imgs[1][0, 0] = x
    imgs[2][5, 7] = 9
    return StereoCapture(*imgs, timestamp_s=12.5)


def test_request_round_trip_is_exact():
    cap = capture(0, 77, shape=(480, 640))
    back = decode_request(encode_request(cap))
    assert back.timestamp_s == 12.5
    for a, b in zip(
        (cap.mask1, cap.base1, cap.mask2, cap.base2),
        (back.mask1, back.base1, back.mask2, back.base2),
        strict=True,
    ):
        assert np.array_equal(a, b)
    with pytest.raises(ValueError):
        decode_request(encode_request(cap)[:-1])


def test_worker_survives_exception_crash_and_hang_without_stalling_the_loop():
    async def main() -> tuple[list[str], float, PerceptionWorker]:
        w = PerceptionWorker(None, timeout_s=0.5, nice=0, fn=faulty_perceive)
        await w.start()
        gaps: list[float] = []
        stop = asyncio.Event()

        async def ticker() -> None:  # stands in for the control loop
            last = time.monotonic()
            while not stop.is_set():
                await asyncio.sleep(0.01)
                now = time.monotonic()
                gaps.append(now - last)
                last = now

        tick = asyncio.create_task(ticker())
        out: list[str] = []
        for code, x in ((0, 11), (3, 0), (0, 12), (2, 0), (0, 13), (1, 0), (0, 14)):
            t0 = time.monotonic()
            try:
                cloud = await w.perceive(capture(code, x))
                out.append(f"ok {cloud.xyz[0, 0]:.0f}")
            except PerceptionFailed as exc:
                out.append(f"failed {exc}")
            if code == 1:
                assert time.monotonic() - t0 < 0.5 + 1.5  # timeout plus the kill
        stop.set()
        await tick
        await w.close()
        return out, max(gaps), w

    out, worst_gap, w = asyncio.run(main())
    assert out[0] == "ok 11" and out[2] == "ok 12" and out[4] == "ok 13" and out[6] == "ok 14"
    assert out[1].startswith("failed perceive failed: ValueError: bad capture")
    assert out[3].startswith("failed perception worker crashed")
    assert out[5].startswith("failed perceive took longer than 0.5 s")
    assert w.restarts == 2 and w.failures == 3
    # the event loop kept ticking throughout (spawning a child may cost a few ms)
    assert worst_gap < 0.1, worst_gap


def test_the_worker_runs_numpys_blas_on_one_thread():
    """OpenBLAS would start a spinning thread per core in the child, beside the control loop."""
    if not blas_threads():
        pytest.skip("numpy here has no OpenBLAS")

    async def main() -> float:
        w = PerceptionWorker(None, timeout_s=5.0, nice=0, fn=blas_threads_perceive)
        await w.start()
        try:
            cloud = await w.perceive(capture(0, 0))
        finally:
            await w.close()
        return float(cloud.xyz[0, 0])

    assert asyncio.run(main()) == 1.0


def test_a_worker_that_stops_reading_costs_one_request_not_a_hung_perceiver():
    """A child that no longer reads its pipe (frozen: SIGSTOP here; in the field a stalled or
    thrashing process) while a 1.2 MB job is sent: the send filled the pipe and blocked with no
    timeout, so the perceiver hung for good (perception stale, never recovering, nothing logged).
    The request must fail within ``timeout_s`` and the next one go to a fresh child."""
    import os
    import signal

    async def main() -> tuple[str, float, str]:
        w = PerceptionWorker(None, timeout_s=0.5, nice=0, fn=faulty_perceive)
        await w.start()
        pid = w.pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        t0 = time.monotonic()
        try:
            await asyncio.wait_for(w.perceive(capture(0, 5, shape=(480, 640))), 2.5)
            first = "ok"
        except PerceptionFailed as exc:
            first = f"failed {exc}"
        except TimeoutError:
            first = "hung"
            os.kill(pid, signal.SIGKILL)  # free the blocked send, so the test can end
        took = time.monotonic() - t0
        try:
            cloud = await asyncio.wait_for(w.perceive(capture(0, 21)), 25.0)
            second = f"ok {cloud.xyz[0, 0]:.0f}"
        except (PerceptionFailed, TimeoutError) as exc:
            second = f"failed {exc!r}"
        await w.close()
        return first, took, second

    first, took, second = asyncio.run(main())
    assert first.startswith("failed"), f"the request {first} (after {took:.1f} s)"
    assert took < 0.5 + 1.5
    assert second == "ok 21"


def test_a_worker_that_freezes_mid_reply_costs_one_request():
    """The answer's first bytes came (poll returned), then the child froze: recv_bytes waited
    for the rest with no timeout, and the perceiver hung for good. The whole request — send,
    wait, receive — must end within ``timeout_s``."""

    async def main() -> tuple[str, float]:
        w = PerceptionWorker(None, timeout_s=0.5, nice=0, fn=half_reply_perceive)
        await w.start()
        pid = w.pid
        t0 = time.monotonic()
        try:
            await asyncio.wait_for(w.perceive(capture(0, 5)), 2.5)
            out = "ok"
        except PerceptionFailed as exc:
            out = f"failed {exc}"
        except TimeoutError:
            out = "hung"
            import os
            import signal

            os.kill(pid, signal.SIGKILL)  # free the blocked receive, so the test can end
        took = time.monotonic() - t0
        await w.close()
        return out, took

    out, took = asyncio.run(main())
    assert out.startswith("failed"), f"the request {out} (after {took:.1f} s)"
    assert took < 0.5 + 1.5
