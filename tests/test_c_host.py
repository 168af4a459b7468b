"""The Vehicle FMU runs in a host that is not Python, and gives FMPy's trajectory there.

``tests/c_host/minimal_host.c`` is a plain C FMI 2.0 co-simulation importer (dlopen, no FMI
library). It is compiled with ``cc``, run as a real subprocess over the default experiment, and its
CSV output is compared with ``fmpy.simulate_fmu`` on the same FMU (run in a fresh interpreter, so
the model code it executes is the copy bundled in the FMU, as in the C host).

The environment given to the C host is built from scratch (nothing inherited, no VIRTUAL_ENV) and is
exactly what docs/fmus.md tells users a non-Python host needs:

    LD_PRELOAD=<LIBDIR>/<INSTSONAME>    the matching libpython, e.g. .../lib/libpython3.11.so.1.0
    PYTHONHOME=<sys.base_prefix>        that Python's installation, never a venv

The failure tests pin down why: without libpython in the process the binary cannot even be loaded
(pythonfmu's binary leaves the Python C API symbols undefined and does not name libpython as a
dependency, so the library path alone does not help), and a venv as PYTHONHOME has no stdlib.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path
from xml.etree import ElementTree

import pytest

from fmus.builders import PYTHONFMU

HOST_SOURCE = Path(__file__).resolve().parent / "c_host" / "minimal_host.c"
OUTPUTS = ("x", "y", "speed", "gap")
TOLERANCE = 1e-9
# Deliberately minimal and not inherited. /usr/bin may hold another python3: with PYTHONHOME set,
# that must not matter.
BASE_PATH = "/usr/bin:/bin"
TIMEOUT = 120


def _libpython() -> Path | None:
    """The shared libpython of the Python running the tests (the FMU must use the same one)."""
    if not sysconfig.get_config_var("Py_ENABLE_SHARED"):
        return None
    libdir = sysconfig.get_config_var("LIBDIR")
    soname = sysconfig.get_config_var("INSTSONAME") or sysconfig.get_config_var("LDLIBRARY")
    if not libdir or not soname:
        return None
    path = Path(libdir) / soname
    return path if path.is_file() else None


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def host_environment(libpython: Path) -> dict[str, str]:
    """Everything a non-Python host process needs to run our FMUs, and nothing else."""
    return {"PATH": BASE_PATH, "LD_PRELOAD": str(libpython), "PYTHONHOME": sys.base_prefix}


@pytest.fixture(scope="module")
def vehicle(tmp_path_factory):
    """The built Vehicle.fmu, its unzipped folder and what its model description says."""
    if sys.platform != "linux":
        pytest.skip("the C host loads binaries/linux64; this test runs on Linux only")
    root = tmp_path_factory.mktemp("c_host")
    built = {fmu.name: fmu for fmu in PYTHONFMU.build(out_dir=root / "fmus", force=True)}
    fmu = built["Vehicle"].path
    unzipped = root / "Vehicle"
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(unzipped)
    md = ElementTree.parse(unzipped / "modelDescription.xml").getroot()
    refs = {v.get("name"): int(v.get("valueReference")) for v in md.iter("ScalarVariable")}
    experiment = md.find("DefaultExperiment")
    return {
        "fmu": fmu,
        "dir": unzipped,
        "guid": md.get("guid"),
        "vrs": [refs[name] for name in OUTPUTS],
        "start": float(experiment.get("startTime")),
        "stop": float(experiment.get("stopTime")),
        "step": float(experiment.get("stepSize")),
    }


@pytest.fixture(scope="module")
def host(tmp_path_factory):
    """The compiled C host."""
    cc = _compiler()
    if cc is None:
        pytest.skip("no C compiler found ($CC, cc, gcc or clang); cannot build tests/c_host/minimal_host.c")
    exe = tmp_path_factory.mktemp("c_host_bin") / "minimal_host"
    result = subprocess.run(
        [cc, "-std=c99", "-Wall", "-Wextra", "-O2", "-o", str(exe), str(HOST_SOURCE), "-ldl"],
        capture_output=True, text=True, timeout=TIMEOUT,
    )
    assert result.returncode == 0, f"compiling the C host failed:\n{result.stderr}"
    return exe


@pytest.fixture(scope="module")
def libpython():
    path = _libpython()
    if path is None:
        pytest.skip("this Python has no shared libpython (built without --enable-shared); a C host cannot embed it")
    return path


def run_host(host: Path, vehicle: dict, steps: int, env: dict[str, str]) -> subprocess.CompletedProcess:
    args = [str(host), str(vehicle["dir"]), vehicle["guid"], str(steps), repr(vehicle["step"])]
    args += [str(vr) for vr in vehicle["vrs"]]
    return subprocess.run(args, capture_output=True, text=True, env=env, timeout=TIMEOUT)


def fmpy_trajectory(fmu: Path, step: float, stop: float) -> list[list[float]]:
    """FMPy's result for the FMU with default start values, from a fresh interpreter."""
    script = (
        "import json, sys, fmpy\n"
        "r = fmpy.simulate_fmu(sys.argv[1], output_interval=float(sys.argv[2]), stop_time=float(sys.argv[3]),"
        f" output={list(OUTPUTS)!r})\n"
        f"print(json.dumps([[float(row[n]) for n in {('time',) + OUTPUTS!r}] for row in r]))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, str(fmu), repr(step), repr(stop)],
        capture_output=True, text=True, timeout=TIMEOUT, cwd=fmu.parent,
    )
    assert result.returncode == 0, f"FMPy failed:\n{result.stderr}"
    return json.loads(result.stdout)


