"""The FMI 3.0 co-simulation FMUs: the native C Vehicle and VirtualTarget behind the FMI 3.0 API.

Their model description (``fmus.modeldescription.fmi3``) is checked against the FMI 3.0 schema that FMPy
ships and against the FMI 2.0 description of the same model: same names, value references, types,
start values, units. The FMUs themselves (``fmus/native/fmi3.c``) are checked against the FMI 2.0
native FMUs, which run the same C model: bit-equal trajectories in FMPy, in a hand-stepped platoon
and in plain C hosts with no environment. Then what a host relies on when things go wrong: invalid
parameters and bad pointers (in a process of their own, so a crash shows as one), a step whose
results would not be finite, unsupported calls, and FMU states, in memory and serialized.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu
from lxml import etree

from fmus.builders.base import slave_instance
from fmus.modeldescription.fmi2 import guid_for, model_description
from fmus.modeldescription.fmi3 import TIME_VALUE_REFERENCE, instantiation_token_for
from fmus.modeldescription.fmi3 import model_description as model_description3
from fmus.slaves.Vehicle import Vehicle
from fmus.slaves.VirtualTarget import VirtualTarget

MODELS = {"Vehicle": Vehicle, "VirtualTarget": VirtualTarget}
FMI3_SCHEMA = Path(fmpy.__file__).parent / "schema" / "fmi3" / "fmi3ModelDescription.xsd"
FMI3_TYPE = {"Real": "Float64", "Integer": "Int32", "Boolean": "Boolean", "String": "String"}


def _description3(name: str, tmp_path: Path, digest: str = "0" * 64) -> Path:
    """A folder holding only the FMI 3.0 modelDescription.xml of model ``name`` (FMPy reads folders)."""
    folder = tmp_path / f"{name}-{digest[:8]}"
    folder.mkdir()
    token = instantiation_token_for(digest, name)
    (folder / "modelDescription.xml").write_bytes(model_description3(MODELS[name], token, "test"))
    return folder


def _read_description2(name: str, tmp_path: Path):
    """The FMI 2.0 description of the same model (as the pythonfmu FMU carries it), read by FMPy."""
    folder = tmp_path / "fmi2"
    folder.mkdir()
    (folder / "modelDescription.xml").write_bytes(model_description(slave_instance(name), guid_for("0" * 64, name), "test"))
    return fmpy.read_model_description(str(folder))


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_model_description_is_valid_against_the_fmi3_schema_and_fmpy(name, tmp_path):
    folder = _description3(name, tmp_path)
    schema = etree.XMLSchema(file=str(FMI3_SCHEMA))
    document = etree.parse(str(folder / "modelDescription.xml"))
    assert schema.validate(document), "\n".join(str(error) for error in schema.error_log)
    # FMPy's own checks beyond the schema: variable names, start values, causality/variability
    # combinations, units, exactly one independent variable, unique value references, ModelStructure
    assert validate_fmu(str(folder)) == []


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_variables_are_the_fmi2_variables_with_the_same_value_references(name, tmp_path):
    fmi3 = fmpy.read_model_description(str(_description3(name, tmp_path)))
    fmi2 = _read_description2(name, tmp_path)

    assert fmi3.fmiVersion == "3.0" and fmi3.coSimulation.modelIdentifier == name
    independent = [v for v in fmi3.modelVariables if v.causality == "independent"]
    assert [(v.name, v.type, v.valueReference) for v in independent] == [("time", "Float64", TIME_VALUE_REFERENCE)]
    declared = [v for v in fmi3.modelVariables if v.causality != "independent"]
    assert len(declared) == len(fmi2.modelVariables)
    for v3, v2 in zip(declared, fmi2.modelVariables):
        assert (v3.name, v3.valueReference) == (v2.name, v2.valueReference)
        assert v3.type == FMI3_TYPE[v2.type]
        assert (v3.causality, v3.variability, v3.unit) == (v2.causality, v2.variability, v2.unit)
        assert (v3.start, v3.min, v3.max) == (v2.start, v2.min, v2.max), v3.name
    # the references are 0..n-1, so time's is outside them
    assert sorted(v.valueReference for v in declared) == list(range(len(declared)))
    assert TIME_VALUE_REFERENCE >= len(declared)


def _dependency_names(unknowns) -> dict[str, set[str] | None]:
    return {u.variable.name: None if u.dependencies is None else {d.name for d in u.dependencies} for u in unknowns}


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_dependencies_name_the_fmi2_ones_plus_parameters_and_time(name, tmp_path):
    """FMPy resolves ``dependencies`` as value references in FMI 3.0 (indices in FMI 2.0): the names it
    finds must be the FMI 2.0 dependencies, plus, at communication points, the parameters the output
    is computed from, and ``time`` for ``output_time``."""
    fmi3 = fmpy.read_model_description(str(_description3(name, tmp_path)))
    fmi2 = _read_description2(name, tmp_path)

    outputs3, outputs2 = _dependency_names(fmi3.outputs), _dependency_names(fmi2.outputs)
    initial3, initial2 = _dependency_names(fmi3.initialUnknowns), _dependency_names(fmi2.initialUnknowns)
    assert list(outputs3) == list(outputs2) and list(initial3) == list(initial2)
    for output in outputs2:
        if outputs2[output] is None:
            assert outputs3[output] is None, output
        else:
            assert outputs2[output] <= outputs3[output], output
            added = outputs3[output] - outputs2[output]
            assert all(n == "time" or n.startswith("path.") for n in added), (output, added)
        if initial2[output] is None:
            assert initial3[output] is None, output
        else:
            assert initial3[output] - initial2[output] <= {"time"}, output
    assert outputs3["output_time"] == initial3["output_time"] == {"time"}
    assert outputs3["x"] == ({"path.kind", "path.radius", "path.x0", "path.y0", "path.heading", "path.direction"}
                             if name == "VirtualTarget" else set())
    if name == "VirtualTarget":
        assert outputs3["curvature"] == {"path.kind", "path.radius", "path.direction"}
        assert outputs3["arc_length"] == set()


def test_instantiation_token_follows_the_sources_and_differs_from_the_fmi2_guid():
    token = instantiation_token_for("a" * 64, "Vehicle")
    assert token == instantiation_token_for("a" * 64, "Vehicle")  # reproducible
    assert token != instantiation_token_for("b" * 64, "Vehicle")
    assert token != instantiation_token_for("a" * 64, "VirtualTarget")
    assert token != guid_for("a" * 64, "Vehicle")


# --- the FMUs -------------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]
HOSTS = Path(__file__).resolve().parent / "c_host"
TIMEOUT = 300


@pytest.fixture(scope="module")
def built():
    """The native FMUs, FMI 2.0 and FMI 3.0, built (or found up to date) where `platoon build` puts them."""
    from fmus.builders import DEFAULT_OUT
    from fmus.builders import NATIVE_FMI2, NATIVE_FMI3, NoCompiler

    from tests.conftest import shared_build

    if sys.platform != "linux":
        pytest.skip("the native FMUs are built and tested on Linux here")
    try:
        with shared_build():
            fmi2 = {fmu.name: fmu.path for fmu in NATIVE_FMI2.build(REPO / DEFAULT_OUT / "native")}
            fmi3 = {fmu.name: fmu.path for fmu in NATIVE_FMI3.build(REPO / DEFAULT_OUT / "fmi3")}
    except NoCompiler as error:
        pytest.skip(str(error))
    return {"fmi2": fmi2, "fmi3": fmi3}


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_fmus_pass_fmpy_validation(built, name):
    path = built["fmi3"][name]
    assert validate_fmu(str(path)) == []
    md3 = fmpy.read_model_description(str(path))
    md2 = fmpy.read_model_description(str(built["fmi2"][name]))
    assert md3.fmiVersion == "3.0" and md3.coSimulation.modelIdentifier == name
    assert md3.guid != md2.guid  # the instantiationToken is not the FMI 2.0 GUID
    with zipfile.ZipFile(path) as archive:
        names = set(archive.namelist())
    assert f"binaries/x86_64-linux/{name}.so" in names  # FMI 3.0's platform tuple, not FMI 2.0's linux64
    assert not any(entry.startswith("binaries/linux64/") for entry in names)


def _pulse(name: str, base: float, value: float, start: float, end: float, stop: float) -> np.ndarray:
    """An input signal for FMPy: ``value`` on [start, end), ``base`` elsewhere."""
    rows = [(0.0, base), (start, base), (start, value), (end, value), (end, base), (stop, base)]
    return np.array(rows, dtype=[("time", float), (name, float)])


SIMULATE_CASES = [
    ("Vehicle", {"law": law, "dynamics": dynamics, "coupling": coupling})
    for law in ("sine", "regular") for dynamics in ("kinematic", "m3pi") for coupling in ("extrapolate", "hold")
] + [
    ("VirtualTarget", {"path.kind": kind, "coupling": coupling, "path.heading": 0.3})
    for kind in ("circle", "line") for coupling in ("extrapolate", "hold")
] + [("Vehicle", {"speed_law": law, "coupling": "extrapolate"}) for law in ("acc", "cacc")] + [
    ("VirtualTarget", {"speed_law": "cacc", "path.kind": "circle"})] + [
    # a robot that is not its nominal model, in the live run's sampled loop (docs/model.md): the car-sized m3pi of
    # the wheel-limit cases, with its own gains and a dead-band, a radio and a motion capture late by no multiple
    # of the step
    ("Vehicle", {"dynamics": "m3pi", "m3pi.wheel_speed_max": 30.0, "m3pi.wheel_gain_right": 1.04,
                 "m3pi.wheel_gain_left": 0.97, "m3pi.wheel_deadband": 0.5, "m3pi.command_latency": 0.035,
                 "m3pi.pose_latency": 0.0125})]
# a disturbance through FMPy's input, so the run is not only the start values
PULSES = {"Vehicle": ("disturbance.lateral_acceleration", 0.0, 5.0), "VirtualTarget": ("lead.gap", 75.0, 90.0)}


@pytest.mark.parametrize("name,start_values", SIMULATE_CASES,
                         ids=[f"{name}-" + "-".join(map(str, values.values())) for name, values in SIMULATE_CASES])
def test_fmpy_simulates_the_fmi3_fmu_exactly_as_the_fmi2_native_one(built, name, start_values):
    """The same C model behind both APIs, the same calls from FMPy: bit-identical results."""
    stop = 10.0
    rows = _pulse(*PULSES[name], start=2.0, end=3.0, stop=stop)
    results = {kind: fmpy.simulate_fmu(str(built[kind][name]), stop_time=stop, output_interval=0.01,
                                       start_values=start_values, input=rows)
               for kind in ("fmi2", "fmi3")}
    fmi2, fmi3 = results["fmi2"], results["fmi3"]
    assert fmi3.dtype.names == fmi2.dtype.names and len(fmi3) == len(fmi2) == 1001
    for column in fmi2.dtype.names:
        assert np.array_equal(fmi3[column], fmi2[column]), column
    assert np.ptp(fmi3["x"]) > 1.0 and np.all(np.isfinite(fmi3["speed"]))  # it moved, and stayed finite


GETTERS3 = {"Float64": "getFloat64", "Int32": "getInt32", "Boolean": "getBoolean", "String": "getString"}
SETTERS3 = {"Float64": "setFloat64", "Int32": "setInt32", "Boolean": "setBoolean", "String": "setString"}
OTHER_VALUE = {"Float64": lambda v: v + 0.25, "Int32": lambda v: -v, "Boolean": lambda v: not v,
               "String": lambda v: v + "?"}


@pytest.mark.parametrize("name", MODELS)
def test_every_variable_reads_back_its_start_value_then_what_was_set(built, name):
    """Each type's getter and setter, on every parameter and input: the model description's start
    value first, then a value set (not checked before initialization ends, as in FMI 2.0)."""
    from fmpy.fmi3 import FMU3Slave

    path = built["fmi3"][name]
    md = fmpy.read_model_description(str(path))
    fmu = FMU3Slave(guid=md.guid, unzipDirectory=fmpy.extract(str(path)), modelIdentifier=name, instanceName="io")
    fmu.instantiate()
    settable = [v for v in md.modelVariables if v.causality in ("parameter", "input")]
    assert {v.type for v in settable} == ({"Float64", "Int32", "String"} if name == "VirtualTarget"
                                          else {"Float64", "Boolean", "String"})
    read = {"Float64": float, "Int32": int, "Boolean": lambda text: text == "true", "String": str}
    for variable in settable:
        start = read[variable.type](variable.start)
        [value] = getattr(fmu, GETTERS3[variable.type])([variable.valueReference])
        assert value == start, variable.name
        other = OTHER_VALUE[variable.type](start)
        getattr(fmu, SETTERS3[variable.type])([variable.valueReference], [other])
        assert getattr(fmu, GETTERS3[variable.type])([variable.valueReference]) == [other], variable.name
    fmu.freeInstance()


def test_time_reads_but_is_never_set_and_array_sizes_must_match(built):
    messages: list = []
    fmu, refs = _logging_instance(built["fmi3"]["VirtualTarget"], messages)
    fmu.enterInitializationMode(startTime=3.5)
    assert fmu.getFloat64([TIME_VALUE_REFERENCE, refs["output_time"]]) == [3.5, 3.5]
    assert _status(fmu.setFloat64, [TIME_VALUE_REFERENCE], [5.0]) == 3
    assert "time (value reference 1000000) is the independent variable" in messages[-1][2]
    assert _status(fmu.getFloat64, [refs["x"]], 2) == 3  # nValues 2 for one scalar
    assert "2 values for 1 value references" in messages[-1][2]
    fmu.exitInitializationMode()
    fmu.doStep(3.5, 0.5)
    assert fmu.getFloat64([refs["output_time"], TIME_VALUE_REFERENCE]) == [4.0, 4.0]
    fmu.terminate()
    fmu.freeInstance()


# --- a platoon stepped by hand through FMPy's FMU2Slave and FMU3Slave --------------------------------

class _Component:
    """One FMU instance behind the calls a master makes, in FMI 2.0 or FMI 3.0 (FMPy's classes)."""

    SETTERS = {"2.0": {"Real": "setReal", "Integer": "setInteger", "Boolean": "setBoolean", "String": "setString"},
               "3.0": {"Float64": "setFloat64", "Int32": "setInt32", "Boolean": "setBoolean", "String": "setString"}}

    def __init__(self, fmu: tuple, instance_name: str):
        from fmpy.fmi2 import FMU2Slave
        from fmpy.fmi3 import FMU3Slave

        md, unzipped = fmu
        self.version = md.fmiVersion
        self.variables = {v.name: v for v in md.modelVariables}
        slave = FMU3Slave if self.version == "3.0" else FMU2Slave
        self.fmu = slave(guid=md.guid, unzipDirectory=unzipped, modelIdentifier=md.coSimulation.modelIdentifier,
                         instanceName=instance_name)
        self.fmu.instantiate()
        self.get_real = self.fmu.getFloat64 if self.version == "3.0" else self.fmu.getReal
        self.set_real = self.fmu.setFloat64 if self.version == "3.0" else self.fmu.setReal

    def start(self, parameters: dict, start_time: float) -> None:
        for name, value in parameters.items():
            variable = self.variables[name]
            getattr(self.fmu, self.SETTERS[self.version][variable.type])([variable.valueReference], [value])
        if self.version == "3.0":
            self.fmu.enterInitializationMode(startTime=start_time)
        else:
            self.fmu.setupExperiment(startTime=start_time)
            self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()

    def refs(self, names) -> list[int]:
        return [self.variables[name].valueReference for name in names]


def _run_platoon(config, kinds: dict[str, str], fmus: dict, stop: float, schedules) -> np.ndarray:
    """Jacobi steps of the config's platoon up to ``stop``: every output of every component at every
    communication point, in one array. ``kinds`` says which FMU kind (fmi2/fmi3) each component is."""
    from orchestrator.scenario.scenario import build_scenario

    scenario = build_scenario(config)
    components = {spec.name: _Component(fmus[kinds[spec.name]][spec.fmu], spec.name) for spec in scenario.components}
    outputs = {name: [v for v, info in c.variables.items() if info.causality == "output"]
               for name, c in components.items()}
    for spec in scenario.components:
        components[spec.name].start(spec.parameters, 0.0)
    incoming = {name: [k for k in scenario.connections if k.destination == name] for name in components}
    h = config.simulation.step
    steps = round(stop / h)
    rows = []
    for n in range(steps + 1):
        t = n * h
        values = {name: dict(zip(outputs[name], c.get_real(c.refs(outputs[name])))) for name, c in components.items()}
        rows.append([values[name][o] for name in components for o in outputs[name]])
        if n == steps:
            break
        for name, c in components.items():
            names = [k.input for k in incoming[name]] + [s.input for s in schedules if s.component == name]
            inputs = [values[k.source][k.output] for k in incoming[name]] + [
                s.value_at(t) for s in schedules if s.component == name]
            c.set_real(c.refs(names), inputs)
        for c in components.values():
            c.fmu.doStep(currentCommunicationPoint=t, communicationStepSize=(n + 1) * h - t)
    for c in components.values():
        c.fmu.terminate()
        c.fmu.freeInstance()
    return np.array(rows)


PLATOON_CASES = {  # config, overrides, lateral kick on vehicle 1 (m/s^2, from 1 s for 0.5 s)
    "highway-sine-circle-extrapolate": ("platoon.toml", ["platoon.count=3"], 35.0),
    "highway-regular-line-hold": ("platoon.toml", ["platoon.count=3", "platoon.law=regular", "path.kind=line",
                                                   "simulation.coupling=hold"], 35.0),
    "m3pi-regular-circle-extrapolate": ("m3pi.toml", ["platoon.count=3", "platoon.law=regular"], 1.0),
    "m3pi-sine-line-hold": ("m3pi.toml", ["platoon.count=3", "path.kind=line", "simulation.coupling=hold"], 1.0),
    "highway-acc-circle-extrapolate": ("platoon.toml", ["platoon.count=3", "platoon.speed_law=acc"], 35.0),
    "highway-cacc-line-hold": ("platoon.toml", ["platoon.count=3", "platoon.speed_law=cacc", "path.kind=line",
                                                "simulation.coupling=hold"], 35.0),
}


@pytest.mark.parametrize("case", PLATOON_CASES)
def test_hand_stepped_platoon_is_the_same_with_fmi3_fmi2_and_both_mixed(built, case):
    """Both laws, both dynamics, both couplings, line and circle, with a disturbance: FMI 3.0 components,
    FMI 2.0 ones, and a platoon mixing both in one process give bit-identical trajectories."""
    from orchestrator.scenario.config import load_config
    from orchestrator.scenario.scenario import ScheduledInput

    file, overrides, kick = PLATOON_CASES[case]
    config, _ = load_config(REPO / "configs" / "paper" / file, overrides)
    schedules = [ScheduledInput("vehicle1", "disturbance.lateral_acceleration", 1.0, 0.5, kick)]
    fmus = {kind: {name: (fmpy.read_model_description(str(path)), fmpy.extract(str(path)))
                   for name, path in built[kind].items()} for kind in ("fmi2", "fmi3")}
    names = ["target", "vehicle1", "vehicle2", "vehicle3"]
    runs = {label: _run_platoon(config, kinds, fmus, 5.0, schedules) for label, kinds in {
        "fmi2": dict.fromkeys(names, "fmi2"),
        "fmi3": dict.fromkeys(names, "fmi3"),
        "mixed": {name: ("fmi3", "fmi2")[i % 2] for i, name in enumerate(names)},
    }.items()}
    assert runs["fmi2"].shape == (501, 9 + 3 * 12)
    assert np.all(np.isfinite(runs["fmi2"]))
    assert np.array_equal(runs["fmi3"], runs["fmi2"])
    assert np.array_equal(runs["mixed"], runs["fmi2"])
    assert not np.array_equal(runs["fmi2"][1], runs["fmi2"][-1])  # it moved


# --- plain C hosts, no environment --------------------------------------------------------------

C_HOST_OUTPUTS = {"Vehicle": ("x", "y", "speed", "gap"), "VirtualTarget": ("x", "y", "speed", "arc_length")}


@pytest.fixture(scope="module")
def hosts(tmp_path_factory):
    """minimal_host (FMI 2.0) and minimal_host3 (FMI 3.0), compiled; the FMI 3.0 one against the
    standard's headers that FMPy ships."""
    from fmus.builders.toolchain import NoCompiler, compiler, fmi_headers

    try:
        cc = compiler()
    except NoCompiler as error:
        pytest.skip(str(error))
    folder = tmp_path_factory.mktemp("c_hosts")
    executables = {}
    for kind, source in (("fmi2", "minimal_host.c"), ("fmi3", "minimal_host3.c")):
        executables[kind] = folder / source.removesuffix(".c")
        result = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", f"-I{fmi_headers()}", "-o",
                                 str(executables[kind]), str(HOSTS / source), "-ldl"],
                                capture_output=True, text=True, timeout=TIMEOUT)
        assert result.returncode == 0, f"compiling {source} failed:\n{result.stderr}"
    return executables


