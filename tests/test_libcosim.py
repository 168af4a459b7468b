"""Interoperability: libcosim (C++, FMI Library) runs our FMUs and gets our orchestrator's numbers.

The same scenario (``build_scenario``: components, parameters, ``platoon_connections`` wiring,
disturbance schedules) is run twice on the same FMU files:

* by our orchestrator, ``run_scenario(engine="python")`` with the Jacobi master (FMPy underneath), and
* by libcosim through libcosimpy: one ``CosimLocalSlave`` per component, every parameter applied as
  an initial value of its declared type, every connection made with ``connect_real_variables``,
  libcosim's fixed-step (Jacobi) algorithm at ``config.simulation.step``. Disturbance pulses are
  set on the inputs before each step with libcosim's override manipulator, sampled at the
  communication point as our master does.

Every output of every component must agree at every communication point, t = 0 included, to
1e-9 absolute. libcosim's log (warning level and above) must say nothing about our FMUs: FMI
Library repairs an illegal model description silently apart from an error-level log line.

Why not bit for bit: the two masters put the communication points on slightly different grids.
libcosim counts time in integer nanoseconds and calls fmi2DoStep(t_k, h_k) with
t_k = k * 10^7 ns / 10^9 and h_k = t_(k+1) - t_k, so h_k wobbles by an ulp around 0.01 while
t_k + h_k lands exactly on t_(k+1). Our master passes t_k = k * 0.01 and h = 0.01 every step. The
start (both start-up procedures settle on identical t = 0 values), the wiring and the Jacobi
order are the same; the ulp-level time differences alone give differences of order 1e-12 m after
20 s. The second check proves it: our own Master and FmuComponents, stepped on libcosim's time
grid, reproduce libcosim's numbers exactly (difference 0.0) at every point.

Values are read with a time-series observer through libcosimc's ``cosim_observer_slave_get_real_samples``
called directly: libcosimpy 0.0.6's ``time_series_real_samples`` trims its result by counting zero
step numbers, so it always drops one sample (the initial one is step 0) and returns nothing for a
single sample.
"""

from __future__ import annotations

import os
import sys
import tempfile
from ctypes import CDLL, POINTER, c_double, c_int, c_int64, c_size_t, c_uint32
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("libcosimpy")

from libcosimpy import CosimConstants  # noqa: E402
from libcosimpy._internal import libcosimc, wrap_function  # noqa: E402
from libcosimpy.CosimEnums import CosimVariableCausality, CosimVariableType  # noqa: E402
from libcosimpy.CosimExecution import CosimExecution  # noqa: E402
from libcosimpy.CosimLogging import CosimLogLevel, log_output_level  # noqa: E402
from libcosimpy.CosimManipulator import CosimManipulator  # noqa: E402
from libcosimpy.CosimObserver import CosimObserver  # noqa: E402
from libcosimpy.CosimSlave import CosimLocalSlave  # noqa: E402

from fmus.builders import PYTHONFMU  # noqa: E402
from orchestrator.components.fmu import FmuComponent, UnpackedFmu  # noqa: E402
from orchestrator.scenario.config import Config, config_from_mapping  # noqa: E402
from orchestrator.execution.python_master import Master  # noqa: E402
from orchestrator.execution.run import run_scenario  # noqa: E402
from orchestrator.scenario.scenario import Scenario, build_scenario, step_count  # noqa: E402
from orchestrator.trace import load  # noqa: E402

_LIBC = CDLL(None)
TOLERANCE = 1e-9  # absolute; positions in metres
NANOSECONDS = 1_000_000_000

# The paper's platoon start: vehicle 1 5 m off the path, 0.1 rad off its heading, all at 0.8 V_c.
PAPER_START = {"radial_offset": 5.0, "heading_error": 0.1, "speed_factor": 0.8}

# Pulses on two vehicles, well after t = 0 and ending before the stop time, to exercise the
# per-step input path (libcosim's override manipulator) against our master's schedules.
DISTURBANCES = [
    {"vehicle": 2, "kind": "lateral_acceleration", "start": 3.0, "duration": 1.5, "value": 2.0},
    {"vehicle": 3, "kind": "speed", "start": 6.005, "duration": 2.0, "value": -1.5},
]


def paper_config(law: str = "sine", coupling: str = "extrapolate", disturbance: list | None = None,
                 stop_time: float = 20.0, speed_law: str = "paper") -> Config:
    raw: dict[str, Any] = {
        "name": f"libcosim-{law}-{coupling}",
        "simulation": {"stop_time": stop_time, "step": 0.01, "master": "jacobi", "coupling": coupling},
        "platoon": {"count": 4, "law": law, "speed_law": speed_law},
        "initial": dict(PAPER_START),
    }
    if disturbance:
        raw["disturbance"] = disturbance
    return config_from_mapping(raw)


