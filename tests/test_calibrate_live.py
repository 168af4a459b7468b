"""`platoon calibrate` on real live runs: the m3pi emulator (a real process) plays robots unlike their model from
a truth file, `platoon run` drives the calibration experiment (configs/hil/calibrate.toml) over Zenoh on
127.0.0.1, and `platoon calibrate` must find each truth from that one run's trace (issue 51's floors).

The experiment is paced in wall-clock time (a minute per robot): the floor test is ``slow``. A run this
machine could not pace (the robot lost for a stall, the run far behind) is tried again and, when every try
fell behind, skipped saying so: its trace would test the machine, not the identification.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import time
import tomllib
from pathlib import Path

import pytest

from tests.conftest import free_port, realtime_not_tested
from orchestrator.trace import load
from tests.calibration_support import random_truth
from tests.test_calibrate import identification_misses
from tests.test_hil import PLATOON, REPO, _env, end_process, endpoint

EXPERIMENT = REPO / "configs" / "hil" / "calibrate.toml"
# s: a run further behind its wall-clock schedule than this is not a fair experiment. Lateness itself is in the
# trace (the commands' send times, the poses' echoes of the commands applied), so calibrate takes a stall in its
# stride; a run that stalls this long has mostly lost its robot instead (exit 1), and is tried again.
BEHIND_LIMIT = 5.0
TRIES = 3


def _emulator(port: int, truth: Path, log: Path, *options: str) -> subprocess.Popen:
    with open(log, "w") as stream:
        process = subprocess.Popen([str(PLATOON), "m3pi-emulator", "--config", str(EXPERIMENT), "--set",
                                    f'vehicles.1.connect=["{endpoint(port)}"]', "--robots", str(truth),
                                    *options], cwd=REPO, env=_env(), stdout=stream,
                                   stderr=subprocess.STDOUT)
    started = time.monotonic()
    while "configured, pose on" not in log.read_text():
        assert process.poll() is None, log.read_text()
        assert time.monotonic() - started < 30.0, "the emulator did not start"
        time.sleep(0.05)
    return process


def live_experiment(tmp_path: Path, truth: dict[str, float], name: str, *options: str) -> tuple[int, Path, str]:
    """One run of the experiment against an emulated robot 1 of ``truth`` (``options`` for the emulator);
    (exit code, trace, stderr)."""
    truth_file = tmp_path / f"{name}-truth.toml"
    own = {k: v for k, v in truth.items() if k not in ("position_noise", "heading_noise")}
    truth_file.write_text("[default]\nposition_noise = 0.002\nheading_noise = 0.035\n[robots.1]\n"
                          + "".join(f"{k} = {v!r}\n" for k, v in own.items()))
    port = free_port()
    emulator = _emulator(port, truth_file, tmp_path / f"{name}-emulator.log", *options)
    trace = tmp_path / f"{name}.mcap"
    try:
        arguments = [str(PLATOON), "run", str(EXPERIMENT), "-q", "--out", str(trace), "--set",
                     f'vehicles.1.connect=["{endpoint(port)}"]']
        run = subprocess.run(arguments, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=300)
    finally:
        end_process(emulator)
    return run.returncode, trace, run.stderr


def behind(trace: Path) -> float:
    """How far (s) the run fell behind its wall-clock schedule, added up over its stalls."""
    return float(json.loads(load(trace).metadata["platoon.hil"]["pacing"])["behind.total"])


def calibrate(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(PLATOON), "calibrate", *arguments], cwd=REPO, env=_env(), capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow  # three minutes of wall-clock runs; identification itself is tested fast in tests/test_calibrate.py
@pytest.mark.realtime  # paced live runs: alone on the machine (README, "Tests")
# Known to miss the floor on some truths, so not yet a gate: on the CI machine, alone at load 3-4 (2026-12-02, seed
# 3350251659), truth 0's command latency came out 21.7 ms against 36.4 ms (pose latency's share of the loop delay);
# under load 20-30 one run met every floor and one missed a loop delay by 3.1 ms. Issue 51 stays open on it.
@pytest.mark.xfail(reason="the loop delay is not yet identified within 3 ms of every random truth (issue 51)",
                   strict=False)
def test_three_random_robots_are_identified_from_one_run_of_the_experiment_each(tmp_path: Path) -> None:
    seed = int.from_bytes(os.urandom(4), "little")
    rng = random.Random(seed)
    unpaced = []
    for index in range(3):
        truth = random_truth(rng)
        for attempt in range(TRIES):
            code, trace, stderr = live_experiment(tmp_path, truth, f"robot{index}-{attempt}")
            late = behind(trace) if trace.exists() and code == 0 else float("inf")
            if code == 0 and late <= BEHIND_LIMIT:
                break
            unpaced.append(f"truth {index} try {attempt}: exit {code}, behind {late:.2f} s: {stderr.strip()[-300:]}")
        else:
            realtime_not_tested(f"seed {seed}: this machine could not pace the experiment: {unpaced}")
        out = tmp_path / f"robot{index}.toml"
        result = calibrate(str(trace), "--out", str(out))
        assert result.returncode == 0, result.stderr
        written = tomllib.loads(out.read_text())["m3pi"]
        from orchestrator.analysis.calibrate import calibrate_robot
        from orchestrator.analysis.robot_record import robot_records

        calibration = calibrate_robot(robot_records(load(trace), trace))
        print(f"\nseed {seed}, truth {index}: {truth}, the run {behind(trace):.2f} s behind\n{result.stdout}")
        assert calibration.values() == pytest.approx(written, rel=1e-5)  # what it printed is what it wrote (6 digits)
        misses = identification_misses(calibration, truth)
        assert not misses, (f"seed {seed}, truth {index} {truth}: {misses} (the run was {behind(trace):.2f} s behind)",
                            result.stdout)


def test_a_trace_without_a_live_robot_is_one_line(tmp_path: Path) -> None:
    trace = tmp_path / "simulated.mcap"
    run = subprocess.run([str(PLATOON), "run", str(EXPERIMENT), "-q", "--out", str(trace), "--set",
                          "vehicles.1.endpoint=fmu", "--set", "simulation.stop_time=2.0"], cwd=REPO, env=_env(),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    result = calibrate(str(trace), "--out", str(tmp_path / "robot.toml"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "no live vehicle" in result.stderr and not (tmp_path / "robot.toml").exists()


def test_a_robot_that_never_moves_and_its_cut_short_run_are_one_line_each(tmp_path: Path) -> None:
    """A dead-band above every command, from rest: the robot stands still, the run's motion watch ends it (exit 1).
    Its trace is a run cut short: refused as such; with --partial, refused for poses that never moved."""
    code, trace, stderr = live_experiment(tmp_path, {"wheel_deadband": 5.0}, "still", "--standing-start")
    assert code == 1 and "not moving" in stderr, stderr
    result = calibrate(str(trace), "--out", str(tmp_path / "robot.toml"))
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "ended early (failed)" in result.stderr and "--partial" in result.stderr
    result = calibrate(str(trace), "--out", str(tmp_path / "robot.toml"), "--partial")
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "poses never moved" in result.stderr and not (tmp_path / "robot.toml").exists()