def _run_host(host: Path, fmu: Path, folder: Path, steps: int, step: float, name: str,
              token: str | None = None) -> subprocess.CompletedProcess:
    """The C host on the unzipped ``fmu``, with an empty environment."""
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(folder)
    md = fmpy.read_model_description(str(fmu))
    refs = {v.name: v.valueReference for v in md.modelVariables}
    args = [str(host), str(folder), token or md.guid, str(steps), repr(step)]
    args += [str(refs[output]) for output in C_HOST_OUTPUTS[name]] + [name]
    return subprocess.run(args, capture_output=True, text=True, env={}, timeout=TIMEOUT)


@pytest.mark.parametrize("name", MODELS)
def test_c_host_runs_the_fmi3_fmu_with_no_environment_as_fmpy_and_the_fmi2_twin(built, hosts, name, tmp_path):
    md = fmpy.read_model_description(str(built["fmi3"][name]))
    experiment = md.defaultExperiment
    step, stop = float(experiment.stepSize), float(experiment.stopTime)
    steps = round(stop / step)
    assert steps == 6000
    fmi3 = _run_host(hosts["fmi3"], built["fmi3"][name], tmp_path / "fmi3", steps, step, name)
    assert fmi3.returncode == 0, fmi3.stderr
    fmi2 = _run_host(hosts["fmi2"], built["fmi2"][name], tmp_path / "fmi2", steps, step, name)
    assert fmi2.returncode == 0, fmi2.stderr
    assert fmi3.stdout == fmi2.stdout  # the same CSV, to the last digit

    lines = fmi3.stdout.splitlines()
    assert lines[0] == "t,x,y,speed,gap" and len(lines) == steps + 2
    rows = np.array([[float(value) for value in line.split(",")] for line in lines[1:]])
    reference = fmpy.simulate_fmu(str(built["fmi3"][name]), stop_time=stop, output_interval=step,
                                  output=list(C_HOST_OUTPUTS[name]))
    assert len(reference) == len(rows)
    assert np.array_equal(rows[:, 0], reference["time"])
    for column, output in enumerate(C_HOST_OUTPUTS[name], start=1):
        assert np.array_equal(rows[:, column], reference[output]), output  # %.17g reads back exactly


