"""Remote vehicles whose servers step FMI 3.0 FMUs: `platoon serve` of our native FMI 3.0 Vehicle on 127.0.0.1.

What a user relies on: an FMI 3.0 co-simulation FMU is served as an FMI 2.0 one is, and a platoon whose
vehicles all run in such servers ends with the numbers of the same platoon stepped locally through the
FMI 3.0 FMUs, and with the local run's (FMI 2.0) trace, bit for bit; the FMU's own refusals reach the
run with its reason; and what cannot be served (model exchange only, inputs or outputs that are not one
Float64 each) is refused at the server's start, in one line naming the FMU and why. The killed-server
fault and the served instance's rules with an FMI 3.0 FMU are in tests/test_remote.py.
"""

from __future__ import annotations

import re
import zipfile
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest

from bridge import fmu_wire as wire
from orchestrator.components.fmu import UnpackedFmu
from orchestrator.components.fmu3 import Fmu3Component, fmu_component
from orchestrator.components.served import ServedInstance
from tests.conftest import free_port
from tests.test_cli import error_line, platoon
from tests.test_remote import PAPER, outputs, platoon_run, remote_sets, server

STOP = 10.0  # s of the paper's platoon (docs/remote.md reports the full 100 s)


def _points(config, scenario, fmus: dict[str, UnpackedFmu], remote: bool) -> list[list[list[float]]]:
    """Every output of every component at every communication point: the target and (``remote`` False) the
    vehicles stepped here through their FMI 3.0 FMUs, or (``remote`` True) the vehicles in their servers."""
    from orchestrator.components.remote import remote_components
    from orchestrator.execution.python_master import Master
    from orchestrator.scenario.raw_config import step_count

    served = remote_components(config, scenario, fmus) if remote else {}
    components = [served.get(spec.name) or fmu_component(spec.name, fmus[spec.fmu], spec.parameters)
                  for spec in scenario.components]
    master = Master(components, scenario.connections, scenario.schedules, config.simulation.master)
    points: list[list[list[float]]] = []
    try:
        master.run(config.simulation.stop_time, config.simulation.step,
                   lambda t, values: points.append([list(v) for v in values]),
                   step_count(config.simulation.stop_time, config.simulation.step))
    finally:
        master.close()
    return points


def test_fmi3_servers_give_the_local_fmi3_numbers_bit_for_bit(tmp_path: Path, fmi3_fmu_dir: Path,
                                                              native_fmu_dir: Path) -> None:
    """The paper's platoon, each vehicle in a `platoon serve` of the FMI 3.0 Vehicle.fmu: stepped by our
    master against the same platoon with every FMU local and FMI 3.0, and by `platoon run` against the
    local run (native FMI 2.0 FMUs, which compute the same C model)."""
    from orchestrator.scenario.config import load_config
    from orchestrator.scenario.scenario import build_scenario

    ports = {vehicle: free_port() for vehicle in (1, 2, 3, 4)}
    sets = [f"simulation.stop_time={STOP}", *[s for s in remote_sets(ports) if s != "--set"]]
    config, _ = load_config(PAPER, sets)
    scenario = build_scenario(config)
    fmus = {name: UnpackedFmu.open(fmi3_fmu_dir / f"{name}.fmu") for name in ("Vehicle", "VirtualTarget")}
    local_run = tmp_path / "local.mcap"
    process = platoon_run(PAPER, local_run, "native", "--set", f"simulation.stop_time={STOP}")
    assert process.communicate(timeout=300)[1] == "" and process.returncode == 0
    try:
        local = _points(config, scenario, fmus, remote=False)
        assert all(isinstance(c, Fmu3Component) for c in [fmu_component("x", fmus["Vehicle"], {})])
        with ExitStack() as stack:
            logs = []
            for vehicle, port in ports.items():
                process = stack.enter_context(server(f"vehicle{vehicle}", port, "native", tmp_path,
                                                     str(fmi3_fmu_dir / "Vehicle.fmu")))
                logs.append(tmp_path / f"serve-vehicle{vehicle}.log")
            there = _points(config, scenario, fmus, remote=True)
            remote_run = tmp_path / "remote.mcap"
            process = platoon_run(PAPER, remote_run, "native", *[a for s in sets for a in ("--set", s)])
            _, err = process.communicate(timeout=300)
            assert process.returncode == 0, err
    finally:
        for fmu in fmus.values():
            fmu.cleanup()
    assert "serving Vehicle.fmu ({" in logs[0].read_text()
    assert len(local) == len(there) == round(STOP / config.simulation.step) + 1
    assert local == there  # bit for bit: Python floats compare exactly
    here, served = outputs(local_run), outputs(remote_run)
    assert here.keys() == served.keys() and len(here["vehicle4.t"]) > 100
    for name in here:
        assert np.array_equal(here[name], served[name]), name


