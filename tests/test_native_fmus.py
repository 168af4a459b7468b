"""The native (C) Vehicle and VirtualTarget FMUs: valid, the same interface, the same numbers.

fmus/native/ mirrors fmus/model equation by equation; these tests hold the two FMU kinds against
each other: FMPy validates the native FMUs and finds the pythonfmu FMUs' variables in them; every
output of a standalone simulation, for every law, dynamics, coupling and path, and of a platoon
stepped by our master with a disturbance pulse, agrees with the pythonfmu FMU's to 1e-9 (observed:
identical to the last bit, fmus/native/pymath.h says why that is possible); the binary needs no
Python (tests/test_c_host.py runs it in an empty environment) and libcosim runs it. The FMU state
(rollback, parameters carried by the state: tests/test_fmus.py, tests/test_hostile_fmus.py) and the
hostile calls (tests/test_hostile_fmus.py) are tested with both kinds where the Python ones are.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import zipfile
from xml.etree import ElementTree

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu
from fmpy.validation import validate_fmu

from fmus.builders import NATIVE_FMI2
from orchestrator.components.fmu import FmuComponent, UnpackedFmu
from orchestrator.scenario.config import config_from_mapping
from orchestrator.execution.python_master import Master
from orchestrator.scenario.scenario import build_scenario, step_count

NAMES = ("Vehicle", "VirtualTarget")
TOLERANCE = 1e-9  # far below any physical meaning; the trajectories are identical here (0.0)


def _root(path) -> ElementTree.Element:
    with zipfile.ZipFile(path) as archive:
        return ElementTree.fromstring(archive.read("modelDescription.xml"))


# --- (a) valid FMUs with the pythonfmu FMUs' interface ----------------------------------------------------


@pytest.mark.parametrize("name", NAMES + ("Link",))
def test_fmpy_validates_the_native_fmu(native_fmu_dir, name):
    assert validate_fmu(str(native_fmu_dir / f"{name}.fmu")) == []


@pytest.mark.parametrize("name", NAMES + ("Link",))
def test_native_fmu_has_the_python_fmus_variables_and_honest_flags(fmu_dir, native_fmu_dir, name):
    """Same names, value references, types, causalities, variabilities, units, start values, ranges
    and model structure; needsExecutionTool="false" (nothing but the C library is needed)."""
    native, python = (read_model_description(str(folder / f"{name}.fmu")) for folder in (native_fmu_dir, fmu_dir))

    def interface(description):
        return [(v.name, v.valueReference, v.type, v.causality, v.variability, v.unit, v.start, v.min, v.max,
                 v.initial) for v in description.modelVariables]

    def structure(description):
        return [(u.variable.name, None if u.dependencies is None else [d.name for d in u.dependencies])
                for u in description.outputs + description.initialUnknowns]

    assert interface(native) == interface(python)
    assert structure(native) == structure(python)
    assert native.guid != python.guid
    cosim = _root(native_fmu_dir / f"{name}.fmu").find("CoSimulation")
    assert cosim.get("needsExecutionTool") == "false"
    assert cosim.get("canGetAndSetFMUstate") == cosim.get("canSerializeFMUstate") == "true"
    assert "native C" in _root(native_fmu_dir / f"{name}.fmu").get("generationTool")


def test_native_build_is_cached_reproducible_and_complete(native_fmu_dir, tmp_path):
    """Up to date: nothing rebuilt, the GUID is the sources' digest. A fresh build elsewhere writes
    the same bytes (no timestamps, no paths). The archive carries the binary and its sources."""
    again = NATIVE_FMI2.build(native_fmu_dir)
    assert not any(built.rebuilt for built in again)
    assert all(built.guid == NATIVE_FMI2.expected_guid(built.name) for built in again)
    fresh = NATIVE_FMI2.build(tmp_path, force=True)
    for built in fresh:
        assert built.path.read_bytes() == (native_fmu_dir / f"{built.name}.fmu").read_bytes()
        with zipfile.ZipFile(built.path) as archive:
            names = set(archive.namelist())
        assert NATIVE_FMI2.binary_entry(built.name) in names
        assert {"sources/framework.c", "sources/fmi2.c", "sources/variables.h"} <= names
    assert not list(tmp_path.glob("*.partial"))


def test_the_binary_needs_only_the_c_library(native_fmu_dir, tmp_path):
    if shutil.which("readelf") is None:
        pytest.skip("readelf is not installed")
    with zipfile.ZipFile(native_fmu_dir / "Vehicle.fmu") as archive:
        binary = tmp_path / "Vehicle.so"
        binary.write_bytes(archive.read(NATIVE_FMI2.binary_entry("Vehicle")))
    dynamic = subprocess.run(["readelf", "-d", str(binary)], capture_output=True, text=True, check=True).stdout
    needed = sorted(line.split("[")[1].rstrip("]") for line in dynamic.splitlines() if "(NEEDED)" in line)
    assert all(name.startswith(("libm.so", "libc.so")) for name in needed), needed
    symbols = subprocess.run(["readelf", "--dyn-syms", "-W", str(binary)], capture_output=True, text=True,
                             check=True).stdout
    exported = {line.split()[-1] for line in symbols.splitlines() if " GLOBAL " in line and " UND " not in line}
    assert "fmi2DoStep" in exported and not any(symbol.startswith("fw_") for symbol in exported)


# --- (b) standalone: every output, both kinds -----------------------------------------------------------

# a robot on the paper's 1 m circle, turning hard towards a target 0.6 m ahead that circles at 0.3 m/s
M3PI_CHASE = {"dynamics": "m3pi", "k_v": 2.0, "v_c": 0.3, "d_star": 0.6, "initial.x": 1.0, "initial.y": -0.6,
              "initial.heading": 2.5, "initial.speed": 0.25, "target.x": 1.0, "target.y": 0.0,
              "target.heading": 1.5707963267948966, "target.speed": 0.3, "target.turn_rate": 0.3,
              "follower.speed": 0.3, "follower.gap": 0.6}
VEHICLE_CASES = [
    {"law": law, "dynamics": dynamics, "coupling": coupling}
    for law in ("sine", "regular") for dynamics in ("kinematic", "m3pi") for coupling in ("extrapolate", "hold")
] + [
    {"is_last": False, "d_star": 60.0, "k_v": 2.0},  # the speed chain: V_cmd from the follower's speed and gap
    {"dynamics": "m3pi", "m3pi.wheel_speed_max": 26.0, "initial.speed": 24.0},  # the wheel limits bite
    {"is_last": False, "d_star": 90.0, "k_v": 2.0, "speed_max": 27.0},  # the kinematic speed limit bites (V_cmd 30)
] + [  # a robot that is not its nominal model (docs/model.md), on the m3pi's scale: its own wheel gains, a dead-band
    # the inner wheel's commands fall into while it turns hard at the start (2 mm off the path without it), and
    # the live run's sampled loop with the radio's and the motion capture's latencies (no multiple of the step)
    {**M3PI_CHASE, "m3pi.wheel_gain_right": 1.08, "m3pi.wheel_gain_left": 0.93, "m3pi.wheel_deadband": 0.2, **loop}
    for loop in ({}, {"m3pi.command_latency": 0.025}, {"m3pi.command_latency": 0.03, "m3pi.pose_latency": 0.0075})
] + [  # the speed laws beyond the paper's: the sensed gap (sensor.*, dead-reckoned like target.*) and target.speed
    {"speed_law": law, "dynamics": dynamics, "time_gap": 1.5, "standstill_gap": 30.0, "cacc_gain": 0.4,
     "m3pi.wheel_speed_max": 30.0}  # the wheels of a car: the default target runs at 25 m/s
    for law in ("acc", "cacc") for dynamics in ("kinematic", "m3pi")
]
TARGET_CASES = [
    {"path.kind": kind, "coupling": coupling} for kind in ("circle", "line") for coupling in ("extrapolate", "hold")
] + [
    {"path.direction": -1, "path.radius": 80.0, "path.x0": 3.0, "path.heading": 0.7, "initial.arc_length": 5.0},
    {"path.kind": "line", "path.heading": -2.0, "path.y0": -4.0},
    {"speed_law": "acc", "v_c": 20.0},  # under acc and cacc the target moves at v_c
    {"speed_law": "cacc", "disturbance.speed": 0.7},  # plus its push
    {"path.kind": "line", "disturbance.speed": -0.4},  # the paper's target: V_1 d*/d_1 plus its push
]


def _compare(native, python) -> float:
    assert native.dtype.names == python.dtype.names and len(native) == len(python)
    worst = 0.0
    for name in native.dtype.names:
        assert np.all(np.isfinite(native[name])), name
        worst = max(worst, float(np.max(np.abs(native[name] - python[name]))))
    return worst


@pytest.mark.parametrize("name, start_values", [("Vehicle", case) for case in VEHICLE_CASES]
                         + [("VirtualTarget", case) for case in TARGET_CASES], ids=repr)
def test_standalone_trajectory_equals_the_python_fmus(fmu_dir, native_fmu_dir, name, start_values):
    """FMPy's simulate_fmu over the default experiment (60 s), output every 0.01 s: every output of
    the native FMU equals the pythonfmu FMU's."""
    kwargs = {"start_values": start_values, "output_interval": 0.01}
    native = simulate_fmu(str(native_fmu_dir / f"{name}.fmu"), **kwargs)
    python = simulate_fmu(str(fmu_dir / f"{name}.fmu"), **kwargs)
    assert len(native) == 6001
    assert _compare(native, python) <= TOLERANCE