def test_c_host_is_refused_an_fmi3_fmu_for_a_token_from_another_build(built, hosts, tmp_path):
    result = _run_host(hosts["fmi3"], built["fmi3"]["Vehicle"], tmp_path, 1, 0.01, "Vehicle",
                       token="{00000000-0000-0000-0000-000000000000}")
    assert result.returncode == 5  # fmi3InstantiateCoSimulation returned NULL ...
    assert "does not match this binary's" in result.stderr  # ... and logged why
    assert result.stdout == ""


# --- failures and FMU state ---------------------------------------------------------------------------

def _slave(path: Path):
    """FMPy's FMU3Slave of the FMU at ``path`` (its library loaded, no instance yet), and its value references."""
    from fmpy.fmi3 import FMU3Slave

    md = fmpy.read_model_description(str(path))
    fmu = FMU3Slave(guid=md.guid, unzipDirectory=fmpy.extract(str(path)),
                    modelIdentifier=md.coSimulation.modelIdentifier, instanceName="under_test")
    return fmu, {v.name: v.valueReference for v in md.modelVariables}


def _logger(messages: list):
    return lambda env, status, category, message: messages.append([status, category.decode(), message.decode()])


def _logging_instance(path: Path, messages: list):
    """An FMI 3.0 instance of the FMU at ``path`` whose log messages go to ``messages``."""
    fmu, refs = _slave(path)
    fmu.instantiate(logMessage=_logger(messages))
    return fmu, refs