# --- libcosim side --------------------------------------------------------------------------------


class _NativeOutput:
    """Collects what native code writes to file descriptors 1 and 2 while the block runs.

    libcosim (Boost.Log) writes its log to standard output, not standard error; C stdio buffers are
    flushed before the descriptors are restored so nothing written inside the block escapes.
    """

    def __enter__(self) -> "_NativeOutput":
        sys.stdout.flush()
        sys.stderr.flush()
        self._file = tempfile.TemporaryFile(mode="w+b")
        self._saved = {fd: os.dup(fd) for fd in (1, 2)}
        for fd in self._saved:
            os.dup2(self._file.fileno(), fd)
        self.text = ""
        return self

    def __exit__(self, *exc: object) -> None:
        sys.stdout.flush()
        sys.stderr.flush()
        _LIBC.fflush(None)
        for fd, saved in self._saved.items():
            os.dup2(saved, fd)
            os.close(saved)
        self._file.seek(0)
        self.text = self._file.read().decode("utf-8", "replace")
        self._file.close()


def _real_samples(observer: CosimObserver, slave: int, reference: int, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All ``count`` samples of one real variable from step 0: (values, step numbers, times in ns)."""
    function = wrap_function(
        lib=libcosimc(),
        funcname="cosim_observer_slave_get_real_samples",
        argtypes=[POINTER(CosimObserver), c_int, c_uint32, c_int64, c_size_t,
                  c_double * count, c_int64 * count, c_int64 * count],
        restype=c_int64,
    )
    values, steps, times = (c_double * count)(), (c_int64 * count)(), (c_int64 * count)()
    got = function(observer.ptr(), slave, reference, 0, count, values, steps, times)
    assert got == count, f"libcosim returned {got} samples of slave {slave} variable {reference}, expected {count}"
    return np.array(values[:]), np.array(steps[:]), np.array(times[:])


_SETTERS = {
    CosimVariableType.REAL: ("real_initial_value", float),
    CosimVariableType.INTEGER: ("integer_initial_value", int),
    CosimVariableType.BOOLEAN: ("boolean_initial_value", bool),
    CosimVariableType.STRING: ("string_initial_value", str),
}


class LibcosimRun:
    """A scenario as a libcosim execution: slaves, initial values, connections, observers."""

    def __init__(self, scenario: Scenario, fmu_paths: dict[str, Path]) -> None:
        self.scenario = scenario
        sim = scenario.config.simulation
        self.step_ns = int(round(sim.step * NANOSECONDS))
        assert self.step_ns / NANOSECONDS == sim.step, "step must be a whole number of nanoseconds"
        self.execution = CosimExecution.from_step_size(self.step_ns)
        self._slaves = []  # keep the Python wrappers alive as long as the execution
        self.index: dict[str, int] = {}
        for spec in scenario.components:
            slave = CosimLocalSlave(str(fmu_paths[spec.fmu]), spec.name)
            self._slaves.append(slave)
            index = self.execution.add_local_slave(slave)
            assert index >= 0, f"libcosim could not add {spec.name} ({fmu_paths[spec.fmu]})"
            self.index[spec.name] = index
        # What libcosim read from each model description: name -> (reference, type, causality).
        self.variables = {
            name: {v.name.decode(): (v.reference, CosimVariableType(v.type), CosimVariableCausality(v.causality))
                   for v in self.execution.slave_variables(index)}
            for name, index in self.index.items()
        }
        self.outputs = {
            name: [n for n, (_, kind, causality) in variables.items()
                   if causality == CosimVariableCausality.OUTPUT and kind == CosimVariableType.REAL]
            for name, variables in self.variables.items()
        }
        for spec in scenario.components:
            for name, value in spec.parameters.items():
                reference, kind, causality = self.variables[spec.name][name]
                assert causality == CosimVariableCausality.PARAMETER, f"{spec.name}.{name} is {causality}"
                setter, convert = _SETTERS[kind]
                assert getattr(self.execution, setter)(self.index[spec.name], reference, convert(value)), (
                    f"libcosim refused {spec.name}.{name} = {value!r}"
                )
        for connection in scenario.connections:
            source_ref, _, source_causality = self.variables[connection.source][connection.output]
            dest_ref, _, dest_causality = self.variables[connection.destination][connection.input]
            assert (source_causality, dest_causality) == (CosimVariableCausality.OUTPUT, CosimVariableCausality.INPUT)
            status = self.execution.connect_real_variables(
                self.index[connection.source], source_ref, self.index[connection.destination], dest_ref
            )
            assert status == CosimConstants.success, f"libcosim refused {connection}"
        self.series = CosimObserver.create_time_series()
        assert self.execution.add_observer(self.series)
        for name, outputs in self.outputs.items():
            for output in outputs:
                assert self.series.start_time_series(self.index[name], self.variables[name][output][0], CosimVariableType.REAL)
        self.last = CosimObserver.create_last_value()
        assert self.execution.add_observer(self.last)
        self.manipulator = CosimManipulator.create_override()
        assert self.execution.add_manipulator(self.manipulator)

    def _scheduled_inputs(self, t: float) -> dict[tuple[str, str], float]:
        """Value of every scheduled input at communication point t (pulses on one input add up)."""
        values: dict[tuple[str, str], float] = {}
        for schedule in self.scenario.schedules:
            key = (schedule.component, schedule.input)
            values[key] = values.get(key, 0.0) + schedule.value_at(t)
        return values

    def run(self) -> dict[str, dict[str, np.ndarray]]:
        """Step to the stop time; every output at every communication point, like Trace.channels."""
        sim = self.scenario.config.simulation
        steps = step_count(sim.stop_time, sim.step)
        applied = {key: 0.0 for key in self._scheduled_inputs(0.0)}  # the inputs' start values
        for k in range(steps):
            t = k * self.step_ns / NANOSECONDS  # libcosim's communication point, as it hands it to the FMUs
            for (component, name), value in self._scheduled_inputs(t).items():
                if value != applied[(component, name)]:
                    reference = self.variables[component][name][0]
                    assert self.manipulator.slave_real_values(self.index[component], [reference], [value])
                    applied[(component, name)] = value
            assert self.execution.step(), f"libcosim step {k} from t = {t} failed: {self.execution.status()}"
        status = self.execution.status()
        assert status.current_time == steps * self.step_ns, status
        channels: dict[str, dict[str, np.ndarray]] = {}
        for name, outputs in self.outputs.items():
            channel: dict[str, np.ndarray] = {}
            for output in outputs:
                values, step_numbers, times = _real_samples(self.series, self.index[name], self.variables[name][output][0], steps + 1)
                assert list(step_numbers) == list(range(steps + 1))
                channel["t"] = times / NANOSECONDS
                channel[output] = values
            channels[name] = channel
        return channels

    def parameter_values(self, component: str) -> dict[str, Any]:
        """Parameter values as libcosim's last-value observer reads them back from the FMU."""
        index = self.index[component]
        readers = {
            CosimVariableType.REAL: self.last.last_real_values,
            CosimVariableType.INTEGER: self.last.last_integer_values,
            CosimVariableType.BOOLEAN: self.last.last_boolean_values,
            CosimVariableType.STRING: self.last.last_string_values,
        }
        values = {}
        for name, (reference, kind, causality) in self.variables[component].items():
            if causality == CosimVariableCausality.PARAMETER:
                value = readers[kind](index, [reference])[0]
                values[name] = value.decode() if isinstance(value, bytes) else value
        return values


def run_libcosim(scenario: Scenario, fmu_paths: dict[str, Path]) -> tuple[dict[str, dict[str, np.ndarray]], str, dict]:
    """Run ``scenario`` in libcosim: (channels, what libcosim logged, parameters read back)."""
    log_output_level(CosimLogLevel.WARNING)
    with _NativeOutput() as captured:
        run = LibcosimRun(scenario, fmu_paths)
        channels = run.run()
        parameters = {spec.name: run.parameter_values(spec.name) for spec in scenario.components}
        del run
    return channels, captured.text, parameters


def run_master_on_libcosim_grid(scenario: Scenario, fmu_paths: dict[str, Path]) -> dict[str, dict[str, np.ndarray]]:
    """Our Jacobi master and FMU components, stepped on libcosim's nanosecond time grid."""
    sim = scenario.config.simulation
    step_ns = int(round(sim.step * NANOSECONDS))
    steps = step_count(sim.stop_time, sim.step)
    unpacked = {kind: UnpackedFmu.open(path) for kind, path in fmu_paths.items()}
    master = None
    try:
        components = [FmuComponent(spec.name, unpacked[spec.fmu], spec.parameters) for spec in scenario.components]
        master = Master(components, scenario.connections, scenario.schedules, "jacobi")
        rows = [master.initialize(0.0)]
        for k in range(steps):
            start, end = k * step_ns / NANOSECONDS, (k + 1) * step_ns / NANOSECONDS
            master.time = start
            rows.append(master.step(end - start))
        return {
            component.name: {name: np.array([row[c][o] for row in rows]) for o, name in enumerate(component.outputs)}
            for c, component in enumerate(components)
        }
    finally:
        if master is not None:
            master.close()
        for fmu in unpacked.values():
            fmu.cleanup()


# --- the comparison -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def fmus(tmp_path_factory) -> tuple[Path, dict[str, Path]]:
    """FMUs built once into a private folder; both importers load exactly these files."""
    folder = tmp_path_factory.mktemp("libcosim") / "fmus"
    built = PYTHONFMU.build(folder)
    return folder, {fmu.name: fmu.path for fmu in built}


CASES = {
    "sine-extrapolate": dict(law="sine", coupling="extrapolate"),
    "sine-hold": dict(law="sine", coupling="hold"),
    "regular-extrapolate": dict(law="regular", coupling="extrapolate"),
    "sine-extrapolate-disturbed": dict(law="sine", coupling="extrapolate", disturbance=DISTURBANCES),
    # the speed laws beyond the paper's: the sensor.* connections and a target at V_c
    "cacc-extrapolate-disturbed": dict(law="sine", coupling="extrapolate", disturbance=DISTURBANCES, speed_law="cacc"),
    "acc-hold": dict(law="sine", coupling="hold", speed_law="acc"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_libcosim_matches_orchestrator_jacobi(case: str, fmus, tmp_path: Path) -> None:
    fmu_dir, fmu_paths = fmus
    config = paper_config(**CASES[case])
    scenario = build_scenario(config)

    result = run_scenario(config, "", tmp_path / "ours.mcap", engine="python", fmu_dir=fmu_dir)
    assert result.status == "completed", result.error
    ours = load(tmp_path / "ours.mcap").channels

    theirs, log, parameters = run_libcosim(scenario, fmu_paths)

    # libcosim must have nothing to say about our FMUs (a repaired model description logs an error).
    noisy = [line for line in log.splitlines() if line.strip()]
    assert not noisy, "libcosim logged:\n" + "\n".join(noisy)

    # The parameters it applied are the ones the FMUs hold.
    for spec in scenario.components:
        for name, value in spec.parameters.items():
            held = parameters[spec.name][name]
            assert held == value, (
                f"{spec.name}.{name}: libcosim left {held!r}, expected {value!r}"
            )

    steps = step_count(config.simulation.stop_time, config.simulation.step)
    assert set(theirs) == set(ours) == {spec.name for spec in scenario.components}
    worst = (0.0, "", "", 0.0)
    worst_initial = 0.0
    for component, channel in ours.items():
        assert set(theirs[component]) == set(channel), component
        assert len(channel["t"]) == steps + 1
        np.testing.assert_allclose(theirs[component]["t"], channel["t"], rtol=0.0, atol=1e-12)
        for output, values in channel.items():
            if output == "t":
                continue
            difference = np.abs(theirs[component][output] - values)
            assert np.all(np.isfinite(difference)), f"{component}.{output}: non-finite values"
            worst_initial = max(worst_initial, float(difference[0]))
            k = int(np.argmax(difference))
            if difference[k] > worst[0]:
                worst = (float(difference[k]), component, output, float(channel["t"][k]))
    largest, component, output, t = worst

    # The same masters on the same time grid: no difference at all.
    ours_on_grid = run_master_on_libcosim_grid(scenario, fmu_paths)
    grid_worst = max(
        float(np.max(np.abs(ours_on_grid[name][output] - theirs[name][output])))
        for name in ours_on_grid for output in ours_on_grid[name]
    )

    print(f"\n[libcosim vs orchestrator jacobi] {case}: max |difference| = {largest:.3e} "
          f"({component}.{output} at t = {t:.2f} s), at t = 0: {worst_initial:.3e}; "
          f"on libcosim's time grid: {grid_worst:.3e}; "
          f"{steps + 1} points x {sum(len(c) - 1 for c in ours.values())} outputs")
    assert largest <= TOLERANCE, f"{case}: {component}.{output} differs by {largest:.3e} at t = {t} s"
    assert worst_initial == 0.0, f"{case}: initial values differ by {worst_initial:.3e}"
    assert grid_worst == 0.0, f"{case}: our master on libcosim's time grid differs from libcosim by {grid_worst:.3e}"