@pytest.mark.parametrize("name, start_values", [("Vehicle", {"law": "regular", "dynamics": "m3pi"}),
                                                  ("Vehicle", {}), ("Vehicle", {"speed_max": 24.0}),
                                                  ("VirtualTarget", {})], ids=repr)
def test_identical_to_the_last_bit(fmu_dir, native_fmu_dir, name, start_values):
    """Stronger than the 1e-9 above: the C does Python's operations in Python's order, calls the
    same libm, and computes math.hypot with CPython's own algorithm (glibc's hypot differs in the
    last bit for 0.19 % of arguments: fmus/native/pymath.h), so every output is the same double.
    A reordered sum or glibc's hypot anywhere in the C shows up here first."""
    kwargs = {"start_values": start_values, "output_interval": 0.01}
    native = simulate_fmu(str(native_fmu_dir / f"{name}.fmu"), **kwargs)
    python = simulate_fmu(str(fmu_dir / f"{name}.fmu"), **kwargs)
    assert _compare(native, python) == 0.0


@pytest.mark.parametrize("name, signals", [
    ("Vehicle", {"disturbance.lateral_acceleration": 3.0, "disturbance.speed": -2.0, "target.turn_rate": 0.1}),
    ("VirtualTarget", {"lead.speed": 30.0, "lead.gap": 70.0, "lead.gap_rate": 0.5, "disturbance.speed": 1.5}),
])
def test_standalone_with_input_pulses_equals_the_python_fmus(fmu_dir, native_fmu_dir, name, signals):
    """Inputs that change during the run (a pulse on each from 10 s to 12 s)."""
    times = [0.0, 10.0, 10.0, 12.0, 12.0, 30.0]
    pulse_on = [False, False, True, True, False, False]  # FMPy takes the later of two rows at one time
    starts = {v.name: float(v.start) for v in read_model_description(str(fmu_dir / f"{name}.fmu")).modelVariables
              if v.causality == "input"}
    dtype = [("time", np.float64)] + [(key, np.float64) for key in signals]
    inputs = np.array([tuple([t] + [value if on else starts[key] for key, value in signals.items()])
                       for t, on in zip(times, pulse_on)], dtype=dtype)
    kwargs = {"input": inputs, "stop_time": 30.0, "output_interval": 0.01}
    native = simulate_fmu(str(native_fmu_dir / f"{name}.fmu"), **kwargs)
    python = simulate_fmu(str(fmu_dir / f"{name}.fmu"), **kwargs)
    assert _compare(native, python) <= TOLERANCE
    assert not np.array_equal(native[native.dtype.names[1]], simulate_fmu(
        str(native_fmu_dir / f"{name}.fmu"), stop_time=30.0, output_interval=0.01)[native.dtype.names[1]])


