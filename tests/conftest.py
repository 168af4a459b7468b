"""Shared fixtures: FMUs built once per test session, and quick scenario runs.

The suite runs in parallel (pytest-xdist, pyproject's addopts): each worker has its own session, so a
session fixture runs once per worker. What workers share (the repository's build/ folder) is built
under ``shared_build``'s lock: the first worker builds, the others wait and find it up to date. A test
that must listen on a fixed port holds ``fixed_ports``; any other takes a free port (``free_port``).
"""

from __future__ import annotations

import os

# One BLAS thread per process, set before numpy loads OpenBLAS (and handed down to every subprocess a test
# starts): the suite's parallel workers keep both cores busy already, and OpenBLAS's own threads only
# spin against them (eigen_report of 100 vehicles: 3.2 s of CPU with its default threads, 1.8 s with one,
# and sooner). A thread count the user set is kept.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

# Every live run and robot side a test starts shares one lab key (bridge/lab_key.py) of this test session,
# handed down to subprocesses: none reads or makes the key in the user's own ~/.config.
if "PLATOON_LAB_KEY" not in os.environ:
    import tempfile as _tempfile

    os.environ["PLATOON_LAB_KEY"] = os.path.join(_tempfile.mkdtemp(prefix="platoon-lab-key-"), "lab.key")

import fcntl
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from fmus.builders import DEFAULT_OUT, FMU_NAMES, LINK_FMU, PYTHONFMU
from fmus.realtime import PRIORITY_VARIABLE
from orchestrator.scenario.config import Config, config_from_mapping
from orchestrator.execution.run import run_scenario
from orchestrator.trace import Trace, load

REPO = Path(__file__).resolve().parents[1]

# A start far enough from the equilibrium to show convergence: vehicle 1 5 m off the path and 0.1 rad off its heading, everyone at
# 80 % of V_c (also the shipped configs/paper/platoon.toml start).
PAPER_START = {"radial_offset": 5.0, "heading_error": 0.1, "speed_factor": 0.8}


# Appended to a paper config: a -100 m/s speed pulse on vehicle 4 at t = 1 s drives its speed below
# zero in the next step, a real mid-run FMU failure.
SPEED_TO_ZERO = """
[[disturbance]]
vehicle = 4
kind = "speed"
start = 1.0
duration = 0.5
value = -100.0
"""


# Set by CI (.ci/run): a real-time test that could not test what it is for (every try of a live run fell
# behind the wall clock) fails instead of skipping, so a green CI means real-time behaviour was tested.
REQUIRE_REALTIME = "PLATOON_REQUIRE_REALTIME"


def realtime_not_tested(why: str) -> None:
    """A real-time test could not test its behaviour on this machine's load: skipped, saying ``why``, where a
    developer runs the suite on a busy laptop; a failure where ``PLATOON_REQUIRE_REALTIME=1`` (CI)."""
    why = f"{why} (paced threads: {_pacing_priority_text()})"
    if os.environ.get(REQUIRE_REALTIME, "") not in ("", "0"):
        pytest.fail(f"{why} ({REQUIRE_REALTIME} is set: real-time behaviour must be tested here)")
    pytest.skip(why)


# The real-time priority a real-time test's paced threads get (fmus/realtime.py, PacingPriority: the run's stepping
# thread, the emulated robot's timing loop; nothing else they start), where this machine permits it: over every
# thread at the normal scheduler (a busy machine's, the test's own, Zenoh's, the trace writer's) and under the
# kernel's interrupt threads (SCHED_FIFO 50). Measured 2026-12-03: docs/hil.md, "Accuracy". A value the user set
# (PLATOON_REALTIME_PRIORITY, 0 for none) is kept.
TEST_PACING_PRIORITY = 10
_pacing_permitted: bool | None = None  # found once per test process (_may_raise_pacing)


def _may_raise_pacing() -> bool:
    """Whether a thread of this process may take ``TEST_PACING_PRIORITY``: asked by a thread of its own, which
    ends at once, so no thread of the test session keeps it."""
    global _pacing_permitted
    if _pacing_permitted is None:
        from fmus.realtime import PacingPriority

        answer: list[bool] = []

        def probe() -> None:
            priority = PacingPriority("probe", {PRIORITY_VARIABLE: str(TEST_PACING_PRIORITY)})
            answer.append(priority.raised)
            priority.restore()

        prober = threading.Thread(target=probe, name="real-time priority probe")
        prober.start()
        prober.join()
        _pacing_permitted = answer == [True]
    return _pacing_permitted


def _pacing_priority_text() -> str:
    wanted = os.environ.get(PRIORITY_VARIABLE, "")
    if wanted not in ("", "0"):
        return f"{PRIORITY_VARIABLE}={wanted}"
    return ("normal scheduler (real-time priority not permitted here: root, CAP_SYS_NICE or `ulimit -r`)"
            if _pacing_permitted is False else "normal scheduler")