def _status(call, *args) -> int:
    """The FMI status of a call through FMPy (which raises for anything worse than a warning)."""
    from fmpy.fmi1 import FMICallException

    try:
        call(*args)
    except FMICallException as error:
        return error.status
    return 0


def _do_step(fmu, t: float, h: float) -> dict:
    """fmi3DoStep itself (FMPy's doStep raises before its output arguments can be read)."""
    from ctypes import byref

    from fmpy.fmi3 import fmi3Boolean, fmi3Float64

    flags = [fmi3Boolean(True) for _ in range(3)]
    last = fmi3Float64(-1.0)
    status = fmu._functions["fmi3DoStep"](fmu.component, t, h, fmi3Boolean(False), *map(byref, flags), byref(last))
    return {"status": status, "event": flags[0].value, "terminate": flags[1].value, "early": flags[2].value,
            "last": last.value}


def invalid_parameter_calls(path: str) -> None:
    """Run in a child process (a crash must not take the test run with it): what each call answers
    on a Vehicle given invalid parameters, printed as JSON."""
    import json

    messages: list = []
    fmu, refs = _logging_instance(Path(path), messages)
    answers = {
        "set": _status(fmu.setFloat64, [refs["d_star"], refs["k_v"]], [-1.0, 0.0]),
        "set law": _status(fmu.setString, [refs["law"]], ["zigzag"]),
        "enter": _status(fmu.enterInitializationMode),
        "exit": _status(fmu.exitInitializationMode),
    }
    answers["exit log"] = list(messages)
    answers |= {
        "get x": _status(fmu.getFloat64, [refs["x"]]),
        "get time": _status(fmu.getFloat64, [TIME_VALUE_REFERENCE]),
        "set input": _status(fmu.setFloat64, [refs["target.x"]], [1.0]),
        "step": _do_step(fmu, 0.0, 0.01),
        "get state": _status(fmu.getFMUState),
        "exit again": _status(fmu.exitInitializationMode),
        "terminate": _status(fmu.terminate),
    }
    answers["last log"] = messages[-1]
    fmu.freeInstance()
    print(json.dumps(answers))


