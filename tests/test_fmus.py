"""The FMUs as users meet them: validated, standalone-sane, converging, isolated, restorable."""

from __future__ import annotations

import zipfile
from xml.etree import ElementTree

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.validation import validate_fmu

from fmus.builders import PYTHONFMU, fmu_guid


@pytest.mark.parametrize("name", ["Vehicle", "VirtualTarget"])
def test_fmpy_validation_reports_no_problem(fmu_dir, name):
    assert validate_fmu(str(fmu_dir / f"{name}.fmu")) == []


@pytest.mark.parametrize("name", ["Vehicle", "VirtualTarget"])
def test_model_description_is_complete(fmu_dir, name):
    path = fmu_dir / f"{name}.fmu"
    with zipfile.ZipFile(path) as archive:
        root = ElementTree.fromstring(archive.read("modelDescription.xml"))
        assert "documentation/index.html" in archive.namelist()
    units = {u.get("name") for u in root.iter("Unit")}
    variables = root.find("ModelVariables")
    for scalar in variables:
        assert scalar.get("variability"), scalar.get("name")
        assert scalar.get("description"), scalar.get("name")
        kind = scalar[0]
        if kind.tag == "Real":
            assert kind.get("unit") in units, scalar.get("name")
        if kind.tag in ("Integer", "Boolean") and scalar.get("causality") == "parameter":
            assert scalar.get("variability") in ("fixed", "tunable")
    outputs = [i for i, s in enumerate(variables, start=1) if s.get("causality") == "output"]
    structure = root.find("ModelStructure")
    assert [int(u.get("index")) for u in structure.find("Outputs")] == outputs
    assert [int(u.get("index")) for u in structure.find("InitialUnknowns")] == outputs
    cosim = root.find("CoSimulation")
    assert cosim.get("needsExecutionTool") == "true"  # a Python installation runs the model
    assert cosim.get("canGetAndSetFMUstate") == "true"
    assert root.find("DefaultExperiment").get("stepSize") == "0.01"


def test_build_is_cached_and_guid_tracks_sources(fmu_dir):
    again = PYTHONFMU.build(fmu_dir)
    assert not any(b.rebuilt for b in again)
    for built in again:
        assert fmu_guid(built.path) == PYTHONFMU.expected_guid(built.name) == built.guid


@pytest.mark.parametrize("name", ["Vehicle", "VirtualTarget"])
def test_default_experiment_runs_standalone(fmu_dir, name):
    """Inputs unconnected, start values only, as `fmpy simulate` and the FMI cross-check run it."""
    result = simulate_fmu(str(fmu_dir / f"{name}.fmu"))
    assert result["time"][-1] == pytest.approx(60.0)
    assert all(np.all(np.isfinite(result[n])) for n in result.dtype.names)
    # both describe motion at about 25 m/s on the R = 50 m circle
    assert result["speed"][-1] == pytest.approx(25.0, rel=1e-6)


def _single_vehicle(fmu_dir, law):
    """A vehicle FMU chasing a VirtualTarget FMU on the circle, wired by hand through FMPy."""
    from orchestrator.components.fmu import FmuComponent, UnpackedFmu
    from orchestrator.execution.python_master import Master
    from orchestrator.scenario.wiring import platoon_connections

    target_fmu = UnpackedFmu.open(fmu_dir / "VirtualTarget.fmu")
    vehicle_fmu = UnpackedFmu.open(fmu_dir / "Vehicle.fmu")
    try:
        components = [
            FmuComponent("target", target_fmu, {}),
            FmuComponent("vehicle1", vehicle_fmu, {"law": law, "initial.speed": 20.0}),
        ]
        master = Master(components, platoon_connections(1))
        rows = []
        master.run(100.0, 0.01, lambda t, outputs: rows.append(outputs[1][:]), 10000)
        master.close()
    finally:
        target_fmu.cleanup()
        vehicle_fmu.cleanup()
    names = components[1].outputs
    last = dict(zip(names, rows[-1]))
    return last


def test_single_vehicle_sine_converges_to_the_circle(fmu_dir):
    last = _single_vehicle(fmu_dir, "sine")
    assert abs(np.hypot(last["x"], last["y"]) - 50.0) < 1e-6
    assert last["gap"] == pytest.approx(75.0, abs=1e-6)
    assert last["speed"] == pytest.approx(25.0, abs=1e-6)


def test_single_vehicle_regular_settles_inside_the_circle(fmu_dir):
    last = _single_vehicle(fmu_dir, "regular")
    offset = np.hypot(last["x"], last["y"]) - 50.0
    assert offset < -1.0  # a steady offset of metres, inward
    assert last["speed"] == pytest.approx(25.0, abs=1e-6)


def _fmu_slave(fmu_dir, name, instance, logger=None):
    from fmpy import extract
    from fmpy.fmi2 import FMU2Slave

    directory = extract(str(fmu_dir / f"{name}.fmu"))
    description = read_model_description(directory)
    slave = FMU2Slave(guid=description.guid, unzipDirectory=directory, modelIdentifier=name, instanceName=instance)
    return slave, {v.name: v.valueReference for v in description.modelVariables}


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("d_star", -1.0, "d_star = -1.0: must be a finite number > 0"),
        ("k_v", 0.0, "k_v = 0.0: must be a finite number > 0"),
        ("law", "straight", "law = 'straight': expected one of regular, sine"),
    ],
)
def test_bad_vehicle_parameters_are_rejected_at_initialization_with_a_logged_error(fmu_dir, name, value, message):
    from fmpy.fmi1 import FMICallException

    logged = []
    with pytest.raises(FMICallException):
        simulate_fmu(str(fmu_dir / "Vehicle.fmu"), start_values={name: value}, stop_time=1.0,
                     logger=lambda *args: logged.append(args[-1].decode()), debug_logging=True)
    assert any(message in line for line in logged), logged


