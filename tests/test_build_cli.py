"""`platoon build`: builds once, then only when an FMU is missing, stale or damaged."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from fmus.builders import PYTHONFMU, fmu_guid

REPO = Path(__file__).resolve().parents[1]
# `platoon` from this checkout (the console script may belong to another install of the package)
PLATOON = [sys.executable, "-c", "import sys; sys.argv[0] = 'platoon'; from orchestrator.cli import main; main()"]


def _build(out: Path) -> dict[str, str]:
    """platoon build --out OUT; each printed line by its FMU's path under OUT without .fmu."""
    result = subprocess.run([*PLATOON, "build", "--out", str(out)], capture_output=True, text=True, cwd=REPO,
                            env={"COLUMNS": "200", "PATH": "/usr/bin:/bin"}, check=True)
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    return {Path(line.split()[0]).relative_to(out).with_suffix("").as_posix(): line for line in lines}


def test_build_writes_every_fmu_then_reuses_them_and_repairs_a_damaged_one(tmp_path):
    from fmus.builders import NATIVE_FMI2, NATIVE_FMI3

    first = _build(tmp_path)
    assert set(first) == {"Vehicle", "VirtualTarget", "Link", "LiveVehicle", "RemoteVehicle", "native/Vehicle", "native/VirtualTarget",
                          "native/Link", "fmi3/Vehicle", "fmi3/VirtualTarget", "fmi3/Link"}
    assert all(line.endswith(("(built)", "(built, native)", "(built, native FMI 3.0)")) for line in first.values())
    for name in ("Vehicle", "VirtualTarget", "LiveVehicle", "RemoteVehicle"):
        assert fmu_guid(tmp_path / f"{name}.fmu") == PYTHONFMU.expected_guid(name)
        assert PYTHONFMU.expected_guid(name) in first[name]
    for name in ("Vehicle", "VirtualTarget"):
        assert fmu_guid(tmp_path / "native" / f"{name}.fmu") == NATIVE_FMI2.expected_guid(name) != PYTHONFMU.expected_guid(name)
        assert NATIVE_FMI2.expected_guid(name) in first[f"native/{name}"]
        assert fmu_guid(tmp_path / "fmi3" / f"{name}.fmu") == NATIVE_FMI3.expected_guid(name) != NATIVE_FMI2.expected_guid(name)
        assert NATIVE_FMI3.expected_guid(name) in first[f"fmi3/{name}"]
    second = _build(tmp_path)
    assert all(line.endswith(("(up to date)", "(up to date, native)", "(up to date, native FMI 3.0)"))
               for line in second.values())
    (tmp_path / "Vehicle.fmu").write_bytes(b"not a zip")
    (tmp_path / "native" / "VirtualTarget.fmu").write_bytes(b"not a zip")
    (tmp_path / "fmi3" / "Vehicle.fmu").write_bytes(b"not a zip")
    third = _build(tmp_path)
    assert third["Vehicle"].endswith("(built)") and third["VirtualTarget"].endswith("(up to date)")
    assert third["LiveVehicle"].endswith("(up to date)")
    assert third["native/VirtualTarget"].endswith("(built, native)")
    assert third["native/Vehicle"].endswith("(up to date, native)")
    assert third["fmi3/Vehicle"].endswith("(built, native FMI 3.0)")
    assert third["fmi3/VirtualTarget"].endswith("(up to date, native FMI 3.0)")
    assert fmu_guid(tmp_path / "Vehicle.fmu") == PYTHONFMU.expected_guid("Vehicle")
    assert not list(tmp_path.glob("**/*.partial"))


_RUN_THEN_BUILD = """
import sys, zipfile
from pathlib import Path
{first}
import fmpy
fmpy.simulate_fmu(sys.argv[1], stop_time=0.05)  # our FMU runs in this interpreter
from fmus.builders import PYTHONFMU, BuildError
out = Path(sys.argv[2])
try:
    built = PYTHONFMU.build(out, force=True)
except BuildError as error:
    print("refused:", error)
for fmu in sorted(out.glob("*.fmu")):
    names = zipfile.ZipFile(fmu).namelist()
    print(fmu.name, any(n.startswith("binaries/") and n.endswith(".so") for n in names))
"""