def test_invalid_parameters_give_fmi3error_with_the_reasons_and_every_later_call_fails_cleanly(built):
    result = subprocess.run(
        [sys.executable, "-c", "import sys; from tests.test_fmi3 import invalid_parameter_calls as run; run(sys.argv[1])",
         str(built["fmi3"]["Vehicle"])], capture_output=True, text=True, timeout=TIMEOUT, cwd=REPO)
    assert result.returncode == 0, result.stderr  # no crash, freeInstance included
    answers = json.loads(result.stdout.splitlines()[-1])
    fmi3_error = 3
    # setting is allowed (the values are checked when initialization ends, as in the FMI 2.0 FMUs)
    assert (answers["set"], answers["set law"], answers["enter"]) == (0, 0, 0)
    assert answers["exit"] == fmi3_error
    [(status, category, message)] = answers["exit log"]  # one refusal naming every invalid parameter
    assert (status, category) == (fmi3_error, "logStatusError")
    assert "invalid parameter(s)" in message and all(name in message for name in ("d_star", "k_v", "law"))
    for call in ("get x", "get time", "set input", "get state", "exit again"):
        assert answers[call] == fmi3_error, call
    assert answers["step"]["status"] == fmi3_error
    assert answers["step"]["terminate"] is False and answers["step"]["last"] == 0.0
    assert "the instance failed: invalid parameter(s)" in answers["last log"][2]
    assert answers["terminate"] == 0