# --- (c) a platoon stepped by our master ----------------------------------------------------------------

PLATOONS = [
    {"platoon": {"count": 3, "law": "sine"}, "simulation": {"coupling": "extrapolate", "master": "jacobi"}},
    {"platoon": {"count": 3, "law": "regular", "dynamics": "m3pi", "speed": 0.35, "d_star": 0.7, "k_v": 2.0},
     "path": {"radius": 1.0}, "simulation": {"coupling": "hold", "master": "gauss-seidel"}},
    {"platoon": {"count": 3, "law": "sine"}, "path": {"kind": "line", "heading": 0.3},
     "simulation": {"coupling": "extrapolate", "master": "gauss-seidel"}},
    {"platoon": {"count": 3, "law": "sine", "speed_law": "acc", "k_v": 1.0, "time_gap": 2.5},
     "simulation": {"coupling": "extrapolate", "master": "jacobi"}},
    {"platoon": {"count": 3, "law": "regular", "dynamics": "m3pi", "speed": 0.35, "d_star": 0.7,
                 "k_v": 2.0, "time_gap": 1.0}, "path": {"radius": 1.0},
     "simulation": {"coupling": "hold", "master": "gauss-seidel"}, "vehicles": {"3": {"speed_law": "cacc"}}},
    # three robots unlike their model and unlike each other (docs/config.md, [vehicles.N.m3pi]), in the live run's
    # sampled loop
    {"platoon": {"count": 3, "law": "sine", "dynamics": "m3pi", "speed": 0.35, "d_star": 0.7, "k_v": 2.0},
     "path": {"radius": 1.0}, "simulation": {"coupling": "extrapolate", "master": "jacobi"},
     "m3pi": {"wheel_gain_right": 1.06, "wheel_gain_left": 0.95, "wheel_deadband": 0.02, "command_latency": 0.02},
     "vehicles": {"2": {"m3pi": {"wheel_gain_left": 1.1, "pose_latency": 0.0125, "motor_time_constant": 0.08}},
                  "3": {"m3pi": {"command_latency": 0.0, "wheel_deadband": 0.0}}}},
]


