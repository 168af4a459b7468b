"""`platoon build`: builds once, then only when an FMU is missing, stale or damaged."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from fmus.build import expected_guid, fmu_guid

REPO = Path(__file__).resolve().parents[1]
# `platoon` from this checkout (the console script may belong to another install of the package)
PLATOON = [sys.executable, "-c", "import sys; sys.argv[0] = 'platoon'; from orchestrator.cli import main; main()"]


def _build(out: Path) -> dict[str, str]:
    result = subprocess.run([*PLATOON, "build", "--out", str(out)], capture_output=True, text=True, cwd=REPO,
                            env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"}, check=True)
    return {Path(line.split()[0]).stem: line for line in result.stdout.splitlines() if line.strip()}


def test_build_writes_every_fmu_then_reuses_them_and_repairs_a_damaged_one(tmp_path):
    first = _build(tmp_path)
    assert set(first) == {"Vehicle", "VirtualTarget", "LiveVehicle"}
    assert all(line.endswith("(built)") for line in first.values())
    for name in first:
        assert fmu_guid(tmp_path / f"{name}.fmu") == expected_guid(name)
        assert expected_guid(name) in first[name]
    second = _build(tmp_path)
    assert all(line.endswith("(up to date)") for line in second.values())
    (tmp_path / "Vehicle.fmu").write_bytes(b"not a zip")
    third = _build(tmp_path)
    assert third["Vehicle"].endswith("(built)") and third["VirtualTarget"].endswith("(up to date)")
    assert third["LiveVehicle"].endswith("(up to date)")
    assert fmu_guid(tmp_path / "Vehicle.fmu") == expected_guid("Vehicle")
    assert not list(tmp_path.glob("*.partial"))