def test_c_host_reproduces_fmpy_over_the_default_experiment(host, vehicle, libpython):
    assert vehicle["start"] == 0.0  # the C host starts at t = 0
    steps = round((vehicle["stop"] - vehicle["start"]) / vehicle["step"])
    assert steps == 6000

    result = run_host(host, vehicle, steps, host_environment(libpython))
    assert result.returncode == 0, f"C host failed ({result.returncode}):\n{result.stderr}"
    lines = result.stdout.splitlines()
    assert lines[0] == "t,x,y,speed,gap"
    c_rows = [[float(value) for value in line.split(",")] for line in lines[1:]]

    reference = fmpy_trajectory(vehicle["fmu"], vehicle["step"], vehicle["stop"])
    assert len(c_rows) == len(reference) == steps + 1
    worst = 0.0
    for c_row, f_row in zip(c_rows, reference):
        assert c_row[0] == pytest.approx(f_row[0], abs=1e-12)
        assert all(math.isfinite(value) for value in c_row)
        worst = max(worst, max(abs(a - b) for a, b in zip(c_row[1:], f_row[1:])))
    assert worst <= TOLERANCE, f"C host and FMPy differ by {worst:g}"
    assert c_rows[-1][0] == pytest.approx(vehicle["stop"])


@pytest.mark.parametrize(
    "case",
    ["no libpython", "libpython only on LD_LIBRARY_PATH"],
)
def test_c_host_cannot_load_the_fmu_without_libpython_in_the_process(host, vehicle, libpython, case):
    env = {"PATH": BASE_PATH, "PYTHONHOME": sys.base_prefix}
    if case == "libpython only on LD_LIBRARY_PATH":
        env["LD_LIBRARY_PATH"] = str(libpython.parent)
    result = run_host(host, vehicle, 1, env)
    assert result.returncode == 3, result.stderr  # dlopen failed
    assert "undefined symbol" in result.stderr
    assert result.stdout == ""


def test_c_host_fails_with_a_venv_as_pythonhome(host, vehicle, libpython):
    if sys.prefix == sys.base_prefix:
        pytest.skip("tests are not running in a venv")
    env = host_environment(libpython) | {"PYTHONHOME": sys.prefix}
    result = run_host(host, vehicle, 1, env)
    assert result.returncode != 0
    assert "No module named 'encodings'" in result.stderr


# --- the native (C) Vehicle FMU: no Python on the host at all -------------------------------------------


@pytest.fixture(scope="module")
def native_vehicle(native_fmu_dir, tmp_path_factory):
    """The native Vehicle.fmu (build/fmus/native), unzipped, with what its model description says."""
    if sys.platform != "linux":
        pytest.skip("the C host loads binaries/linux64; this test runs on Linux only")
    fmu = native_fmu_dir / "Vehicle.fmu"
    unzipped = tmp_path_factory.mktemp("c_host_native") / "Vehicle"
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(unzipped)
    md = ElementTree.parse(unzipped / "modelDescription.xml").getroot()
    refs = {v.get("name"): int(v.get("valueReference")) for v in md.iter("ScalarVariable")}
    experiment = md.find("DefaultExperiment")
    return {"fmu": fmu, "dir": unzipped, "guid": md.get("guid"), "vrs": [refs[name] for name in OUTPUTS],
            "start": float(experiment.get("startTime")), "stop": float(experiment.get("stopTime")),
            "step": float(experiment.get("stepSize"))}


def test_c_host_runs_the_native_fmu_in_an_empty_environment(host, native_vehicle, fmu_dir):
    """No LD_PRELOAD, no PYTHONHOME, no PATH: nothing at all in the environment. The C host's
    trajectory equals FMPy's for the same native FMU, and the pythonfmu FMU's (to 1e-9)."""
    steps = round((native_vehicle["stop"] - native_vehicle["start"]) / native_vehicle["step"])
    result = run_host(host, native_vehicle, steps, {})
    assert result.returncode == 0, f"C host failed ({result.returncode}):\n{result.stderr}"
    assert result.stderr == ""
    lines = result.stdout.splitlines()
    assert lines[0] == "t,x,y,speed,gap"
    c_rows = [[float(value) for value in line.split(",")] for line in lines[1:]]
    for reference in (fmpy_trajectory(native_vehicle["fmu"], native_vehicle["step"], native_vehicle["stop"]),
                      fmpy_trajectory(fmu_dir / "Vehicle.fmu", native_vehicle["step"], native_vehicle["stop"])):
        assert len(c_rows) == len(reference) == steps + 1
        worst = max(abs(a - b) for c_row, f_row in zip(c_rows, reference) for a, b in zip(c_row, f_row))
        assert worst <= TOLERANCE, f"C host and FMPy differ by {worst:g}"
