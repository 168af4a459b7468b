""""N steps in X s" counts a run's work, not its start's waits for a live robot (the viewer's wait,
--live-wait, is tests/test_foxglove_view.py's): a real run of configs/hil/m3pi_live3.toml whose robot's
emulator is started a few seconds after the run says it waits for it."""

from __future__ import annotations

import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.conftest import free_port
from tests.test_hil import LIVE3, PLATOON, REPO, _env, emulator, endpoint, wait_for


@pytest.mark.realtime
def test_the_steps_time_leaves_out_the_wait_for_the_robot(tmp_path: Path) -> None:
    """The robot's emulator starts HOLD s after the run says it waits for the robot (a wait made on purpose:
    it is what is measured). The 2 s run is paced to the wall clock, so its own work is a little over 2 s;
    X stays under 2 + HOLD / 2 s on a loaded machine, and would be over 2 + HOLD if the wait counted."""
    hold, stop = 6.0, 2.0
    port, trace, errors = free_port(), tmp_path / "late.mcap", tmp_path / "run.stderr"
    with open(errors, "w") as stream:
        run = subprocess.Popen([str(PLATOON), "run", str(LIVE3), "--out", str(trace), "--set", f"simulation.stop_time={stop}",
                                "--set", f'vehicles.3.connect=["{endpoint(port)}"]', "--set", "hil.connect_timeout=120"],
                               cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=stream, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        wait_for(lambda: "waiting for robot 3" in errors.read_text(), "the run waits for its robot", run)
        time.sleep(hold)
        with emulator(port, tmp_path):
            stdout, _ = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
    assert run.returncode == 0, errors.read_text()
    done = re.search(r"\((\d+) steps in ([\d.]+) s\)", stdout)
    assert done and int(done.group(1)) == 200, stdout
    assert stop <= float(done.group(2)) < stop + hold / 2, stdout
    assert "reported nothing back" not in stdout  # our protocol's robot side reports what it received
    # where those seconds went: the stepping, held to the pace's 2 s (or behind it, saying so), and the start
    # and finish around it
    paced = re.search(r"^paced: 2 s of simulated time on the wall clock; stepping took ([\d.]+) s(.*); starting and "
                      r"finishing ([\d.]+) s$", stdout, re.MULTILINE)
    assert paced and float(paced.group(1)) >= stop - 0.005, stdout
    assert float(paced.group(1)) + float(paced.group(3)) == pytest.approx(float(done.group(2)), abs=0.011), stdout
    assert paced.group(2) in ("", f", so the run ended {float(paced.group(1)) - stop:.2f} s behind the pace: it fell "
                                  "behind (a loaded machine)"), stdout