def careless_calls(path: str) -> None:
    """Run in a child process: NULL, freed and foreign pointers handed to the FMI 3.0 binary; each
    call's status printed as JSON (a crash ends the process instead)."""
    from ctypes import byref, c_double, c_uint

    from fmpy.fmi3 import fmi3FMUState

    messages: list = []
    fmu, refs = _logging_instance(Path(path), messages)
    call = fmu._functions
    vr, value = c_uint(refs["x"]), c_double()
    state = fmi3FMUState()
    fmu.enterInitializationMode(startTime=0.0)
    fmu.exitInitializationMode()
    answers = {"get state": call["fmi3GetFMUState"](fmu.component, byref(state))}
    answers |= {
        "NULL get": call["fmi3GetFloat64"](None, byref(vr), 1, byref(value), 1),
        "NULL step": call["fmi3DoStep"](None, 0.0, 0.01, False, None, None, None, None),
        "state as instance": call["fmi3GetFloat64"](state, byref(vr), 1, byref(value), 1),
        "NULL state set": call["fmi3SetFMUState"](fmu.component, None),
        "step with NULL outputs": call["fmi3DoStep"](fmu.component, 0.0, 0.01, False, None, None, None, None),
        "free state": call["fmi3FreeFMUState"](fmu.component, byref(state)),
    }
    component = fmu.component
    call["fmi3FreeInstance"](component)
    answers |= {
        "freed get": call["fmi3GetFloat64"](component, byref(vr), 1, byref(value), 1),
        "freed terminate": call["fmi3Terminate"](component),
    }
    call["fmi3FreeInstance"](component)  # twice: nothing happens
    call["fmi3FreeInstance"](None)
    answers["logs"] = [message for _, _, message in messages]
    print(json.dumps(answers))


