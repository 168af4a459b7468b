"""Remote vehicles in other tools: ``platoon export-ssp`` of a config with remote vehicles puts the RemoteVehicle
FMU (a client of ``platoon serve``) in their place, and libcosim and FMPy step it as any FMU.

Real ``platoon serve`` processes on 127.0.0.1, real libcosim (libcosimpy) and FMPy in processes of their own.
What a user relies on: the other tool's run ends with our local run's numbers (<= 1e-9 m); its process exits
at once after the run whether it frees the FMUs or never does, and the servers are free for the next run
either way; a server killed mid-run fails the importer's step within the step timeout, naming the vehicle and
the server, never a hang.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import zipfile
from contextlib import ExitStack
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
from lxml import etree

from tests.conftest import free_port, shared_build
from tests.test_hil import wait_for
from tests.test_live_fmu import HOST, JOINED_WITHIN, RUNNER, _lines_until_exit
from tests.test_remote import server
from tests.test_ssp import NS, platoon, schema, typed
from orchestrator.trace import load

pytest.importorskip("libcosimpy")

REPO = Path(__file__).resolve().parents[1]
REMOTE = REPO / "configs" / "remote" / "platoon.toml"
PAPER = REPO / "configs" / "paper" / "platoon.toml"
STOP = 10.0  # s of the platoon: 1000 steps, each vehicle a round trip per step
EXITED_WITHIN = 2.0  # s from a host's run's end to its exit (issue 56; measured 0.1-0.25 s)
VEHICLES = ("vehicle1", "vehicle2", "vehicle3", "vehicle4")


def connect_sets(ports: dict[int, int]) -> list[str]:
    return [arg for vehicle, port in ports.items()
            for arg in ("--set", f'vehicles.{vehicle}.connect=["tcp/127.0.0.1:{port}"]')]


def export(out: Path, ports: dict[int, int], *sets: str, config: Path = REMOTE) -> str:
    """``platoon export-ssp`` of the all-remote paper platoon, its servers at ``ports``; the command's output."""
    extra = [arg for assignment in sets for arg in ("--set", assignment)]
    result = platoon("export-ssp", str(config), "--out", str(out), *connect_sets(ports), *extra)
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.fixture(scope="module")
def servers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict[int, int], Path]]:
    """Four native ``platoon serve Vehicle``, one per vehicle, shared by this module's runs (each run must
    leave them free: the next one is refused otherwise)."""
    folder = tmp_path_factory.mktemp("servers")
    ports = {vehicle: free_port() for vehicle in (1, 2, 3, 4)}
    with ExitStack() as stack:
        for vehicle, port in ports.items():
            stack.enter_context(server(f"vehicle{vehicle}", port, "native", folder))
        yield ports, folder


