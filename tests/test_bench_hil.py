"""``platoon bench hil`` works end to end on loopback: ping-pong and live runs against the emulator.

Functional checks only (keys present, medians finite and positive): the numbers themselves are
reported by the bench, never asserted, since timing on a shared machine is no pass/fail criterion.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tests.test_bench import written
from tests.test_cli import REPO, platoon

LIVE = ("step 100 Hz, poses 200 Hz", "step 200 Hz, poses 200 Hz", "step 100 Hz, poses 1000 Hz",
        "step 100 Hz, poses 200 Hz, TLS+ACL")


@pytest.mark.realtime
def test_hil_measures_transport_and_live_runs(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "hil", "--seconds", "2", "--out-dir", tmp_path, "-q", cwd=REPO)
    data = written(result, tmp_path, "hil")
    assert result.stderr == ""  # --quiet: no progress lines
    medians = data["medians"]
    assert set(medians) == {"transport", "transport, TLS+ACL", *LIVE}
    for name, values in medians.items():
        assert all(math.isfinite(values[f"round_trip.{s}"]) and values[f"round_trip.{s}"] > 0
                   for s in ("median", "p99", "max")), (name, values)
    for name in LIVE:
        values = medians[name]
        assert all(math.isfinite(values[f"jitter.{s}"]) and values[f"jitter.{s}"] >= 0 for s in ("median", "p99", "max"))
        assert values["points"] > 0 and values["overruns"] >= 0
        assert data["round_trip_over_transport"][name] > 0
    live = [s for s in data["samples"] if s["kind"] == "live"]
    assert sorted((s["step"], s["pose_rate"], s["secure"]) for s in live) == [
        (0.005, 200.0, False), (0.01, 200.0, False), (0.01, 200.0, True), (0.01, 1000.0, False)]
    assert all(s["vehicles"] == ["vehicle3"] and s["link"]["command.sent"] > 0 for s in live)
    assert "round trip, ms" in result.stdout and "step jitter, ms" in result.stdout
    checks = data["checks"]  # every message's checks, and decoding alone as their reference
    assert set(checks) == {"pose.decode", "pose.checks", "command.decode", "command.checks"}
    assert all(math.isfinite(value) and value > 0 for value in checks.values())
    assert "checks per message" in result.stdout
