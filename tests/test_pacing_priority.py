"""PLATOON_REALTIME_PRIORITY (fmus/realtime.py, PacingPriority and pacing_helper): only the thread that asks is
raised, the threads it starts afterwards are not, restore undoes it, and where the OS refuses it the thread is
left as it was with one line saying why. Each check runs on a thread of its own, so the test process keeps its
scheduler whatever happens."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Callable

import pytest

from fmus.realtime import PRIORITY_VARIABLE, PacingPriority

REPO = Path(__file__).resolve().parents[1]
linux = pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="no per-thread scheduling policy on this OS")


def on_a_thread(work: Callable[[], Any]) -> Any:
    """``work()`` on a thread of its own, which ends with it; its result (or what it raised)."""
    result: list[Any] = []

    def run() -> None:
        try:
            result.append(work())
        except BaseException as error:  # noqa: BLE001  (re-raised in the test's thread)
            result.append(error)

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    if isinstance(result[0], BaseException):
        raise result[0]
    return result[0]


def scheduler() -> tuple[int, int]:
    return os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(0).sched_priority


def permitted() -> bool:
    return on_a_thread(lambda: PacingPriority("probe", {PRIORITY_VARIABLE: "1"}).raised)


def not_a_priority(value: str) -> str:
    return (f"{PRIORITY_VARIABLE}={value}: expected a real-time priority 1-{os.sched_get_priority_max(os.SCHED_FIFO)} "
            "(or 0: none); the run's stepping thread keeps the normal scheduler")


@linux
@pytest.mark.parametrize("value, says", [("", None), ("0", None), ("high", not_a_priority), ("-3", not_a_priority),
                                         ("1000", not_a_priority)])
def test_unset_or_0_changes_nothing_silently_and_a_value_that_is_no_priority_says_so(
        value: str, says: Callable[[str], str] | None) -> None:
    def ask() -> tuple[Any, ...]:
        before = scheduler()
        priority = PacingPriority("the run's stepping thread", {PRIORITY_VARIABLE: value})
        return priority.note, priority.raised, before, scheduler()

    note, raised, before, after = on_a_thread(ask)
    assert not raised and before == after
    assert note == (says(value) if says is not None else None)


@linux
def test_only_the_asking_thread_is_raised_not_the_threads_it_starts_and_restore_undoes_it() -> None:
    if not permitted():
        pytest.skip("real-time priority is not permitted here (root, CAP_SYS_NICE or `ulimit -r`)")

    def ask() -> tuple[Any, ...]:
        before = scheduler()
        priority = PacingPriority("the loop", {PRIORITY_VARIABLE: "7"})
        raised = scheduler()
        started = on_a_thread(scheduler)  # a thread it starts: the normal scheduler (SCHED_RESET_ON_FORK)
        child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                               capture_output=True, text=True, check=True).stdout.strip()
        priority.restore()
        priority.restore()  # once undone, a second call changes nothing
        return priority.note, before, raised, started, child, scheduler()

    note, before, raised, started, child, after = on_a_thread(ask)
    assert note == f"the loop at real-time priority (SCHED_FIFO 7, {PRIORITY_VARIABLE}=7); the threads it starts are not"
    assert raised == (os.SCHED_FIFO, 7)
    assert started == (os.SCHED_OTHER, 0) and child == str(os.SCHED_OTHER)
    assert after == before == (os.SCHED_OTHER, 0)
    assert scheduler() == (os.SCHED_OTHER, 0)  # the test's own thread was never touched


@linux
def test_where_not_permitted_the_thread_keeps_its_scheduler_and_one_line_says_why(tmp_path: Path) -> None:
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run a check as an unprivileged user")
    script = ("import os\nfrom fmus.realtime import PacingPriority\n"
              "p = PacingPriority('the run\\'s stepping thread', {'PLATOON_REALTIME_PRIORITY': '10'})\n"
              "print(p.raised, p.level, os.sched_getscheduler(0))\nprint(p.note)\n")
    done = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-c", script],
                          cwd=REPO, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr
    state, note = done.stdout.splitlines()
    assert state == f"False Warning {os.SCHED_OTHER}"
    assert note == (f"{PRIORITY_VARIABLE}=10: real-time priority not permitted here (it needs root, CAP_SYS_NICE or an "
                    "rtprio limit: `ulimit -r`); the run's stepping thread keeps the normal scheduler, and may fall "
                    "behind on a busy machine")
