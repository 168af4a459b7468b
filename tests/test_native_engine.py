"""The native engine (C stepping core) gives exactly the Python engine's numbers, and its failures.

``NativeMaster`` (orchestrator/execution/native) and ``Master`` + ``FmuComponent`` (FMPy underneath) run the
same scenario on the same FMU files; every output of every component must be equal (``==``, not
close) at every communication point, t = 0 included: the native core makes the same FMI calls with
the same arguments in the same order, so any difference is a bug. Covered: the paper platoon with
both laws, Jacobi and Gauss-Seidel, with disturbance pulses on two vehicles (one starting off the
communication grid), the block interface with trace decimation, and failures: a step failure
mid-run and non-finite initial outputs give the same ComponentError (component, time, reason) with
the same points delivered before it.

The extension must be built here (``pip install -e .`` compiles it): these tests fail, rather than
skip, when it is missing.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fmus.builders import PYTHONFMU
from orchestrator.components import fmu as components_module
from orchestrator.components.fmu import ComponentError, FmuComponent, UnpackedFmu
from orchestrator.scenario.config import Config, config_from_mapping
from orchestrator.execution.python_master import Master
from orchestrator.execution.native import IMPORT_ERROR, NativeComponent, NativeMaster, available
from orchestrator.scenario.scenario import Scenario, build_scenario, step_count

PAPER_START = {"radial_offset": 5.0, "heading_error": 0.1, "speed_factor": 0.8}
DISTURBANCES = [
    {"vehicle": 2, "kind": "lateral_acceleration", "start": 1.0, "duration": 1.5, "value": 2.0},
    {"vehicle": 3, "kind": "speed", "start": 2.005, "duration": 2.0, "value": -1.5},  # between two points
    {"vehicle": 3, "kind": "speed", "start": 3.0, "duration": 0.5, "value": 0.75},  # overlapping pulses add
]
SPEED_TO_ZERO = [{"vehicle": 4, "kind": "speed", "start": 1.0, "duration": 0.5, "value": -100.0}]

Rows = list[tuple[float, list[list[float]]]]


def paper_config(law: str = "sine", master: str = "jacobi", stop_time: float = 6.0, disturbance: list | None = None,
                 **extra: Any) -> Config:
    raw: dict[str, Any] = {
        "name": f"native-{law}-{master}",
        "simulation": {"stop_time": stop_time, "step": 0.01, "master": master},
        "platoon": {"count": 4, "law": law},
        "initial": dict(PAPER_START),
        **extra,
    }
    if disturbance:
        raw["disturbance"] = disturbance
    return config_from_mapping(raw)


@pytest.fixture(scope="module")
def fmus(fmu_dir: Path):
    unpacked = {built.name: UnpackedFmu.open(built.path) for built in PYTHONFMU.build(fmu_dir)}
    yield unpacked
    for fmu in unpacked.values():
        fmu.cleanup()


def make_master(engine: str, scenario: Scenario, fmus: dict[str, UnpackedFmu]):
    """``python-wrappers``: the Python engine as it runs should FMPy stop exposing its resolved fmi2
    functions: FMPy's own wrappers stand in for the hot calls."""
    sim = scenario.config.simulation
    if engine in ("python", "python-wrappers"):
        components = [FmuComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
        return Master(components, scenario.connections, scenario.schedules, sim.master)
    components = [NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    return NativeMaster(components, scenario.connections, scenario.schedules, sim.master)


def run_engine(engine: str, config: Config, fmus: dict[str, UnpackedFmu]) -> tuple[Rows, ComponentError | None]:
    """Every observed (t, outputs) of a run, and the ComponentError that ended it, if any."""
    if engine == "python-wrappers":
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(components_module, "resolved_functions", lambda slave: {})
            return run_engine("python", config, fmus)
    scenario = build_scenario(config)
    sim = config.simulation
    master = make_master(engine, scenario, fmus)
    rows: Rows = []
    failure = None
    try:
        master.run(sim.stop_time, sim.step, lambda t, outputs: rows.append((t, [list(v) for v in outputs])),
                   step_count(sim.stop_time, sim.step))
    except ComponentError as error:
        failure = error
    finally:
        master.close()
    return rows, failure


def test_extension_is_built() -> None:
    assert available(), f"orchestrator.execution.native._core did not import: {IMPORT_ERROR}"


@pytest.mark.parametrize("law, master, python", [
    ("sine", "jacobi", "python"), ("sine", "gauss-seidel", "python"), ("regular", "jacobi", "python"),
    ("regular", "gauss-seidel", "python"), ("sine", "jacobi", "python-wrappers")])
def test_bit_identical_to_python_engine(law: str, master: str, python: str, fmus) -> None:
    config = paper_config(law, master, disturbance=DISTURBANCES)
    python_rows, python_failure = run_engine(python, config, fmus)
    native_rows, native_failure = run_engine("native", config, fmus)
    assert python_failure is None and native_failure is None, (python_failure, native_failure)
    steps = step_count(config.simulation.stop_time, config.simulation.step)
    assert len(python_rows) == len(native_rows) == steps + 1
    for k, ((t_py, out_py), (t_nat, out_nat)) in enumerate(zip(python_rows, native_rows)):
        assert t_nat == t_py, f"point {k}: t = {t_nat!r} vs {t_py!r}"
        if out_nat != out_py:
            worst = max(abs(a - b) for ra, rb in zip(out_nat, out_py) for a, b in zip(ra, rb))
            pytest.fail(f"{law}/{master}: outputs differ at point {k} (t = {t_py}), by up to {worst:.3e}")
    # the disturbances did act: vehicle 2's lateral acceleration output carries the pulse
    assert python_rows != run_engine("python", paper_config(law, master), fmus)[0]


def test_step_interface_matches_master(fmus) -> None:
    """initialize / step(h) / outputs / time, driven by hand as run_master_on_libcosim_grid does."""
    scenario = build_scenario(paper_config("sine", "gauss-seidel", disturbance=DISTURBANCES))
    python, native = make_master("python", scenario, fmus), make_master("native", scenario, fmus)
    try:
        assert native.initialize(0.0) == python.initialize(0.0)
        for k in range(150):
            start, end = k * 10_000_000 / 1e9, (k + 1) * 10_000_000 / 1e9  # libcosim's nanosecond grid
            python.time = native.time = start
            assert native.step(end - start) == python.step(end - start), f"step {k}"
        assert native.outputs == python.outputs
        assert [c.name for c in native.components] == [c.name for c in python.components]
        assert [c.outputs for c in native.components] == [c.outputs for c in python.components]
        assert [c.inputs for c in native.components] == [c.inputs for c in python.components]
    finally:
        python.close()
        native.close()


@pytest.mark.parametrize("every,block", [(1, 500), (3, 7), (7, 2)])
def test_run_blocks_fills_trace_rows(every: int, block: int, fmus) -> None:
    """The C loop's trace rows: [t, every output], the initial point, then every every-th point."""
    config = paper_config("sine", "jacobi", stop_time=2.0, disturbance=DISTURBANCES)
    python_rows, _ = run_engine("python", config, fmus)
    scenario = build_scenario(config)
    master = make_master("native", scenario, fmus)
    blocks: list[np.ndarray] = []
    ticks: list[int] = []
    try:
        master.run_blocks(0.01, len(python_rows) - 1, lambda rows: blocks.append(rows.array().copy()), every=every,
                          block=block, tick=ticks.append)
    finally:
        master.close()
    assert all(len(b) <= max(block, 2) for b in blocks)
    got = np.concatenate(blocks)
    expected = [row for j, row in enumerate(python_rows) if j % every == 0]
    assert len(got) == len(expected)
    for row, (t, outputs) in zip(got.tolist(), expected):
        assert row == [t] + [value for values in outputs for value in values]
    assert ticks[-1] == len(python_rows) - 1 and ticks == sorted(ticks)


def test_run_blocks_untraced_ends_where_the_traced_run_ends(fmus) -> None:
    config = paper_config("regular", "gauss-seidel", stop_time=1.0)
    scenario = build_scenario(config)
    final = []
    for sink in (None, lambda rows: None):
        master = make_master("native", scenario, fmus)
        try:
            master.run_blocks(0.01, 100, sink, block=16)
            final.append((master.time, master.outputs))
        finally:
            master.close()
    python_rows, _ = run_engine("python", config, fmus)
    assert final[0] == final[1] == python_rows[-1]


@pytest.mark.parametrize("python", ["python", "python-wrappers"])
def test_step_failure_raises_component_error_like_python(python: str, fmus) -> None:
    """A -100 m/s speed pulse on vehicle 4 at t = 1 s: its speed goes negative in the next step."""
    config = paper_config("sine", "jacobi", stop_time=3.0, disturbance=SPEED_TO_ZERO)
    python_rows, python_failure = run_engine(python, config, fmus)
    native_rows, native_failure = run_engine("native", config, fmus)
    assert isinstance(native_failure, ComponentError) and isinstance(python_failure, ComponentError)
    assert native_failure.component == "vehicle4"
    assert native_failure.time == 1.0
    assert "speed fell" in native_failure.reason, native_failure.reason
    assert str(native_failure) == str(python_failure)
    assert (native_failure.component, native_failure.time, native_failure.reason) == (
        python_failure.component, python_failure.time, python_failure.reason)
    # every point up to the failure was observed, and nothing after it
    assert len(native_rows) == len(python_rows) == 101
    assert native_rows == python_rows


@pytest.mark.parametrize("engine", ["python", "native"])
def test_outputs_after_a_failed_jacobi_step_are_the_last_complete_point(engine: str, fmus) -> None:
    """Vehicle 4 (the last component) fails at t = 1 s after the others stepped: the outputs stay those
    at t = 1 s. A master that read each output right after its component's step (for cache locality,
    docs/performance.md) must keep this: it would have to read into a spare array."""
    config = paper_config("sine", "jacobi", stop_time=3.0, disturbance=SPEED_TO_ZERO)
    master = make_master(engine, build_scenario(config), fmus)
    rows: Rows = []
    try:
        with pytest.raises(ComponentError, match="vehicle4"):
            master.run(3.0, 0.01, lambda t, outputs: rows.append((t, [list(v) for v in outputs])), 300)
        outputs = [list(values) for values in master.outputs]
    finally:
        master.close()
    assert rows[-1] == (1.0, outputs)


def test_step_failure_in_blocks_delivers_rows_then_raises(fmus) -> None:
    config = paper_config("sine", "gauss-seidel", stop_time=3.0, disturbance=SPEED_TO_ZERO)
    python_rows, python_failure = run_engine("python", config, fmus)
    master = make_master("native", build_scenario(config), fmus)
    blocks: list[np.ndarray] = []
    try:
        with pytest.raises(ComponentError) as caught:
            master.run_blocks(0.01, 300, lambda rows: blocks.append(rows.array().copy()), block=64)
        messages = master.messages("vehicle4")
        assert master.time == 1.0
    finally:
        master.close()
    assert str(caught.value) == str(python_failure)
    assert caught.value.reason in messages
    got = np.concatenate(blocks)
    assert got[:, 0].tolist() == [t for t, _ in python_rows]
    assert got[-1, 1:].tolist() == [v for values in python_rows[-1][1] for v in values]


def test_non_finite_initial_outputs_fail_like_python(fmus) -> None:
    """Vehicle 1 placed exactly on its target: distance 0, the initial outputs are not finite."""
    config = paper_config("sine", "jacobi", stop_time=1.0, vehicles={
        "1": {"initial": {"x": 50.0, "y": 0.0, "heading": 1.5707963267948966, "speed": 20.0}}})
    python_rows, python_failure = run_engine("python", config, fmus)
    native_rows, native_failure = run_engine("native", config, fmus)
    assert python_failure is not None and native_failure is not None
    assert str(native_failure) == str(python_failure)
    assert native_failure.time == 0.0
    assert native_rows == python_rows == []


def test_unknown_parameter_and_wiring_are_refused(fmus) -> None:
    scenario = build_scenario(paper_config())
    with pytest.raises(ValueError, match="no variable"):
        NativeComponent("vehicle1", fmus["Vehicle"], {"no.such.parameter": 1.0})
    components = [NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    bad = scenario.connections[0].__class__("target", "x", "vehicle9", "target.x")
    with pytest.raises(ValueError, match="no component named 'vehicle9'"):
        NativeMaster(components, [*scenario.connections, bad])
    with pytest.raises(ValueError, match="unknown master"):
        NativeMaster(components, scenario.connections, algorithm="newton")


# --- stopping between two steps, and partial blocks on a wall-time interval --------------------------

class Stop(Exception):
    pass


@pytest.mark.parametrize("with_sink", [True, False], ids=["traced", "untraced"])
def test_check_stops_the_run_between_two_steps_after_delivering_its_rows(fmus, with_sink: bool) -> None:
    """``check()`` runs after every step in C: raising there (as a signal's flag does in run_scenario)
    stops the run at that step; every row up to it reaches the sink first."""
    scenario = build_scenario(paper_config("sine", "jacobi", stop_time=2.0))
    calls = []

    def check() -> None:
        calls.append(len(calls) + 1)
        if len(calls) == 37:
            raise Stop()

    blocks: list[np.ndarray] = []
    master = make_master("native", scenario, fmus)
    try:
        with pytest.raises(Stop):
            master.run_blocks(0.01, 200, (lambda rows: blocks.append(rows.array().copy())) if with_sink else None, every=2,
                              block=500, check=check)
        assert master.time == pytest.approx(0.37)  # 37 steps taken, not one more
    finally:
        master.close()
    assert calls[-1] == 37
    if with_sink:
        got = np.concatenate(blocks)
        assert np.allclose(got[:, 0], np.arange(19) * 0.02)  # t = 0, 0.02, ..., 0.36: every 2nd point up to the stop


def test_partial_blocks_are_delivered_on_the_wall_time_interval(fmus) -> None:
    """``deliver_interval=0``: a (partial) block after every call into C, so a trace on disk keeps up."""
    scenario = build_scenario(paper_config("sine", "jacobi", stop_time=3.0))
    sizes: list[int] = []
    master = make_master("native", scenario, fmus)
    try:
        master.run_blocks(0.01, 300, lambda rows: sizes.append(len(rows)), every=1, block=500, deliver_interval=0.0)
    finally:
        master.close()
    assert sum(sizes) == 301 and len(sizes) >= 300 // 64 and max(sizes) <= 65


class TruncatingComponent:
    """A real FMU component that, after its ``after``-th step, returns one output too few, as a
    malformed live endpoint might."""

    def __init__(self, inner: FmuComponent, after: int) -> None:
        self.inner, self.after, self.steps = inner, after, 0
        self.name, self.inputs, self.outputs, self.input_defaults = (
            inner.name, inner.inputs, inner.outputs, inner.input_defaults)

    def step(self, time: float, step: float) -> None:
        self.steps += 1
        self.inner.step(time, step)

    def get_outputs(self) -> list[float]:
        values = self.inner.get_outputs()
        return values[:-1] if self.steps > self.after else values

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


@pytest.mark.parametrize("algorithm", ["jacobi", "gauss-seidel"])
def test_a_component_returning_the_wrong_number_of_outputs_fails_the_run_by_name(algorithm: str, fmus) -> None:
    """No transfer may read a shifted value: the step fails naming the component, and the master's
    outputs keep only complete vectors (with Jacobi, the last complete point, as on an FMU failure)."""
    scenario = build_scenario(paper_config("sine", algorithm, stop_time=1.0))
    components = [FmuComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    components[2] = TruncatingComponent(components[2], after=5)
    master = Master(components, scenario.connections, scenario.schedules, algorithm)
    rows: Rows = []
    try:
        with pytest.raises(ComponentError, match=r"returned \d+ outputs, expected") as caught:
            master.run(1.0, 0.01, lambda t, outputs: rows.append((t, [list(v) for v in outputs])), 100)
        outputs = [list(values) for values in master.outputs]
    finally:
        master.close()
    assert caught.value.component == components[2].name
    assert len(rows) == 1 + 5  # t = 0 and the five good steps
    assert rows[-1][0] == pytest.approx(0.05)
    if algorithm == "jacobi":
        assert rows[-1][1] == outputs
    assert all(len(values) == len(c.outputs) for values, c in zip(outputs, components))


def test_a_closed_fmu_component_refuses_to_step_instead_of_calling_a_freed_instance(fmus) -> None:
    scenario = build_scenario(paper_config("sine", "jacobi", stop_time=1.0))
    spec = scenario.components[1]
    component = FmuComponent(spec.name, fmus[spec.fmu], spec.parameters)
    with pytest.raises(RuntimeError, match="not instantiated"):
        component.get_outputs()
    component.initialize(0.0)
    component.end_initialization()
    assert len(component.get_outputs()) == len(component.outputs)
    component.close()
    for call in (lambda: component.set_inputs(component.input_defaults), lambda: component.step(0.0, 0.01),
                 component.get_outputs):
        with pytest.raises(RuntimeError, match="not instantiated"):
            call()
