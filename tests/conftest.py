"""Shared fixtures: seeded random generators and the nominal stereo rig."""

from __future__ import annotations

import contextlib
import inspect
import os
import threading

# One thread per test process, set before numpy and OpenCV load: the suite runs one pytest-xdist
# worker per core, and each library's own pool on top (OpenBLAS spin-waits, OpenCV splits every
# remap) cost a quarter more CPU for the same results. Processes the tests start inherit it.
for _var in (
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from omnid.core.geometry import StereoRig  # noqa: E402


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--soak-minutes",
        type=float,
        default=2.0,
        help="simulated minutes of tests/scenarios/test_soak.py (2 in CI; the half hour: 30)",
    )
    parser.addoption(
        "--fuzz-streams",
        type=int,
        default=30_000,
        help="random streams of the control-unit parser fuzz, tests/devices/test_cu_codec.py "
        "(30 000 in CI; docs/benchmarks.md's figure: 100 000)",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "slow(seconds): a long run (still part of CI) and about how long it takes on a 2-core "
        "machine, s: the suite starts it first, on the least loaded worker",
    )


def _seconds(item: pytest.Item) -> float:
    mark = item.get_closest_marker("slow")
    if mark is None:
        return 0.0
    return float(mark.kwargs["seconds"] if "seconds" in mark.kwargs else mark.args[0])


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the tests so that pytest-xdist starts every long run first, spread over its workers.

    ``--dist worksteal`` hands each of n workers one contiguous share of the collection and
    later moves the tail of the longest queue to an idle worker. So each long run (``slow(seconds)``) goes, longest first, to the head of the share
    with the least long-run time so far; the others keep their order behind them. Without it,
    the suite's last half-minute was one worker alone in a 25 s test."""
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    long_runs = sorted((it for it in items if _seconds(it) > 0), key=_seconds, reverse=True)
    if not long_runs:
        return
    rest = [it for it in items if _seconds(it) == 0]
    sizes, left = [], len(items)
    for k in range(workers):  # the shares' sizes as worksteal's first distribution cuts them
        sizes.append(left // (workers - k))
        left -= sizes[-1]
    heads: list[list[pytest.Item]] = [[] for _ in range(workers)]
    load = [0.0] * workers
    for it in long_runs:
        k = min((k for k in range(workers) if len(heads[k]) < sizes[k]), key=lambda k: load[k])
        heads[k].append(it)
        load[k] += _seconds(it)
    order: list[pytest.Item] = []
    for head, size in zip(heads, sizes, strict=True):
        take = size - len(head)
        order += head + rest[:take]
        rest = rest[take:]
    items[:] = order


BACKGROUND_NICE = 10  # CFS weight 110 against 1024: a real-time process gets ~90 % of a core

#: The tests that keep wall-clock deadlines (processes, ptys, sockets, sleeps), by node id: the
#: daemon and the device links against emulators, the recorder and the bench, the
#: hardware-in-the-loop run, the frame server, the newcomer's first run.
REALTIME_PATHS = (
    "tests/daemon/",
    "tests/devices/",
    "tests/record/",
    "tests/scenarios/test_hil.py",
    "tests/sim/test_frame_server.py",
    "tests/test_cli_newcomer.py",
)
#: Under those paths, but pure computation (no clock, no pty): the codecs' fuzz tests, 10–15 s
#: of CPU that would otherwise compete with the real-time tests at their priority.
COMPUTE_ONLY_PATHS = ("tests/devices/test_cu_codec.py", "tests/devices/test_tilt_codec.py")


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem: pytest.Function) -> bool | None:
    """Run a test that only computes (on the simulator's virtual clock, or none) in a thread of
    lower CPU priority (Linux: a nice value is per thread, inherited by the processes it starts;
    the thread and its priority end with the test).

    Whenever such a test shares the cores with a real-time one (the daemon as a process against
    emulators on ptys, with wall-clock deadlines), the real-time test's processes should get
    the CPU first, or the suite's own load makes them miss their deadlines — as it did (the
    HIL run out of time at 45 s, 4 stream masks where >10 are due) while all ran at one
    priority. The real-time tests (:data:`REALTIME_PATHS`) stay on the main thread."""
    nodeid = pyfuncitem.nodeid
    realtime = nodeid.startswith(REALTIME_PATHS) and not nodeid.startswith(COMPUTE_ONLY_PATHS)
    if realtime or inspect.iscoroutinefunction(pyfuncitem.obj):
        return None
    args = {name: pyfuncitem.funcargs[name] for name in pyfuncitem._fixtureinfo.argnames}
    raised: list[BaseException] = []

    def body() -> None:
        with contextlib.suppress(AttributeError, OSError):  # not Linux: the usual priority
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), BACKGROUND_NICE)
        try:
            pyfuncitem.obj(**args)
        except BaseException as exc:  # re-raised in the test's own thread
            raised.append(exc)

    worker = threading.Thread(target=body, name=f"background {pyfuncitem.name}")
    worker.start()
    worker.join()
    if raised:
        raise raised[0]
    return True


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def nominal_rig() -> StereoRig:
    return StereoRig.nominal()


@pytest.fixture(scope="session")
def random_installations(
    tmp_path_factory: pytest.TempPathFactory, worker_id: str
) -> list[tuple[object, object]]:
    """10 random rigs with random lasers (rig 7: source near the mirror plane; rig 9: in it,
    with a grid uniform in angle), each calibrated on its floor and extras: (RigCase,
    Calibration). Shared by the calibration and matching rate tests (calibrating is the cost:
    ~10 s), and by the pytest-xdist workers: the first computes them, the others read its
    pickle (under a file lock)."""
    import fcntl
    import pickle

    from omnid.experiments import rigs as ev

    def compute() -> list[tuple[object, object]]:
        out = []
        for r in range(10):
            case = ev.rig_case(r, seed=1)
            out.append((case, ev.calibrate_case(case, seed=1)))
        return out

    if worker_id == "master":  # not distributed
        return compute()
    shared = tmp_path_factory.getbasetemp().parent / "random_installations.pickle"
    with open(shared.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if shared.exists():
            return pickle.loads(shared.read_bytes())  # type: ignore[no-any-return]
        data = compute()
        shared.write_bytes(pickle.dumps(data))
        return data