def _run_platoon(scenario, folder) -> list[list[list[float]]]:
    fmus = {name: UnpackedFmu.open(folder / f"{name}.fmu") for name in NAMES}
    components = [FmuComponent(spec.name, fmus[spec.fmu], spec.parameters) for spec in scenario.components]
    sim = scenario.config.simulation
    master = Master(components, scenario.connections, scenario.schedules, sim.master)
    points: list[list[list[float]]] = []
    try:
        master.run(sim.stop_time, sim.step, lambda t, outputs: points.append([list(o) for o in outputs]),
                   step_count(sim.stop_time, sim.step))
    finally:
        master.close()
        for fmu in fmus.values():
            fmu.cleanup()
    return points


@pytest.mark.parametrize("sections", PLATOONS, ids=["sine-extrapolate-jacobi", "m3pi-regular-hold-gs", "line", "acc",
                                                    "m3pi-paper-then-cacc-hold-gs", "m3pi-robots-unlike-their-model"])
def test_platoon_through_our_master_equals_the_python_fmus(fmu_dir, native_fmu_dir, sections):
    """A virtual target and three vehicles, wired as Fig. 2 (orchestrator.scenario.wiring), a lateral pulse on
    vehicle 2, a speed pulse on vehicle 3 and a speed sinusoid on the target, 20 s: every output of every component at every
    communication point agrees."""
    raw = {"name": "native", "simulation": {"stop_time": 20.0, "step": 0.01}, "initial": {
        "radial_offset": 0.1 if "radius" in sections.get("path", {}) else 5.0, "heading_error": 0.1,
        "speed_factor": 0.8},
        "disturbance": [{"vehicle": 2, "kind": "lateral_acceleration", "start": 5.0, "duration": 1.0, "value": 0.5},
                        {"vehicle": 3, "kind": "speed", "start": 8.0, "duration": 1.0, "value": 0.05},
                        {"vehicle": 0, "kind": "speed", "start": 3.0, "duration": 10.0, "value": 0.05,
                         "frequency": 1.0}]}
    for key, value in sections.items():
        raw[key] = {**raw.get(key, {}), **value}
    scenario = build_scenario(config_from_mapping(raw))
    native = _run_platoon(scenario, native_fmu_dir)
    python = _run_platoon(scenario, fmu_dir)
    assert len(native) == len(python) == 2001
    worst = max(abs(a - b) for n, p in zip(native, python) for cn, cp in zip(n, p) for a, b in zip(cn, cp))
    assert worst <= TOLERANCE
    # Stronger: the same doubles. In a platoon each step starts at its inputs' sample instant and the
    # outputs follow a step, the two places where the C step takes exact shortcuts the Python model
    # does not (science.h's arc_extrapolate at dt = 0, vehicle.c's step memo); this holds them exact.
    assert worst == 0.0
    # the pulse reached vehicle 2: its lateral acceleration (output 6) jumps by about 0.5 m/s^2 at 5 s
    assert scenario.components[2].name == "vehicle2"
    assert abs(native[501][2][6] - native[500][2][6] - 0.5) < 0.1