def test_null_freed_and_foreign_pointers_are_refused_and_never_crash(built):
    result = subprocess.run(
        [sys.executable, "-c", "import sys; from tests.test_fmi3 import careless_calls as run; run(sys.argv[1])",
         str(built["fmi3"]["Vehicle"])], capture_output=True, text=True, timeout=TIMEOUT, cwd=REPO)
    assert result.returncode == 0, result.stderr[-2000:]  # the double free included
    answers = json.loads(result.stdout.splitlines()[-1])
    logs = answers.pop("logs")
    assert (answers.pop("get state"), answers.pop("step with NULL outputs"), answers.pop("free state")) == (0, 0, 0)
    assert answers == dict.fromkeys(answers, 3), answers  # fmi3Error for each
    assert any("the FMU state: it is NULL" in line for line in logs), logs


def test_a_step_with_non_finite_results_is_discarded_and_the_state_kept(built):
    """An input that makes the outputs overflow: fmi3Discard, lastSuccessfulTime where the step began,
    and once the input is sane again the run goes on exactly as one that never saw the bad step."""
    messages: list = []
    fmu, refs = _logging_instance(built["fmi3"]["Vehicle"], messages)
    reference, _ = _logging_instance(built["fmi3"]["Vehicle"], [])
    outputs = [v for v in refs if v in C_HOST_OUTPUTS["Vehicle"]]
    for instance in (fmu, reference):
        instance.enterInitializationMode(startTime=0.0)
        instance.exitInitializationMode()
        for n in range(100):
            instance.doStep(n * 0.01, (n + 1) * 0.01 - n * 0.01)
    before = fmu.getFloat64(fmu_refs := [refs[o] for o in outputs])
    target_x = fmu.getFloat64([refs["target.x"]])
    fmu.setFloat64([refs["target.x"]], [1e308])
    answer = _do_step(fmu, 1.0, 0.01)
    assert answer == {"status": 2, "event": False, "terminate": False, "early": False, "last": 1.0}
    assert messages[-1][:2] == [2, "logStatusDiscard"] and "would not be finite" in messages[-1][2]
    fmu.setFloat64([refs["target.x"]], target_x)
    assert fmu.getFloat64(fmu_refs) == before
    assert fmu.getFloat64([TIME_VALUE_REFERENCE]) == [1.0]
    for instance in (fmu, reference):
        for n in range(100, 200):
            instance.doStep(n * 0.01, (n + 1) * 0.01 - n * 0.01)
    assert fmu.getFloat64(fmu_refs) == reference.getFloat64(fmu_refs)
    assert fmu.getFloat64([TIME_VALUE_REFERENCE]) == [2.0]
    for instance in (fmu, reference):
        instance.terminate()
        instance.freeInstance()