@pytest.fixture(autouse=True)
def _realtime_pacing_priority(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A real-time test's runs and emulated robots pace at ``TEST_PACING_PRIORITY`` where permitted (handed down
    in the environment): on a quiet machine their tracking then fell behind less often (docs/hil.md, "Accuracy";
    beside a CPU-bound process it did not help); a test not marked realtime changes nothing."""
    if request.node.get_closest_marker("realtime") is None or PRIORITY_VARIABLE in os.environ:
        return
    if _may_raise_pacing():
        monkeypatch.setenv(PRIORITY_VARIABLE, str(TEST_PACING_PRIORITY))


@contextmanager
def shared_build() -> Iterator[None]:
    """Held while building into the repository's build/ folder: parallel workers (and two test runs in
    one checkout) would otherwise compile the same FMUs side by side, each a few seconds of both cores.
    Builds are safe without it (each FMU is renamed into place whole); the lock only saves the work."""
    folder = REPO / "build"
    folder.mkdir(exist_ok=True)
    with open(folder / ".tests-build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed, or the process dies
        yield


@contextmanager
def machine_lock(name: str) -> Iterator[None]:
    """Held across parallel workers and across test runs of other checkouts on this machine (the lock
    file is in the system's temporary folder): for what the machine shares, a fixed port or Zig's cache."""
    with open(Path(tempfile.gettempdir()) / f"platoon-cosim-tests-{name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed, or the process dies
        yield


@pytest.fixture(scope="session")
def zig_cache() -> dict[str, float]:
    """Zig's global cache warmed for every release target (fmus/builders/zig_cache.py) before a test
    times a cross-compilation (`platoon build --all-platforms`): on a cold cache the first build for a
    target also builds its C library and compiler-rt, minutes on 2 cores (MinGW-w64's CRT most of it).
    Once per machine: the first worker warms it under the lock, the others then find it warm (under a
    second). Returns the seconds each target took; skips without ziglang."""
    from importlib.util import find_spec

    if find_spec("ziglang") is None:
        pytest.skip("ziglang is not installed (pip install -e '.[release]'): no cross-compiled binaries")
    from fmus.builders.zig_cache import warm_cross_cache

    with machine_lock("zig-cache"):
        return warm_cross_cache()


@contextmanager
def fixed_ports() -> Iterator[None]:
    """Held while a test listens on a fixed, documented port (a HIL config's tcp/127.0.0.1:7447, a live
    view's port) instead of a free one: such tests run one at a time across parallel workers, and across
    test runs of other checkouts on this machine."""
    with machine_lock("fixed-ports"):
        yield


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now (the kernel's pick; a test binds it soon after)."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="session")
def fmu_dir() -> Path:
    """The FMUs, built (or found up to date) in the repository's build folder, as users get them."""
    out = REPO / DEFAULT_OUT
    with shared_build():
        PYTHONFMU.build(out, names=FMU_NAMES + (LINK_FMU,))
    return out


@pytest.fixture(scope="session")
def native_fmu_dir() -> Path:
    """The native (C) FMUs, built (or found up to date) in build/fmus/native; skipped without a C compiler."""
    from fmus.builders import NATIVE_FMI2, NATIVE_OUT, NoCompiler

    out = REPO / NATIVE_OUT
    try:
        with shared_build():
            NATIVE_FMI2.build(out, names=FMU_NAMES + (LINK_FMU,))
    except NoCompiler as error:
        pytest.skip(str(error))
    return out


@pytest.fixture(scope="session")
def fmi3_fmu_dir() -> Path:
    """The native FMI 3.0 FMUs (Vehicle, VirtualTarget), built (or found up to date) in build/fmus/fmi3;
    skipped without a C compiler."""
    from fmus.builders import FMI3_OUT, NATIVE_FMI3, NoCompiler

    out = REPO / FMI3_OUT
    try:
        with shared_build():
            NATIVE_FMI3.build(out, names=FMU_NAMES)
    except NoCompiler as error:
        pytest.skip(str(error))
    return out


def make_config(**sections: Any) -> Config:
    raw: dict[str, Any] = {"name": "test"}
    raw.update(sections)
    return config_from_mapping(raw)


@pytest.fixture
def run(tmp_path: Path, fmu_dir: Path):
    """run(config, engine=None) -> Trace (default engine: native when built), under the test's tmp folder."""
    counter = iter(range(1000))

    def _run(config: Config, engine: str | None = None) -> Trace:
        out = tmp_path / f"{config.name}-{engine or 'default'}-{next(counter)}.mcap"
        result = run_scenario(config, "", out, engine=engine, fmu_dir=fmu_dir)
        assert result.status == "completed", result.error
        return load(out)

    return _run


# pythonfmu FMUs run inside this interpreter, and its teardown after they ran intermittently
# corrupts the heap (glibc: "corrupted double-linked list"), turning a green run into exit 134. The
# CLI leaves with os._exit for the same reason (orchestrator/cli/app.py: main); here, once pytest has
# reported everything, we do the same with pytest's own exit status.
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    session.config.stash[_EXIT_STATUS] = int(exitstatus)


_EXIT_STATUS = pytest.StashKey[int]()


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    if _EXIT_STATUS in config.stash:
        import os
        import sys

        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(config.stash[_EXIT_STATUS])