# --- (e) libcosim runs them ------------------------------------------------------------------------------


def test_libcosim_runs_the_native_fmus_as_it_runs_the_python_ones(fmu_dir, native_fmu_dir):
    """The paper platoon (4 vehicles, a pulse) in libcosim, once with each kind: every output of
    every component at every communication point agrees, and libcosim logs no complaint."""
    pytest.importorskip("libcosimpy")
    from tests.test_libcosim import DISTURBANCES, paper_config, run_libcosim

    scenario = build_scenario(paper_config(disturbance=DISTURBANCES, stop_time=10.0))
    native, native_log, _ = run_libcosim(scenario, {name: native_fmu_dir / f"{name}.fmu" for name in NAMES})
    python, _, _ = run_libcosim(scenario, {name: fmu_dir / f"{name}.fmu" for name in NAMES})
    assert native_log.strip() == ""
    worst = 0.0
    for component, channel in python.items():
        for output, values in channel.items():
            assert np.all(np.isfinite(native[component][output]))
            worst = max(worst, float(np.max(np.abs(native[component][output] - values))))
    assert len(native["vehicle1"]["x"]) == 1001
    assert worst <= TOLERANCE


def test_build_without_a_compiler_says_so_in_one_line(tmp_path):
    """platoon build on a machine without cc: the pythonfmu FMUs are built, the native ones are
    skipped with one line saying why, exit status 0."""
    env = dict(os.environ, PATH=str(tmp_path), CC="")
    script = "import sys; from orchestrator.cli.app import main; sys.argv = ['platoon', 'build', '--out', sys.argv[1]]; main()"
    out = tmp_path / "fmus"
    result = subprocess.run([sys_executable(), "-c", script, str(out)], capture_output=True, text=True, env=env,
                            timeout=600, cwd=os.getcwd())
    assert result.returncode == 0, result.stderr
    assert (out / "Vehicle.fmu").is_file() and not (out / "native").exists()
    assert result.stderr.count("\n") == 1 and "no C compiler found" in result.stderr, result.stderr


def sys_executable() -> str:
    import sys

    return sys.executable


# --- the C helpers that make the numbers and the messages Python's ------------------------------------