def _run_then_build(fmu_dir: Path, out: Path, first: str) -> list[str]:
    script = _RUN_THEN_BUILD.format(first=first)
    result = subprocess.run([sys.executable, "-c", script, str(fmu_dir / "Vehicle.fmu"), str(out)],
                            capture_output=True, text=True, cwd=out.parent, timeout=300)
    assert result.returncode == 0, result.stderr
    return result.stdout.splitlines()


def test_a_build_after_an_fmu_ran_in_process_writes_fmus_with_their_binaries(fmu_dir, tmp_path):
    """The usual order (the build module imported first, as `platoon` and the tests do)."""
    lines = _run_then_build(fmu_dir, tmp_path / "out", "import fmus.builders")
    assert sorted(lines) == ["Vehicle.fmu True", "VirtualTarget.fmu True"], lines


def test_a_build_never_writes_an_fmu_without_binaries(fmu_dir, tmp_path):
    """pythonfmu first imported by an FMU (from its resources, a copy without binaries): the build
    refuses with the reason instead of writing FMUs that no host can load."""
    lines = _run_then_build(fmu_dir, tmp_path / "out", "")
    assert lines and lines[0].startswith("refused: pythonfmu was imported from"), lines
    assert "platoon build" in lines[0]
    assert lines[1:] == [], lines  # nothing written


def test_a_cross_compile_past_its_time_is_one_line_naming_the_target_and_writes_no_native_fmu(tmp_path):
    """`platoon build --all-platforms` on a cold Zig cache (an empty ZIG_GLOBAL_CACHE_DIR) with a compile
    limit of 4 s (PLATOON_COMPILE_TIMEOUT): Zig is still building a target's C runtime when the limit comes
    (Windows' takes minutes of CPU on any machine; Linux's may be done within the 4 s). The user gets a line while it waits, then one error line
    naming the target, what Zig was doing and what to do, exit 1, no traceback; no native FMU and no partial
    file is left, and no compiler of that build is still running."""
    import os

    import psutil
    import pytest

    pytest.importorskip("ziglang")
    from fmus.builders.toolchain import ZIG_TARGETS

    cache, out = tmp_path / "zig-cache", tmp_path / "out"
    env = {**os.environ, "ZIG_GLOBAL_CACHE_DIR": str(cache), "PLATOON_COMPILE_TIMEOUT": "4",
           "PLATOON_PROGRESS_SECONDS": "1", "COLUMNS": "200"}
    result = subprocess.run([*PLATOON, "build", "--all-platforms", "--out", str(out)], capture_output=True, text=True,
                            cwd=REPO, env=env, timeout=300)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    # the first target whose C runtime takes Zig longer than 4 s: Linux's glibc stubs may be built within them on a
    # quiet machine (a clean-clone CI run here did), Windows' C runtime takes minutes
    late = [target for target in ZIG_TARGETS.values()
            if lines[-1].startswith(f"error: build --all-platforms: Zig's compiler for {target} did not finish within "
                                    f"4 s: Zig was most likely still building its C runtime for {target}")]
    assert len(late) == 1, lines[-1]
    assert "Run the same command again" in lines[-1] and "python -m fmus.builders.zig_cache" in lines[-1]
    assert any(line.startswith(f"zig: building its C runtime for {late[0]}, ") for line in lines), lines
    assert not list(out.glob("native/*")) and not list(out.glob("fmi3/*")) and not list(out.rglob("*partial*"))
    assert len(list(out.glob("*.fmu"))) == 5  # the pythonfmu FMUs, built before: whole

    def ours() -> list[psutil.Process]:  # a compiler of this build, alive (its environment names the cache)
        alive = []
        for process in psutil.process_iter():
            try:
                if process.status() != psutil.STATUS_ZOMBIE and process.environ().get("ZIG_GLOBAL_CACHE_DIR") == str(cache):
                    alive.append(process)
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
        return alive

    assert not ours()
