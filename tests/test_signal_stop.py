"""The robot-side programs (m3pi-emulator, m3pi-bridge, mocap, serve) stop on SIGINT/SIGTERM through
``stop_on_signals``, whose main thread waits on the stop event in a loop. A handler that set the event itself
deadlocked when the signal landed while the main thread held the event's lock inside ``wait()``: an emulator
hung on Ctrl-C (then ignored every signal after it). Here the main thread spends its time inside ``wait(0)``,
where that window is widest (the old handler hung within the first two of these trials, three times of three),
and every signal must still end the wait."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

TRIALS = 300
PROGRAM = f"""
import os, random, signal, threading
from orchestrator.cli.hil import stop_on_signals

for trial in range({TRIALS}):
    stop = threading.Event()
    stop_on_signals(stop)
    threading.Timer(random.uniform(0, 0.002), os.kill, (os.getpid(), signal.SIGINT)).start()
    while not stop.is_set():
        stop.wait(0)
print("stopped", trial + 1)
"""


def test_every_signal_stops_a_loop_waiting_on_the_event() -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    try:
        done = subprocess.run([sys.executable, "-c", PROGRAM], cwd=REPO, env=env, capture_output=True, text=True,
                              timeout=60)  # a hung child is killed (SIGKILL)
    except subprocess.TimeoutExpired as error:
        raise AssertionError(f"a signal did not stop the loop (deadlocked); output so far: {error.stdout!r}") from None
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["stopped", str(TRIALS)]