@pytest.fixture(scope="module")
def c_helpers(tmp_path_factory):
    """fmus/native/pymath.h's py_hypot, science.h's wrap_angle and arc_extrapolate, and framework.c's
    fw_text_float, compiled as the FMUs are."""
    import ctypes

    from fmus.builders.toolchain import CFLAGS, NATIVE_SOURCES, NoCompiler, compiler

    try:
        cc = compiler()
    except NoCompiler as error:
        pytest.skip(str(error))
    folder = tmp_path_factory.mktemp("c_helpers")
    (folder / "probe.c").write_text(
        '#include "science.h"\n#include "framework.h"\n#include <string.h>\n'
        "double probe_hypot(double x, double y) { return py_hypot(x, y); }\n"
        "double probe_wrap(double angle) { return wrap_angle(angle); }\n"
        "void probe_arc(double x, double y, double heading, double speed, double speed_rate, double turn_rate,\n"
        "               double dt, double *out) { arc_extrapolate(x, y, heading, speed, speed_rate, turn_rate, dt, out); }\n"
        "void probe_repr(double x, char *out) { FwText t; fw_text_clear(&t); fw_text_float(&t, x); strcpy(out, t.text); }\n")
    library = folder / "probe.so"
    subprocess.run([cc, *[flag for flag in CFLAGS if flag != "-fvisibility=hidden"], f"-I{NATIVE_SOURCES}",
                    str(folder / "probe.c"), str(NATIVE_SOURCES / "framework.c"), "-o", str(library), "-lm"],
                   check=True, capture_output=True)
    probe = ctypes.CDLL(str(library))
    probe.probe_hypot.restype = ctypes.c_double
    probe.probe_hypot.argtypes = [ctypes.c_double, ctypes.c_double]
    probe.probe_repr.argtypes = [ctypes.c_double, ctypes.c_char_p]
    probe.probe_wrap.restype = ctypes.c_double
    probe.probe_wrap.argtypes = [ctypes.c_double]
    probe.probe_arc.argtypes = [ctypes.c_double] * 7 + [ctypes.POINTER(ctypes.c_double)]
    return probe


def test_py_hypot_is_pythons_math_hypot_to_the_last_bit(c_helpers):
    """glibc's hypot differs from math.hypot in the last bit for about 0.2 % of arguments; py_hypot
    never does: 200 000 random pairs over the whole range of doubles, and the edge cases."""
    import math
    import random

    generator = random.Random(21)
    pairs = [(generator.uniform(-1, 1) * 10.0 ** generator.uniform(-3, 3),
              generator.uniform(-1, 1) * 10.0 ** generator.uniform(-3, 3)) for _ in range(100_000)]
    pairs += [(generator.uniform(-1, 1) * 10.0 ** generator.uniform(-310, 308),
               generator.uniform(-1, 1) * 10.0 ** generator.uniform(-310, 308)) for _ in range(100_000)]
    pairs += [(0.0, 0.0), (-0.0, 5e-324), (5e-324, 5e-324), (1e-310, 2.2250738585072014e-308), (3.0, 4.0),
              (1e308, 1e308), (1.7e308, 1.7e308), (math.inf, math.nan), (math.nan, 1.0), (-math.inf, 0.0)]
    wrong = [(x, y) for x, y in pairs
             if not (c_helpers.probe_hypot(x, y) == math.hypot(x, y)
                     or math.isnan(c_helpers.probe_hypot(x, y)) and math.isnan(math.hypot(x, y)))]
    assert wrong == []


def _same_bits(a: float, b: float) -> bool:
    """Equal as doubles, the sign of a zero included (NaNs equal each other)."""
    import struct

    return struct.pack("<d", a) == struct.pack("<d", b) or (a != a and b != b)


def test_wrap_angle_skips_fmod_only_where_fmod_is_the_identity(c_helpers):
    """The C wrap_angle calls fmod only for angles of a turn or more (fmod(x, 2 pi) is x itself below
    that, exactly): the same doubles as fmus.model.angles.wrap_angle, signed zeros included, on both
    sides of every boundary and over many turns."""
    import math
    import random

    from fmus.model.angles import TWO_PI, wrap_angle

    generator = random.Random(7)
    angles = [generator.uniform(-1, 1) * 10.0 ** generator.uniform(-6, 4) for _ in range(50_000)]
    for edge in (TWO_PI, math.pi, 0.0, 3 * math.pi, 1e300):
        for value in (edge, math.nextafter(edge, 0.0), math.nextafter(edge, math.inf)):
            angles += [value, -value]
    wrong = [a for a in angles if not _same_bits(c_helpers.probe_wrap(a), wrap_angle(a))]
    assert wrong == []