def test_an_fmi3_step_the_fmu_discards_is_refused_with_its_reason(fmi3_fmu_dir: Path) -> None:
    """A step the FMU answers fmi3Discard (here: a speed disturbance that stops the vehicle) reaches the run
    as the server's refusal carrying the FMU's own reason and the step's time, and the instance is not
    stepped further by a retry."""
    fmu = UnpackedFmu.open(fmi3_fmu_dir / "Vehicle.fmu")
    served = ServedInstance(fmu)
    token = b"t" * wire.TOKEN_SIZE
    try:
        opened = wire.parse_json(wire.parse_reply(served.handle(wire.request(wire.OPEN, token, 0, wire.json_body(
            {"name": "vehicle1", "start": 0.0, "parameters": {}}))))[1], "open")
        assert wire.parse_reply(served.handle(wire.request(wire.END_INIT, token, 1)))[0]
        inputs = list(opened["input_defaults"])
        inputs[opened["inputs"].index("disturbance.speed")] = -1e6
        reply = served.handle(wire.request(wire.STEP, token, 2, wire.step_body(0.0, 0.01, inputs)))
        ok, body = wire.parse_reply(reply)
        assert not ok and body.decode().endswith("(t = 0 s)"), body
        assert "speed" in body.decode(), body
        assert served.steps == 0
    finally:
        served.close()
        fmu.cleanup()


def _rewritten(source: Path, target: Path, edit) -> Path:
    """A copy of the FMU ``source`` whose modelDescription.xml is ``edit(text)`` (still valid FMI 3.0)."""
    with zipfile.ZipFile(source) as zin, zipfile.ZipFile(target, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item)
            if item.filename == "modelDescription.xml":
                data = edit(data.decode()).encode()
            zout.writestr(item, data)
    return target


UNSERVABLE = {
    "model-exchange": (lambda text: re.sub(r"<CoSimulation [^>]*/>", '<ModelExchange modelIdentifier="Vehicle"/>', text),
                       "cannot be served: FMI 3.0 model exchange only: a served FMU must be co-simulation"),
    "float32-output": (lambda text: re.sub(r'<Float64 (name="x" [^>]*causality="output")', r"<Float32 \1", text),
                       "cannot be served: output 'x' is Float32: inputs and outputs must be Float64"),
    "array-output": (lambda text: re.sub(r'(<Float64 name="y" [^>]*causality="output"[^>]*)/>',
                                         r'\1><Dimension start="2"/></Float64>', text),
                     "cannot be served: output 'y' is an array: inputs and outputs must be scalars"),
}


@pytest.mark.parametrize("case", UNSERVABLE)
def test_what_cannot_be_served_is_one_line_and_exit_2(case: str, tmp_path: Path, fmi3_fmu_dir: Path) -> None:
    edit, expected = UNSERVABLE[case]
    fmu = _rewritten(fmi3_fmu_dir / "Vehicle.fmu", tmp_path / f"{case}.fmu", edit)
    result = platoon("serve", fmu, "--name", "vehicle1", "--listen", f"tcp/127.0.0.1:{free_port()}", cwd=tmp_path)
    line = error_line(result)
    assert result.returncode == 2 and f"{case}.fmu: {expected}" in line, result.stderr
    assert "ready" not in result.stderr