@pytest.fixture(scope="module")
def exported(servers: tuple[dict[int, int], Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """The package (``STOP`` s), our local Jacobi run of the same platoon, and what export-ssp printed."""
    ports, _ = servers
    folder = tmp_path_factory.mktemp("remote-ssp")
    package, trace = folder / "remote.ssp", folder / "local.mcap"
    said = export(package, ports, f"simulation.stop_time={STOP}")
    ours = platoon("run", str(PAPER), "--set", f"simulation.stop_time={STOP}", "--set", "simulation.master=jacobi",
                   "--out", str(trace), "-q")
    assert ours.returncode == 0, ours.stderr
    return package, trace, said


def freed(folder: Path, runs: int) -> bool:
    """Every server's log says its instance was freed by its run ``runs`` times."""
    return all((folder / f"serve-{name}.log").read_text().count(f"{name} freed by its run") >= runs for name in VEHICLES)


def test_export_puts_the_client_fmu_where_each_remote_vehicle_is(exported, servers) -> None:
    """The package is valid SSP 1.0; each remote vehicle is RemoteVehicle.fmu with the scenario's parameters and
    the ``remote.*`` ones that reach its server; the command says the servers must run."""
    package, _, said = exported
    ports, _ = servers
    assert "remote: vehicle1, vehicle2, vehicle3, vehicle4 (RemoteVehicle.fmu: start their platoon serve first)" in said
    with zipfile.ZipFile(package) as archive:
        ssd = etree.fromstring(archive.read("SystemStructure.ssd"))
        assert schema("SystemStructureDescription.xsd").validate(ssd)
        sources = {c.get("name"): c.get("source") for c in ssd.findall("ssd:System/ssd:Elements/ssd:Component", NS)}
        assert sources == {"target": "resources/VirtualTarget.fmu",
                           **{name: "resources/RemoteVehicle.fmu" for name in VEHICLES}}
        assert "resources/Vehicle.fmu" not in archive.namelist()  # nothing runs a vehicle locally
        ssv = etree.fromstring(archive.read("resources/vehicle2.ssv"))
        assert schema("SystemStructureParameterValues.xsd").validate(ssv)
    values = {p.get("name"): typed(p[0]) for p in ssv.findall("ssv:Parameters/ssv:Parameter", NS)}
    assert {k: v for k, v in values.items() if k.startswith("remote.")} == {
        "remote.server": "vehicle2", "remote.prefix": "platoon", "remote.connect": f"tcp/127.0.0.1:{ports[2]}",
        "remote.listen": "", "remote.zenoh_config": "", "remote.step_timeout": 2.0, "remote.connect_timeout": 120.0,
        "remote.allow_insecure": False}
    assert values["d_star"] == 75.0 and values["is_last"] is False  # the scenario's, as platoon run sends them


def _worst(final: dict[str, tuple[float, float]], trace: Path) -> float:
    loaded = load(trace)
    assert set(final) == {"target", *VEHICLES}
    worst = 0.0
    for name, (x, y) in final.items():
        channel = loaded.component(name)
        assert channel["t"][-1] == STOP
        worst = max(worst, float(np.hypot(x - channel["x"][-1], y - channel["y"][-1])))
    return worst


def test_libcosim_runs_the_remote_platoon_to_our_numbers(exported, servers, tmp_path: Path) -> None:
    """libcosim, with this project's packages taken from its import machinery (the client FMU runs on the code
    in its resources and on zenoh): final positions within 1e-9 m of our local run; every server freed."""
    package, trace, _ = exported
    _, folder = servers
    before = min((folder / f"serve-{name}.log").read_text().count("freed by its run") for name in VEHICLES)
    run = subprocess.run([sys.executable, str(RUNNER), str(package), "--isolate"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "steps completed" in run.stdout and f"end {STOP}" in run.stdout, run.stdout[-3000:]
    final = {line.split()[0]: (float(line.split()[1]), float(line.split()[2]))
             for line in run.stdout.splitlines() if line.startswith(("target ", "vehicle"))}
    modules = dict(line.split()[1:] for line in run.stdout.splitlines() if line.startswith("module "))
    assert set(modules) == {"fmus", "bridge"} and all("/resources/" in path for path in modules.values()), modules
    worst = _worst(final, trace)
    print(f"\n[remote vehicles in libcosim vs platoon run, jacobi] largest final position difference {worst:.3e} m")
    assert worst <= 1e-9
    wait_for(lambda: freed(folder, before + 1), "every server freed by the libcosim run")


FMPY_SCRIPT = """
import sys
from orchestrator.interop.fmpy_ssp import simulate_ssp

result = simulate_ssp(sys.argv[1], stop_time=float(sys.argv[2]), step_size=0.01)
for name in ("target", "vehicle1", "vehicle2", "vehicle3", "vehicle4"):
    print(name, repr(float(result[name + ".x"][-1])), repr(float(result[name + ".y"][-1])))
print("rows", len(result))
"""


def test_fmpy_runs_the_remote_platoon_to_our_numbers(exported, servers, tmp_path: Path) -> None:
    """FMPy's SSP runner (with orchestrator/interop/fmpy_ssp.py, docs/fmus.md "In FMPy"), in a process of its own:
    final positions within 1e-9 m of our local run; every server freed."""
    package, trace, _ = exported
    _, folder = servers
    before = min((folder / f"serve-{name}.log").read_text().count("freed by its run") for name in VEHICLES)
    run = subprocess.run([sys.executable, "-c", FMPY_SCRIPT, str(package), str(STOP)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and f"rows {round(STOP / 0.01)}" in run.stdout, run.stdout[-2000:] + run.stderr[-2000:]
    final = {line.split()[0]: (float(line.split()[1]), float(line.split()[2]))
             for line in run.stdout.splitlines() if line.startswith(("target ", "vehicle"))}
    worst = _worst(final, trace)
    print(f"\n[remote vehicles in FMPy vs platoon run, jacobi] largest final position difference {worst:.3e} m")
    assert worst <= 1e-9
    wait_for(lambda: freed(folder, before + 1), "every server freed by the FMPy run")


@pytest.fixture(scope="module")
def short(servers: tuple[dict[int, int], Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package, 2 s (200 steps), for the hosts that free the FMUs or never do."""
    ports, _ = servers
    package = tmp_path_factory.mktemp("remote-2s") / "remote2.ssp"
    export(package, ports, "simulation.stop_time=2")
    return package


@pytest.mark.parametrize("mode", ["free", "keep"])
@pytest.mark.parametrize("host", ["libcosim", "fmpy"])
def test_a_host_that_frees_the_client_fmu_or_never_does_exits_at_once_and_frees_the_servers(
        host: str, mode: str, short: Path, servers, tmp_path: Path) -> None:
    """A user's script (tests/live_fmu_host.py) runs the package and ends the ordinary way. Freeing the FMUs
    frees the served instances at once; a host that keeps them (libcosim's execution collected in the teardown,
    FMPy's instances never freed) frees them as its interpreter begins to exit. Either way its threads are
    joined within 2 s of the run's end, and every server is free for the next run."""
    _, folder = servers
    before = min((folder / f"serve-{name}.log").read_text().count("freed by its run") for name in VEHICLES)
    run = subprocess.Popen([sys.executable, str(HOST), str(short), host, mode], cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines, moments = _lines_until_exit(run)
    out = "\n".join(lines)
    assert run.returncode == 0 and "steps completed" in out, out
    assert "Fatal" not in out and "Traceback" not in out, out
    wait_for(lambda: freed(folder, before + 1), lambda: f"every server freed ({host}, {mode}): {out}")
    for name in VEHICLES:
        assert f"{name} freed by its run after 200 steps" in (folder / f"serve-{name}.log").read_text()
    joined, exited = moments["joined"] - moments["end"], moments["exit"] - moments["end"]
    print(f"\n[remote FMU host exit] {host} ({mode}): threads joined {joined:.2f} s, process exited {exited:.2f} s "
          "after the run's end")
    assert joined <= JOINED_WITHIN, f"{host} ({mode}): its threads joined {joined:.2f} s after the run's end: {out}"
    assert exited <= EXITED_WITHIN, f"{host} ({mode}): it exited {exited:.2f} s after the run's end: {out}"


KILL_SCRIPTS = {"libcosim": """
import sys
from libcosimpy.CosimExecution import CosimExecution
from libcosimpy.CosimLogging import CosimLogLevel, log_output_level

log_output_level(CosimLogLevel.WARNING)  # FMU errors are logged at error level
execution = CosimExecution.from_ssp_file(sys.argv[1])
while execution.step(10):
    print("at", execution.status().current_time / 1e9, flush=True)
print("failed at", execution.status().current_time / 1e9, flush=True)
""", "fmpy": """
import sys
import fmpy.ssp.simulation as runner
from orchestrator.interop.fmpy_ssp import simulate_ssp

step = runner.do_step
def do_step(component, time, h):
    step(component, time, h)
    if component.name == "target" and round(time / h) % 10 == 0:
        print("at", time, flush=True)
runner.do_step = do_step
try:
    simulate_ssp(sys.argv[1], stop_time=5000.0, step_size=0.01)
except Exception as error:
    print("failed at", error, flush=True)
"""}


@pytest.mark.parametrize("signal_", [signal.SIGKILL, signal.SIGSTOP], ids=["killed", "frozen"])
@pytest.mark.parametrize("host", ["libcosim", "fmpy"])
def test_a_killed_or_frozen_server_fails_the_importers_step_within_its_timeout(host: str, signal_: int,
                                                                               tmp_path: Path) -> None:
    """kill -9 of vehicle 2's server while libcosim or FMPy steps the package (its connection drops: Zenoh ends the query
    at once), or SIGSTOP (a partition, a server too slow: the connection stays, no reply comes): within
    ``remote.step_timeout`` (1 s) the step fails (0.5 s allowed for a loaded machine), libcosim's log naming vehicle 2, its server's key and where
    it was reached (FMPy's runner prints it with orchestrator/interop/fmpy_ssp.py); the host exits; the other
    server is freed."""
    ports = {1: free_port(), 2: free_port()}
    package = tmp_path / "two.ssp"
    with server("vehicle1", ports[1], "native", tmp_path), server("vehicle2", ports[2], "native", tmp_path) as victim:
        export(package, ports, "platoon.count=2", "simulation.stop_time=5000", "remote.step_timeout=1.0",
               "vehicles.1.endpoint=remote", "vehicles.2.endpoint=remote", config=PAPER)
        run = subprocess.Popen([sys.executable, "-c", KILL_SCRIPTS[host], str(package)], cwd=tmp_path,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(run.stdout))  # type: ignore[arg-type]
        reader.start()
        try:
            wait_for(lambda: any(line.startswith("at 1.") for line in lines), f"{host} steps the package", run)
            os.kill(victim.pid, signal_)
            killed = time.monotonic()
            wait_for(lambda: any(line.startswith("failed at") for line in lines) or run.poll() is not None,
                     "the step fails", seconds=30)
            took = time.monotonic() - killed
            run.wait(30)
        finally:
            if run.poll() is None:
                run.kill()
            reader.join()
            os.kill(victim.pid, signal.SIGCONT)  # a frozen server ends as any other
        out = "".join(lines)
        wait_for(lambda: "vehicle1 freed by its run" in (tmp_path / "serve-vehicle1.log").read_text(),
                 lambda: f"vehicle 1's server freed: {(tmp_path / 'serve-vehicle1.log').read_text()}")
    print(f"\n[remote FMU, server {signal.Signals(signal_).name}] {host}'s step failed {took:.2f} s after the signal "
          f"(step timeout 1 s): {next(line for line in lines if 'vehicle2 failed' in line).strip()}")
    assert run.returncode == 0 and "failed at" in out, out
    assert took <= 1.0 + 0.5, f"the step failed {took:.2f} s after the signal (timeout 1 s)"  # measured 0.02, 1.01 s
    assert (f"vehicle2 failed at t = " in out and "no reply to step from t = " in out
            and f"(server platoon/fmu/vehicle2 at tcp/127.0.0.1:{ports[2]})" in out), out


NO_SERVER_SCRIPTS = {"libcosim": [str(RUNNER)], "fmpy": ["-c", KILL_SCRIPTS["fmpy"]]}


@pytest.mark.parametrize("host", ["libcosim", "fmpy"])
def test_no_server_fails_the_run_at_its_start_naming_the_vehicle_and_the_server(host: str, tmp_path: Path) -> None:
    """Nobody serves vehicle 1 (``remote.connect_timeout`` 1 s): the importer's run fails at its start, its log
    saying which vehicle found no server at which key and endpoint; it exits (no hang, no abort)."""
    port = free_port()
    package = tmp_path / "none.ssp"
    export(package, {1: port}, "platoon.count=1", "vehicles.1.endpoint=remote", "remote.connect_timeout=1.0",
           "simulation.stop_time=5", config=PAPER)
    started = time.monotonic()
    run = subprocess.run([sys.executable, *NO_SERVER_SCRIPTS[host], str(package)], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    took = time.monotonic() - started
    out = run.stdout + run.stderr
    print(f"\n[remote FMU, no server] {host} failed {took:.2f} s after its start (connect timeout 1 s)")
    assert ("steps failed" in out and "end 0.0" in out) if host == "libcosim" else "failed at" in out, out
    assert (f"vehicle1 failed at t = 0 s: no server answered within 1 s (is `platoon serve` running there?) "
            f"(server platoon/fmu/vehicle1 at tcp/127.0.0.1:{port})") in out, out


TWIN_SCRIPT = """
import sys
from fmpy import extract, read_model_description
from fmpy.fmi2 import FMU2Slave

def instance(path, name, parameters, early):
    description = read_model_description(path)
    refs = {v.name: (v.valueReference, v.type) for v in description.modelVariables}
    fmu = FMU2Slave(guid=description.guid, unzipDirectory=extract(path), instanceName=name,
                    modelIdentifier=description.coSimulation.modelIdentifier)
    fmu.instantiate(loggingOn=True)
    fmu.setupExperiment(startTime=0.0)
    def set_(values):
        for key, value in values.items():
            ref, kind = refs[key]
            {"Real": fmu.setReal, "String": fmu.setString, "Boolean": fmu.setBoolean}[kind]([ref], [value])
    set_(early)
    fmu.enterInitializationMode()
    outputs = [v.valueReference for v in description.modelVariables if v.causality == "output"]
    fmu.getReal(outputs)  # read in initialization (libcosim does): opens the served instance
    set_(parameters)  # set after that read: the served instance must get them too
    fmu.exitInitializationMode()
    for k in range(3):
        fmu.doStep(k * 0.01, 0.01)
    values = fmu.getReal(outputs)
    fmu.terminate()
    fmu.freeInstance()
    return values

parameters = {"d_star": 80.0, "law": "regular", "is_last": True, "initial.x": 3.0}
local = instance(sys.argv[1], "vehicle1", parameters, {})
remote = instance(sys.argv[2], "vehicle1", parameters, {"remote.connect": sys.argv[3], "d_star": 70.0})
print("equal" if local == remote else f"differ {local} {remote}")
"""


def test_parameters_set_after_the_instance_opened_reopen_it_and_reach_the_server(servers, fmu_dir: Path,
                                                                                 tmp_path: Path) -> None:
    """An importer that reads outputs in initialization mode (the served instance opens then) and sets parameters
    after: the instance is opened again with them (freed, then opened), and three steps give exactly what the
    local Vehicle FMU gives with those parameters, every output bit for bit."""
    from fmus.builders import PYTHONFMU, REMOTE_FMU

    with shared_build():
        PYTHONFMU.build(fmu_dir, names=(REMOTE_FMU,))
    ports, folder = servers
    log = folder / "serve-vehicle1.log"
    opened, before = log.read_text().count("opened vehicle1"), log.read_text().count("freed by its run")
    run = subprocess.run([sys.executable, "-c", TWIN_SCRIPT, str(fmu_dir / "Vehicle.fmu"),
                          str(fmu_dir / "RemoteVehicle.fmu"), f"tcp/127.0.0.1:{ports[1]}"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip().endswith("equal"), run.stdout[-2000:] + run.stderr[-2000:]
    wait_for(lambda: log.read_text().count("freed by its run") >= before + 2, lambda: log.read_text())
    text = log.read_text()
    assert text.count("opened vehicle1") == opened + 2 and "vehicle1 freed by its run after 0 steps" in text, text
    assert "vehicle1 freed by its run after 3 steps" in text, text