def test_arc_extrapolate_at_the_sample_instant_is_pythons(c_helpers):
    """At dt = 0 (each step starts where its inputs were sampled) the C arc_extrapolate returns the
    sample without computing cos and sin: the same doubles as fmus.model.coupling.arc_extrapolate,
    also for zero coordinates or headings of either sign, a standstill, a curvature that overflows,
    and around dt = 0."""
    import ctypes
    import itertools
    import random

    from fmus.model.coupling import arc_extrapolate

    generator = random.Random(11)
    cases = [(x, y, heading, speed, rate, turn_rate, dt)
             for x, y, heading in itertools.product((0.0, -0.0, 1.5, -2e-300), (0.0, -0.0, 7.0), (0.0, -0.0, 2.0, 40.0))
             for speed, rate, turn_rate in ((20.0, 0.5, 0.3), (0.0, 1.0, 0.2), (1e-320, 0.0, 1.0), (-3.0, -1.0, -0.1))
             for dt in (0.0, -0.0, 5e-324, -0.01, 0.005)]
    cases += [tuple(generator.uniform(-100, 100) for _ in range(6)) + (generator.choice((0.0, 0.01)),)
              for _ in range(20_000)]
    out = (ctypes.c_double * 4)()
    wrong = []
    for case in cases:
        try:
            expected = arc_extrapolate(*case)
        except ValueError:  # sin(inf) of an overflowed turn, away from dt = 0: refused by either FMU
            assert case[-1] != 0.0 and case[3] == 1e-320
            continue
        c_helpers.probe_arc(*case, out)
        if not all(_same_bits(a, b) for a, b in zip(out, expected)):
            wrong.append(case)
    assert wrong == []


def test_reasons_print_numbers_as_python_does(c_helpers):
    """The native FMUs' refusals quote values as the pythonfmu FMUs' do (repr of a float)."""
    import ctypes
    import math

    values = [0.0, -0.0, -1.0, 75.0, 0.01, 1e-05, 0.0001, 1e16, 1e15, 123456789012345.6, 2.5e-300, 1e308,
              -43.30127018922194, 1 / 3, math.inf, -math.inf, math.nan, 100.0, 5e-324]
    buffer = ctypes.create_string_buffer(64)
    for value in values:
        c_helpers.probe_repr(value, buffer)
        assert buffer.value.decode() == repr(value)


# --- NULL pointers, wrong references, wrong types, a double free: fmi2Error, never a crash ------------

