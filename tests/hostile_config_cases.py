"""The hostile config and command-line cases, run as a user would; prints one line per case.

    python tests/hostile_config_cases.py          # from the repository root; exit 1 if any is left

Each case must end with exit 2 and exactly one ``error:`` line on stderr, no traceback, within 60 s
(a hang counts as left). tests/test_hostile_config.py asserts the same and more (messages, the
accepted cases, the SIGKILL sweep, the FMU rebuild); this is the quick survey of what is left.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = str(REPO / "configs" / "paper" / "platoon.toml")
SHORT = ["--set", "simulation.stop_time=1.0"]
PULSE = 'disturbance=[{vehicle=2, kind="speed", start=1.0, duration=1.0, value=1.0}]'  # analyze then runs it

SETS = [  # run PAPER --set X: every one must be refused
    "simulation.stop_time=inf", "simulation.stop_time=nan", "simulation.step=inf", "simulation.max_substep=nan",
    "platoon.k_v=inf", "platoon.d_star=nan", "platoon.speed=inf", "path.radius=inf", "path.center=[nan, 0.0]",
    "path.heading=inf", "initial.radial_offset=inf", "initial.heading_error=nan", "initial.speed_factor=inf",
    "m3pi.track=nan", "vehicles.1.k_v=inf", "vehicles.1.initial={x=inf, y=0.0, heading=0.0, speed=1.0}",
    'disturbance=[{vehicle=1, kind="speed", start=nan, duration=1.0, value=1.0}]',
    'disturbance=[{vehicle=1, kind="speed", start=1.0, duration=1.0, value=1e308}]', "hil.pose_timeout=nan",
    "simulation.stop_time=1e12", "simulation.step=1e-300", "simulation.max_substep=1e-12",
    "platoon.d_star=100.0", 'name="a\\u0000b"', 'name="../../x"', 'description="\\u001b[2J"',
    "platoon.count=3 x=1", "platoon.count=3\nx=1", "platoon.count=3 # note",
]


def cases(folder: Path) -> list[tuple[str, list[str | bytes]]]:
    latin = folder / "latin1.toml"
    latin.write_bytes('description = "Düsseldorf"\n'.encode("latin-1"))
    latin_sweep = folder / "sweep-latin1.toml"
    latin_sweep.write_bytes(f'base = "{PAPER}"\n# Düsseldorf\n[grid]\n"platoon.count" = [1, 2]\n'.encode("latin-1"))
    found = [(f"run --set {value!r}", ["run", PAPER, *SHORT, "--set", value, "--out", str(folder / "x.mcap")])
             for value in SETS]
    found += [
        ("run non-UTF-8 config", ["run", str(latin)]),
        ("analyze non-UTF-8 config", ["analyze", str(latin)]),
        ("m3pi-emulator non-UTF-8 config", ["m3pi-emulator", "--config", str(latin)]),
        ("export-ssp non-UTF-8 config", ["export-ssp", str(latin), "--out", str(folder / "x.ssp")]),
        ("sweep non-UTF-8 sweep file", ["sweep", str(latin_sweep), "--out", str(folder / "sweep")]),
        ("run --set description=<not UTF-8>", ["run", PAPER, *SHORT, "--set", b"description=\xff"]),
        ("run --trace-every 101 (100 steps)", ["run", PAPER, *SHORT, "--trace-every", "101"]),
        ("run --trace-every 1e29", ["run", PAPER, *SHORT, "--trace-every", "1" + "0" * 29]),
        ("analyze --set platoon.d_star=100.0", ["analyze", PAPER, "--set", "platoon.d_star=100.0"]),
        ("analyze --set platoon.count=1000", ["analyze", PAPER, "--set", "platoon.count=1000"]),
        ("run --set platoon.count=10000 (for the default 100 s)", ["run", PAPER, "--set", "platoon.count=10000"]),
        ("analyze --set simulation.stop_time=1e12, a disturbance", ["analyze", PAPER, "--set", "simulation.stop_time=1e12",
                                                                    "--set", PULSE]),
        ("m3pi-emulator --set platoon.k_v=inf", ["m3pi-emulator", "--config", PAPER, "--set", "platoon.k_v=inf"]),
    ]
    return found


def outcome(argv: list[str | bytes], cwd: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NO_COLOR": "1", "TERM": "dumb", "COLUMNS": "200"}
    try:
        result = subprocess.run([str(PLATOON), *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return "LEFT: still running after 60 s"
    lines = result.stderr.strip().splitlines()
    if "Traceback" in result.stderr:
        return f"LEFT: traceback, exit {result.returncode}: {lines[-1] if lines else ''}"
    if result.returncode != 2 or len(lines) != 1 or not lines[0].startswith("error: "):
        return f"LEFT: exit {result.returncode}, {len(lines)} stderr line(s): {lines[:1]}"
    return f"ok: {lines[0]}"


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="hostile-config-") as scratch:
        folder = Path(scratch)
        results = [(label, outcome(argv, folder)) for label, argv in cases(folder)]
    for label, text in results:
        print(f"{label:60s} {text}")
    left = sum(text.startswith("LEFT") for _, text in results)
    print(f"{len(results)} cases, {left} left")
    return 1 if left else 0


if __name__ == "__main__":
    sys.exit(main())