def test_fmu_state_round_trip_in_memory_and_serialized_into_another_instance(built):
    """Get a state at 2 s, run on to 4 s; set the state back and run again; deserialize it into an
    instance made with other parameters and run again: the same trajectory, to the bit."""
    messages: list = []
    fmu, refs = _logging_instance(built["fmi3"]["Vehicle"], messages)
    watched = [refs[o] for o in ("x", "y", "heading", "speed", "gap", "output_time")]
    fmu.setString([refs["law"]], ["regular"])
    fmu.enterInitializationMode(startTime=0.0)
    fmu.exitInitializationMode()

    def run(instance, start: int, end: int) -> list:
        rows = []
        for n in range(start, end):
            instance.doStep(n * 0.01, (n + 1) * 0.01 - n * 0.01)
            rows.append(instance.getFloat64(watched))
        return rows

    run(fmu, 0, 200)
    state = fmu.getFMUState()
    first = run(fmu, 200, 400)
    fmu.setFMUState(state)
    assert fmu.getFloat64([TIME_VALUE_REFERENCE]) == [2.0]
    assert run(fmu, 200, 400) == first
    serialized = fmu.serializeFMUState(state)
    fmu.freeFMUState(state)

    other_messages: list = []
    other, _ = _logging_instance(built["fmi3"]["Vehicle"], other_messages)
    other.setString([refs["law"]], ["sine"])  # the state brings its own parameters (law = regular)
    other.enterInitializationMode(startTime=0.0)
    other.exitInitializationMode()
    restored = other.deserializeFMUState(serialized)
    other.setFMUState(restored)
    other.freeFMUState(restored)
    assert run(other, 200, 400) == first
    assert first[0] != first[-1]
    # bytes that are no state are refused with the reason, and the instance is untouched
    assert _status(other.deserializeFMUState, serialized[:-1]) == 3
    assert other_messages[-1][:2] == [3, "logStatusError"] and "the serialized state cannot be read" in other_messages[-1][2]
    assert run(other, 400, 410) == run(fmu, 400, 410)  # other went on from where it was
    for instance in (fmu, other):
        instance.terminate()
        instance.freeInstance()


@pytest.mark.parametrize("name", MODELS)
def test_fmpy_rebuilds_the_binary_from_the_fmus_sources_and_it_runs_the_same(built, name, tmp_path):
    """sources/ and sources/buildDescription.xml are all an importer needs to compile the FMU for its
    own platform: FMPy's CMake build (fmpy.build) makes a binary that gives the shipped one's results."""
    from fmpy.build import build_platform_binary

    if shutil.which("cmake") is None:
        pytest.skip("FMPy's source build needs cmake")
    unzipped = tmp_path / "fmu"
    with zipfile.ZipFile(built["fmi3"][name]) as archive:
        archive.extractall(unzipped)
    shutil.rmtree(unzipped / "binaries")
    (tmp_path / "build").mkdir()
    build_platform_binary(unzipped, build_dir=tmp_path / "build")
    assert (unzipped / "binaries" / "x86_64-linux" / f"{name}.so").is_file()
    start_values = {"dynamics": "m3pi"} if name == "Vehicle" else {"path.kind": "line"}
    rebuilt = fmpy.simulate_fmu(str(unzipped), stop_time=5.0, output_interval=0.01, start_values=start_values)
    shipped = fmpy.simulate_fmu(str(built["fmi3"][name]), stop_time=5.0, output_interval=0.01,
                                start_values=start_values)
    for column in shipped.dtype.names:
        assert np.array_equal(rebuilt[column], shipped[column]), column


def test_what_the_fmu_does_not_support_is_refused_with_the_reason(built):
    """Event mode, Model Exchange, types the models do not have: NULL or fmi3Error, the reason logged."""
    from ctypes import c_size_t

    from fmpy.fmi3 import fmi3LogMessageCallback

    messages: list = []
    path = built["fmi3"]["Vehicle"]
    fmu, refs = _slave(path)
    with pytest.raises(Exception, match="Failed to instantiate"):
        fmu.instantiate(eventModeUsed=True, logMessage=_logger(messages))
    assert "has no event mode" in messages[-1][2]
    logger = fmi3LogMessageCallback(_logger(messages))
    instance = fmu._functions["fmi3InstantiateModelExchange"](b"me", fmu.guid.encode(), b"", False, False, None, logger)
    assert instance is None and "Model Exchange is not supported" in messages[-1][2]
    fmu.freeLibrary()

    fmu, refs = _logging_instance(path, messages)
    assert _status(fmu.enterEventMode) == 3 and "fmi3EnterEventMode is not supported" in messages[-1][2]
    assert _status(fmu.getFloat32, [refs["x"]]) == 3 and "no Float32 variables" in messages[-1][2]
    count = c_size_t(0)
    assert fmu._functions["fmi3GetNumberOfContinuousStates"](fmu.component, count) == 3
    assert "co-simulation FMU" in messages[-1][2]
    declared = [category.name for category in fmpy.read_model_description(str(path)).logCategories]
    assert len(declared) == 5 and _status(fmu.setDebugLogging, True, declared) == 0
    assert _status(fmu.setDebugLogging, True, ["logEverything"]) == 3
    assert "unknown log category logEverything" in messages[-1][2]
    fmu.enterInitializationMode(startTime=0.0)  # and the instance still works
    fmu.exitInitializationMode()
    fmu.doStep(0.0, 0.01)
    fmu.terminate()
    fmu.freeInstance()