_CARELESS_HOST = r'''
import ctypes, json, sys
from ctypes import POINTER, byref, c_char_p, c_double, c_int, c_size_t, c_uint, c_void_p
lib = ctypes.CDLL(sys.argv[1])
guid = sys.argv[2].encode()
# the logger is variadic; its first three arguments after the format come as the next parameters (x86-64
# passes them in registers like any others); every format the FMU logs with holds only %s
LOGGER = ctypes.CFUNCTYPE(None, c_void_p, c_char_p, c_int, c_char_p, c_char_p, c_void_p, c_void_p, c_void_p)
logs = []
def log(env, name, status, category, message, *args):
    text = message.decode()
    for argument in args[:text.count("%s")]:
        text = text.replace("%s", ctypes.string_at(argument).decode(), 1)
    logs.append(text)
logger = LOGGER(log)
class Callbacks(ctypes.Structure):
    _fields_ = [("logger", LOGGER), ("allocate", c_void_p), ("free", c_void_p), ("finished", c_void_p),
                ("environment", c_void_p)]
callbacks = Callbacks(logger, None, None, None, None)
lib.fmi2Instantiate.restype = c_void_p
lib.fmi2Instantiate.argtypes = [c_char_p, c_int, c_char_p, c_char_p, POINTER(Callbacks), c_int, c_int]
for name in ("fmi2GetReal", "fmi2SetReal", "fmi2GetString", "fmi2SetString", "fmi2DoStep", "fmi2FreeInstance",
             "fmi2ExitInitializationMode", "fmi2EnterInitializationMode", "fmi2GetFMUstate", "fmi2SetFMUstate",
             "fmi2GetBoolean", "fmi2DeSerializeFMUstate", "fmi2SerializedFMUstateSize"):
    getattr(lib, name).argtypes = None
lib.fmi2DoStep.argtypes = [c_void_p, c_double, c_double, c_int]
statuses = {}
def record(key, value):
    statuses[key] = value
    print(json.dumps({key: value}), flush=True)
record("instantiate with a wrong GUID", lib.fmi2Instantiate(b"x", 1, b"{wrong}", b"", byref(callbacks), 0, 0) is None)
record("instantiate as model exchange", lib.fmi2Instantiate(b"x", 0, guid, b"", byref(callbacks), 0, 0) is None)
record("instantiate without callbacks", lib.fmi2Instantiate(b"x", 1, guid, b"", None, 0, 0) is None)
c = c_void_p(lib.fmi2Instantiate(b"x", 1, guid, b"", byref(callbacks), 0, 0))
refs, values = (c_uint * 2)(0, 1), (c_double * 2)()
record("doStep(NULL)", lib.fmi2DoStep(None, 0.0, 0.01, 1))
record("getReal(NULL instance)", lib.fmi2GetReal(None, refs, c_size_t(1), values))
record("getReal of reference 999", lib.fmi2GetReal(c, (c_uint * 1)(999), c_size_t(1), values))
record("getReal with NULL arrays", lib.fmi2GetReal(c, None, c_size_t(2), None))
record("getReal of a String", lib.fmi2GetReal(c, (c_uint * 1)(0), c_size_t(1), values))
record("getBoolean of a Real", lib.fmi2GetBoolean(c, (c_uint * 1)(1), c_size_t(1), (c_int * 1)()))
record("setString with a NULL value", lib.fmi2SetString(c, (c_uint * 1)(0), c_size_t(1), (c_char_p * 1)(None)))
record("setFMUstate(NULL)", lib.fmi2SetFMUstate(c, None))
record("setFMUstate(the instance)", lib.fmi2SetFMUstate(c, c))
record("deSerialize(NULL bytes)", lib.fmi2DeSerializeFMUstate(c, None, c_size_t(8), byref(c_void_p())))
record("serializedSize(NULL state)", lib.fmi2SerializedFMUstateSize(c, None, byref(c_size_t())))
lib.fmi2EnterInitializationMode(c)
record("exit", lib.fmi2ExitInitializationMode(c))
record("setReal of an output", lib.fmi2SetReal(c, (c_uint * 1)(29), c_size_t(1), (c_double * 1)(1.0)))
record("setReal of a parameter after initialization", lib.fmi2SetReal(c, (c_uint * 1)(1), c_size_t(1), (c_double * 1)(1.0)))
record("doStep", lib.fmi2DoStep(c, 0.0, 0.01, 1))
lib.fmi2FreeInstance(c)
lib.fmi2FreeInstance(c)  # again
record("doStep on a freed instance", lib.fmi2DoStep(c, 0.01, 0.01, 1))
record("logs", logs)
'''


def test_careless_calls_are_refused_and_never_crash(native_fmu_dir, tmp_path):
    """A host in a process of its own calls the native Vehicle's binary with NULL pointers, unknown
    value references, wrong types, an output or a fixed parameter to set, a freed instance: each
    call answers fmi2Error (3) or NULL, the reasons are logged, the process ends normally."""
    import json
    import sys

    with zipfile.ZipFile(native_fmu_dir / "Vehicle.fmu") as archive:
        binary = tmp_path / "Vehicle.so"
        binary.write_bytes(archive.read(NATIVE_FMI2.binary_entry("Vehicle")))
    guid = read_model_description(str(native_fmu_dir / "Vehicle.fmu")).guid
    result = subprocess.run([sys.executable, "-c", _CARELESS_HOST, str(binary), guid], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    statuses = {key: value for line in result.stdout.splitlines() for key, value in json.loads(line).items()}
    logs = statuses.pop("logs")
    assert statuses.pop("exit") == statuses.pop("doStep") == 0  # the instance worked in between
    instantiated = {key: statuses.pop(key) for key in list(statuses) if key.startswith("instantiate")}
    assert all(instantiated.values()), instantiated  # each refused: NULL
    assert statuses == {key: 3 for key in statuses}, statuses
    for reason in ("does not match this binary's", "fmi2ModelExchange is not supported", "no variable has value reference 999",
                   "law (value reference 0) is a String, not a Real", "x is an output", "d_star: a parameter is fixed",
                   "the value of law is NULL", "the FMU state: it is NULL", "not a live FMU state"):
        assert any(reason in line for line in logs), (reason, logs)