def test_d_star_beyond_the_diameter_is_rejected(fmu_dir):
    from fmpy.fmi1 import FMICallException

    logged = []
    with pytest.raises(FMICallException):
        simulate_fmu(str(fmu_dir / "VirtualTarget.fmu"), start_values={"d_star": 120.0}, stop_time=1.0,
                     logger=lambda *args: logged.append(args[-1].decode()), debug_logging=True)
    assert any("must be <= 2 R = 100.0" in line for line in logged), logged


def test_two_platoons_in_one_process_stay_independent(fmu_dir, run):
    """Two interleaved platoons of the same FMUs give exactly what each gives alone."""
    from orchestrator.components.fmu import FmuComponent, UnpackedFmu
    from orchestrator.execution.python_master import Master
    from orchestrator.scenario.scenario import build_scenario
    from tests.conftest import make_config

    configs = [make_config(name="a", platoon={"count": 2, "law": "sine"}, initial={"radial_offset": 5.0}),
               make_config(name="b", platoon={"count": 2, "law": "regular"}, initial={"speed_factor": 0.7})]
    fmus = {n: UnpackedFmu.open(fmu_dir / f"{n}.fmu") for n in ("Vehicle", "VirtualTarget")}
    masters = []
    for config in configs:
        scenario = build_scenario(config)
        components = [FmuComponent(f"{config.name}-{s.name}", fmus[s.fmu], s.parameters) for s in scenario.components]
        connections = [type(c)(f"{config.name}-{c.source}", c.output, f"{config.name}-{c.destination}", c.input)
                       for c in scenario.connections]
        masters.append(Master(components, connections))
    for master in masters:
        master.initialize()
    for k in range(500):
        for master in masters:
            master.time = k * 0.01
            master.step((k + 1) * 0.01 - master.time)  # the grid Master.run steps on
    together = [[list(o) for o in master.outputs] for master in masters]
    for master in masters:
        master.close()
    for fmu in fmus.values():
        fmu.cleanup()
    for config, outputs in zip(configs, together):
        alone = run(config.model_copy(update={"simulation": config.simulation.model_copy(update={"stop_time": 5.0})}))
        for name, values in zip(["target", "vehicle1", "vehicle2"], outputs):
            channel = alone.component(name)
            keys = [k for k in channel if k != "t"]
            assert [channel[k][-1] for k in keys] == values


# A Link (docs/links.md) holds messages in flight only when its sender's message changes: it is fed a
# new one every step, with a delay, jitter and losses, so a state taken mid-run holds some in flight.
LINK_STATE_PARAMETERS = {"delay": 0.3, "jitter": 0.1, "loss": 0.3, "burst": 2.0, "seed": 3}


@pytest.mark.parametrize("kind", ["python", "native"])
@pytest.mark.parametrize("name", ["Vehicle", "VirtualTarget", "Link"])
def test_fmu_state_rolls_a_run_back_exactly(request, name, kind):
    """canGetAndSetFMUstate and canSerializeFMUstate are declared true: a saved state, restored
    (directly or through its serialized bytes), replays the same steps to the same outputs; for the
    pythonfmu FMUs and their native twins (fmus/native, whose serialized state starts with its tag;
    the Link's carries its messages in flight, the framework's memory block)."""
    from orchestrator.components.fmu import FmuComponent, UnpackedFmu

    folder = request.getfixturevalue("fmu_dir" if kind == "python" else "native_fmu_dir")
    fmu = UnpackedFmu.open(folder / f"{name}.fmu")
    component = FmuComponent("rollback", fmu, LINK_STATE_PARAMETERS if name == "Link" else {})

    def step(k: int) -> None:
        if name == "Link":  # the sender's message of t_k
            values = list(component.input_defaults)
            values[component.inputs.index("in.time")], values[component.inputs.index("in.x")] = k * 0.01, float(k)
            component.set_inputs(values)
        component.step(k * 0.01, 0.01)

    try:
        component.initialize(0.0)
        component.set_inputs(component.input_defaults)
        component.end_initialization()
        slave = component._slave
        for k in range(50):
            step(k)
        saved = slave.getFMUstate()
        serialized = slave.serializeFMUstate(saved)
        if kind == "native":
            assert bytes(serialized).startswith(b"platoon-cosim native FMU state")

        def replay() -> list[list[float]]:
            rows = []
            for k in range(50, 150):
                step(k)
                rows.append(component.get_outputs())
            return rows

        first = replay()
        slave.setFMUstate(saved)
        second = replay()
        slave.setFMUstate(slave.deSerializeFMUstate(serialized))
        third = replay()
        assert first == second == third
        outputs = dict(zip(component.outputs, first[-1]))
        if name == "Link":  # messages were in flight, and the held one is a delayed one
            assert outputs["sent"] > outputs["delivered"] + outputs["lost"] and outputs["age"] >= 0.3 - 1e-9
        else:
            assert outputs["output_time"] == pytest.approx(1.5)
        slave.freeFMUstate(saved)
    finally:
        component.close()
        fmu.cleanup()
