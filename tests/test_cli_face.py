"""The CLI as a newcomer meets it: ``platoon --version`` and a summary table that names its units and
the interval its max |path error| is taken over, at 80 columns (the console script, in a subprocess)."""

from __future__ import annotations

from pathlib import Path

from orchestrator import __version__
from tests.test_viewer import PAPER, platoon

FRONT_LATERAL = PAPER.with_name("platoon_front_lateral.toml")


def test_version_prints_the_package_version(tmp_path: Path) -> None:
    result = platoon("--version", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"platoon {__version__} (") and "fmpy" in result.stdout


def test_summary_table_shows_units_and_the_interval_of_the_max_path_error(tmp_path: Path) -> None:
    plain = platoon("run", PAPER, "--set", "simulation.stop_time=1.0", "--out", tmp_path / "a.mcap", cwd=tmp_path)
    assert plain.returncode == 0, plain.stderr
    # rich reads "[m]" as markup and drops it unless escaped; the header may wrap, the units must show
    for unit in ("[m]", "[m/s]"):
        assert unit in plain.stdout
    assert "max |path error|" in plain.stdout and "whole run" in plain.stdout
    assert "means over the last 10% of the recorded time" in plain.stdout
    for line in plain.stdout.splitlines():
        assert len(line) <= 80, line
    disturbed = platoon("run", FRONT_LATERAL, "--set", "simulation.stop_time=36.0", "--out", tmp_path / "b.mcap",
                        cwd=tmp_path)
    assert disturbed.returncode == 0, disturbed.stderr
    assert "t >= 35 s" in disturbed.stdout  # from the first disturbance on (orchestrator/metrics.py)
