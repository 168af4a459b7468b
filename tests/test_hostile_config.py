"""Configs and command line under hostile input: exit 2 and one clear line, never a
traceback, a hang, a write outside runs/ or a temp folder left behind.

Where the user meets a case it is a real ``platoon`` subprocess (with PYTHONPATH set to this
repository, so that a worktree tests its own code, not the installed one); where the rule itself is
tested, the config loader is called directly.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import typing
import zipfile
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel

from fmus.builders import ALL_FMUS, FMU_NAMES, PYTHONFMU
from orchestrator.scenario.config import Config, ConfigError, config_from_mapping, load_config, parse_value
from orchestrator.scenario.limits import MAX_FMU_SUBSTEPS, MAX_STEPS, MAX_SUBSTEPS_PER_STEP, check_run_size, run_size
from orchestrator.support.scratch import ScratchDir, sweep
from orchestrator.trace import load
from tests.test_cli import error_line

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = REPO / "configs" / "paper" / "platoon.toml"
SHORT = ("--set", "simulation.stop_time=1.0")


def platoon(*args: object, cwd: Path, timeout: float = 120, env: dict[str, str] | None = None
            ) -> subprocess.CompletedProcess[str]:
    """The console script as a user runs it (no terminal, no colour), on this repository's code."""
    environment = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb", "PYTHONPATH": str(REPO),
                   **(env or {})}
    environment.pop("FORCE_COLOR", None)
    return subprocess.run([str(PLATOON), *map(str, args)], cwd=cwd, env=environment, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Current folder of every call; its build/fmus is built once here, from this repository."""
    folder = tmp_path_factory.mktemp("hostile")
    PYTHONFMU.build(folder / "build" / "fmus")
    return folder


def refused(result: subprocess.CompletedProcess[str], *pieces: str) -> str:
    """Exit 2, one ``error:`` line, no traceback, holding every piece; returns the line."""
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    line = error_line(result)
    for piece in pieces:
        assert piece in line, f"{piece!r} missing from {line!r}"
    return line


# --- 6: every float key is finite, every key has a range ------------------------------------------

DISTURBANCE = {"vehicle": 1, "kind": "speed", "start": 1.0, "duration": 1.0, "value": 1.0}
INITIAL = {"x": 0.0, "y": -50.0, "heading": 0.0, "speed": 20.0}
# Every float key of the config, with the mapping that reaches it (a disturbance or an initial state
# needs its other keys). test_every_float_key_is_listed keeps this list complete.
FLOAT_KEYS = [
    "simulation.stop_time", "simulation.step", "simulation.max_substep",
    "path.radius", "path.center[0]", "path.center[1]", "path.heading",
    "platoon.d_star", "platoon.k_v", "platoon.speed",
    "platoon.time_gap", "platoon.standstill_gap", "platoon.cacc_gain", "platoon.speed_max",
    "initial.radial_offset", "initial.heading_error", "initial.speed_factor",
    "m3pi.track", "m3pi.wheel_speed_max", "m3pi.motor_time_constant",
    "m3pi.wheel_gain_right", "m3pi.wheel_gain_left", "m3pi.wheel_deadband", "m3pi.command_latency", "m3pi.pose_latency",
    "disturbance[0].start", "disturbance[0].duration", "disturbance[0].value", "disturbance[0].frequency",
    "vehicles.1.k_v", "vehicles.1.initial.x", "vehicles.1.initial.y", "vehicles.1.initial.heading",
    "vehicles.1.initial.speed",
] + [f"vehicles.1.m3pi.{key}" for key in ("track", "wheel_speed_max", "motor_time_constant", "wheel_gain_right",
                                          "wheel_gain_left", "wheel_deadband", "command_latency", "pose_latency")] + [
    "hil.pose_timeout", "hil.connect_timeout", "hil.command_validity", "hil.max_pose_age",
    "remote.step_timeout", "remote.connect_timeout",
    "vehicles.1.ros2.frame.x", "vehicles.1.ros2.frame.y", "vehicles.1.ros2.frame.yaw", "ros2.rate",
    "validity.min_gap", "validity.max_speed",
] + [f"links.{table}{key}" for table in ("", "backward.", "forward.", "vehicles.1.backward.", "vehicles.1.forward.")
     for key in ("delay", "jitter", "period", "loss", "burst")]


def mapping_with(key: str, value: Any) -> dict[str, Any]:
    """A valid config mapping with ``key`` (dotted, [i] for a list item) set to ``value``."""
    raw: dict[str, Any] = {"name": "hostile", "disturbance": [dict(DISTURBANCE)],
                           "vehicles": {"1": {"initial": dict(INITIAL)}}}
    node: Any = raw
    parts = key.replace("[", ".").replace("]", "").split(".")
    for part, following in zip(parts, parts[1:]):
        index = int(part) if part.isdigit() and isinstance(node, list) else part
        if isinstance(node, dict) and index not in node:
            node[index] = [0.0, 0.0] if following.isdigit() and part == "center" else {}
        node = node[index]
    last = parts[-1]
    node[int(last) if isinstance(node, list) else last] = value
    return raw


def float_keys_of(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every float key under ``model``, found from the declarations (lists and tables given one item)."""
    keys = []
    for name, field in model.model_fields.items():
        annotation = field.annotation
        key = f"{prefix}{name}"
        while typing.get_origin(annotation) in (typing.Union, getattr(__import__("types"), "UnionType", None)):
            annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
        origin, args = typing.get_origin(annotation), typing.get_args(annotation)
        if typing.get_origin(annotation) is typing.Annotated:
            annotation = args[0]
        if origin is list:
            element = args[0]
            element = typing.get_args(element)[0] if typing.get_origin(element) is typing.Annotated else element
            if element is float:
                keys += [f"{key}[0]", f"{key}[1]"]
            elif isinstance(element, type) and issubclass(element, BaseModel):
                keys += float_keys_of(element, f"{key}[0].")
        elif origin is dict:
            keys += float_keys_of(args[1], f"{key}.1.")
        elif annotation is float:
            keys.append(key)
        elif isinstance(annotation, type) and issubclass(annotation, BaseModel):
            keys += float_keys_of(annotation, f"{key}.")
    return keys


def test_every_float_key_is_listed() -> None:
    assert sorted(float_keys_of(Config)) == sorted(FLOAT_KEYS)


def test_the_base_mapping_is_valid() -> None:
    config_from_mapping(mapping_with("platoon.k_v", 0.5))


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")], ids=["inf", "-inf", "nan"])
@pytest.mark.parametrize("key", FLOAT_KEYS)
def test_no_float_key_accepts_inf_or_nan(key: str, value: float) -> None:
    with pytest.raises(ConfigError) as raised:
        config_from_mapping(mapping_with(key, value))
    message = str(raised.value)
    assert message.startswith(f"{key} = {value!r}: must be a finite number"), message


# key, a value just outside its range, the range the message states, a value just inside it
RANGES = [
    ("simulation.stop_time", 0.0, "a finite number > 0 s", 1.0),
    ("simulation.max_substep", -0.01, "a finite number > 0 s", 0.001),
    ("path.radius", 1.1e6, "a finite number >= 0.001 m and <= 1e+06 m", 1e6),
    ("path.center[0]", -2e6, "a finite number >= -1e+06 m and <= 1e+06 m", -1e6),
    ("path.heading", 7.0, "a finite number >= -6.28319 rad and <= 6.28319 rad (radians: 90 degrees = 1.5708 rad)", -6.0),
    ("platoon.d_star", 0.0, "a finite number >= 0.001 m and <= 1e+06 m", 1e-3),
    ("platoon.k_v", 1001.0, "a finite number >= 0.001 1/s and <= 1000 1/s", 200.0),  # 1000 needs a smaller substep
    ("platoon.k_v", 1e-200, "a finite number >= 0.001 1/s and <= 1000 1/s", 1e-3),  # analyze divided by k_v^2 = 0
    ("platoon.speed", 1e4, "a finite number >= 0.001 m/s and <= 1000 m/s", 1000.0),
    ("platoon.speed", 1e-300, "a finite number >= 0.001 m/s and <= 1000 m/s", 1e-3),
    ("platoon.count", 10001, "an integer >= 1 and <= 10000", 10000),
    ("initial.radial_offset", 1e7, "a finite number >= -1e+06 m and <= 1e+06 m", -1e6),
    ("initial.speed_factor", 11.0, "a finite number >= 0.001 and <= 10", 10.0),
    ("m3pi.track", 0.0, "a finite number >= 0.001 m and <= 10 m", 0.2),
    ("m3pi.motor_time_constant", 1e-9, "a finite number >= 0.001 s and <= 100 s", 1e-3),
    ("m3pi.wheel_gain_left", 0.05, "a finite number >= 0.1 and <= 10", 0.1),
    ("m3pi.wheel_deadband", -0.001, "a finite number >= 0 m/s and <= 100 m/s", 0.0),
    ("m3pi.command_latency", 1.5, "a finite number >= 0 s and <= 1 s", 1.0),
    ("vehicles.1.m3pi.pose_latency", -1e-3, "a finite number >= 0 s and <= 1 s", 0.015),
    ("vehicles.1.m3pi.wheel_gain_right", 11.0, "a finite number >= 0.1 and <= 10", 10.0),
    ("disturbance[0].start", -1.0, "a finite number >= 0 s", 0.0),
    ("disturbance[0].value", -1e7, 'a finite number >= -1e+06 and <= 1e+06 (m/s² for kind = "lateral_acceleration", '
     'm/s for kind = "speed")', -1e6),
    ("vehicles.1.k_v", 0.0, "a finite number >= 0.001 1/s and <= 1000 1/s", 2.0),
    ("vehicles.1.initial.speed", 0.0, "a finite number >= 0.001 m/s and <= 1000 m/s", 1e-3),
    ("vehicles.1.initial.heading", -7.0, "a finite number >= -6.28319 rad and <= 6.28319 rad (radians: 90 degrees = 1.5708 rad)", 3.0),
    ("hil.pose_timeout", 6.0, "a finite number > 0 s and <= 5 s", 5.0),
    ("remote.step_timeout", 0.0, "a finite number > 0 s and <= 600 s", 0.05),
    ("validity.min_gap", -1.0, "a finite number >= 0 m and <= 1e+06 m", 0.0),
    ("validity.max_speed", 2000.0, "a finite number >= 0.001 m/s and <= 1000 m/s", 1000.0),
]


@pytest.mark.parametrize("key, outside, expected, inside", RANGES, ids=[f"{r[0]}={r[1]}" for r in RANGES])
def test_each_key_states_its_range(key: str, outside: Any, expected: str, inside: Any) -> None:
    with pytest.raises(ConfigError) as raised:
        config_from_mapping(mapping_with(key, outside))
    assert str(raised.value) == f"{key} = {outside!r}: must be {expected}"
    config_from_mapping(mapping_with(key, inside))


@pytest.mark.parametrize("assignments, key, limit", [
    (["platoon.k_v=1000"], "platoon.k_v (time constant 0.001 s)", "max_substep <= 0.002 s"),
    (["vehicles.2.k_v=500"], "vehicles.2.k_v (time constant 0.002 s)", "max_substep <= 0.004 s"),
    (["platoon.dynamics=m3pi", "m3pi.motor_time_constant=0.001"], "m3pi.motor_time_constant (time constant 0.001 s)",
     "max_substep <= 0.002 s"),
])
def test_a_lag_faster_than_the_substep_is_refused_not_blamed_on_another_component(
        assignments: list[str], key: str, limit: str, workdir: Path, tmp_path: Path) -> None:
    """RK4 diverged on these and the run failed later, at the m3pi motor as a NaN in the *target*."""
    sets = [arg for assignment in assignments for arg in ("--set", assignment)]
    result = platoon("run", PAPER, *SHORT, *sets, "-q", "--out", tmp_path / "never.mcap", cwd=workdir)
    refused(result, "simulation.max_substep = 0.01: expected RK4 substeps of at most 2 x the fastest lag", key, limit)
    fine = platoon("run", PAPER, *SHORT, *sets, "--set", "simulation.max_substep=0.001", "-q", "--out",
                   tmp_path / "fine.mcap", cwd=workdir)
    assert fine.returncode == 0, fine.stderr


def test_a_fast_motor_is_no_concern_of_kinematic_vehicles() -> None:
    config_from_mapping({"m3pi": {"motor_time_constant": 0.001}})


COMMANDS = {  # every command that loads a config, with what it needs besides the config
    "run": lambda config, tmp: ["run", config, "-q", "--out", tmp / "never.mcap"],
    "analyze": lambda config, tmp: ["analyze", config],
    "m3pi-emulator": lambda config, tmp: ["m3pi-emulator", "--config", config],
    "export-ssp": lambda config, tmp: ["export-ssp", config, "--out", tmp / "never.ssp"],
    "bench scenarios": lambda config, tmp: ["bench", "scenarios", "--config", config, "--rounds", "1", "-q",
                                            "--out-dir", tmp / "bench"],
}


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("assignment, key", [
    ("simulation.stop_time=inf", "simulation.stop_time = inf"),
    ("platoon.k_v=inf", "platoon.k_v = inf"),
    ("path.center=[nan, 0.0]", "path.center[0] = nan"),
    ("path.heading=inf", "path.heading = inf"),
    ("vehicles.2.initial={x=nan, y=0.0, heading=0.0, speed=1.0}", "vehicles.2.initial.x = nan"),
])
def test_inf_and_nan_exit_2_naming_the_key_in_every_command(command: str, assignment: str, key: str, workdir: Path,
                                                              tmp_path: Path) -> None:
    result = platoon(*COMMANDS[command](PAPER, tmp_path), "--set", assignment, cwd=workdir)
    refused(result, f"config {PAPER}: {key}: must be a finite number")
    assert not (tmp_path / "never.mcap").exists()


# --- 7: absurd sizes are refused with their numbers, unless --allow-long --------------------------

PULSE = 'disturbance=[{vehicle=2, kind="speed", start=1.0, duration=1.0, value=1.0}]'  # analyze then runs it


@pytest.mark.parametrize("command", ["run", "analyze"])
@pytest.mark.parametrize("assignments, pieces", [
    (["simulation.stop_time=1e12"], ["100,000,000,000,000 steps", f"more than {MAX_STEPS:,}", "--allow-long"]),
    (["simulation.max_substep=1e-12"], ["10,000,000,000 RK4 substeps per step", f"more than {MAX_SUBSTEPS_PER_STEP:,}"]),
    (["simulation.stop_time=10000", "simulation.max_substep=0.0001"],
     ["1,000,000 steps x 100 substeps x 5 components (4 vehicles and the target) = 500,000,000 FMU-substeps",
      "more than 100,000,000"]),
    (["simulation.stop_time=4000", "platoon.count=100", "path.radius=2000", "links.delay=0.05"],  # 2 links a vehicle
     ["400,000 steps x (1 substeps x 101 components (100 vehicles and the target) + 200 link FMUs, one step each) = "
      "120,400,000 FMU-substeps", "more than 100,000,000"]),
    (["simulation.step=1e-300"], ["1e+302 steps", "at most 2**53", "no option lifts this"]),
])
def test_absurd_sizes_are_refused_with_the_numbers(command: str, assignments: list[str], pieces: list[str],
                                                   workdir: Path, tmp_path: Path) -> None:
    sets = [arg for assignment in [*assignments, PULSE] for arg in ("--set", assignment)]
    result = platoon(*COMMANDS[command](PAPER, tmp_path), *sets, cwd=workdir, timeout=60)
    refused(result, *pieces)


def test_analyze_without_a_disturbance_runs_nothing_so_needs_no_size_limit(workdir: Path) -> None:
    result = platoon("analyze", PAPER, "--set", "simulation.stop_time=1e12", cwd=workdir, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "the config has no [[disturbance]]" in result.stdout


def test_allow_long_lifts_the_size_limits(workdir: Path, tmp_path: Path) -> None:
    """1112 substeps per step is above the limit; two steps of it are quick, and run with the flag."""
    sets = ["--set", "simulation.stop_time=0.02", "--set", "simulation.max_substep=0.000009"]
    refused(platoon("run", PAPER, *sets, "-q", "--out", tmp_path / "a.mcap", cwd=workdir), "1,112 RK4 substeps per step")
    result = platoon("run", PAPER, *sets, "-q", "--allow-long", "--out", tmp_path / "a.mcap", cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert len(load(tmp_path / "a.mcap").component("vehicle1")["t"]) == 3


# scenario configs: not sweep files (configs/sweeps) nor robot truth files (configs/robots: the robot side's)
SCENARIOS = sorted(path for path in (REPO / "configs").rglob("*.toml") if not {"sweeps", "robots"} & set(path.parts))


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.name)
def test_every_shipped_config_is_within_the_size_limits(path: Path) -> None:
    check_run_size(load_config(path)[0])  # the 100-vehicle hour of configs/bench included


def test_the_limits_are_above_the_longest_shipped_run_and_below_absurd() -> None:
    bench, _ = load_config(REPO / "configs" / "bench" / "platoon100-1h.toml")
    assert bench.steps == 36_000 and 36_000 * 101 < MAX_FMU_SUBSTEPS


def test_ten_thousand_vehicles_for_the_default_100_s_are_above_the_work_limit() -> None:
    config = config_from_mapping({"platoon": {"count": 10000}, "path": {"radius": 1e6}})
    with pytest.raises(ConfigError, match=r"^10,000 steps x 1 substeps x 10,001 components \(10,000 vehicles and the "
                                          r"target\) = 100,010,000 FMU-substeps"):
        check_run_size(config)


def test_link_fmus_count_in_the_work_limit_and_the_refusal_says_so() -> None:
    """With [links] every vehicle has two more FMUs (a step each, whatever max_substep says; a link's step
    costs about a vehicle's): 4,000 vehicles for 100 s are within the limit without links, above it with."""
    mapping = {"platoon": {"count": 4000}, "path": {"radius": 1e6}}
    check_run_size(config_from_mapping(mapping))  # 10,000 x 4,001 = 40,010,000
    linked = config_from_mapping({**mapping, "links": {"delay": 0.05}})
    assert len(linked.linked()) == 8000
    with pytest.raises(ConfigError, match=r"^10,000 steps x \(1 substeps x 4,001 components \(4,000 vehicles and the "
                                          r"target\) \+ 8,000 link FMUs, one step each\) = 120,010,000 FMU-substeps"):
        check_run_size(linked)
    one_way = config_from_mapping({**mapping, "links": {"vehicles": {"7": {"forward": {"delay": 0.05}}}}})
    assert run_size(one_way).links == 1 and run_size(one_way).work == 10_000 * (4001 + 1)  # only the links made


def test_a_sweep_point_above_the_size_limits_is_invalid_not_run(tmp_path: Path) -> None:
    from orchestrator.sweep.plan import plan
    from orchestrator.sweep.spec import load_sweep

    sweep = tmp_path / "long.toml"
    sweep.write_text(f'base = "{PAPER}"\n[grid]\n"simulation.stop_time" = [1.0, 1e12]\n')
    runs = plan(load_sweep(sweep))
    assert [run.config is not None for run in runs] == [True, False]
    assert "100,000,000,000,000 steps: more than 1,000,000" in runs[1].error


def test_analyze_refuses_a_platoon_too_big_to_linearize(workdir: Path, tmp_path: Path) -> None:
    result = platoon("analyze", PAPER, "--no-measure", "--set", "platoon.count=1000",
                     "--set", "path.radius=20000.0", cwd=workdir, timeout=60)
    refused(result, "platoon.count = 1000: analyze linearizes at most 100 vehicles", "--allow-long")


# --- 8: the other tracebacks where exit 2 is promised ----------------------------------------------

@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_config_that_is_not_utf8_exits_2(command: str, workdir: Path, tmp_path: Path) -> None:
    config = tmp_path / "latin1.toml"
    config.write_bytes('description = "Düsseldorf"\n'.encode("latin-1"))
    refused(platoon(*COMMANDS[command](config, tmp_path), cwd=workdir),
            f"config {config}: not UTF-8 text: byte 0xfc at line 1")


def test_a_sweep_file_that_is_not_utf8_exits_2(workdir: Path, tmp_path: Path) -> None:
    sweep = tmp_path / "latin1.toml"
    sweep.write_bytes(f'base = "{PAPER}"\n# Düsseldorf\n[grid]\n"platoon.count" = [1, 2]\n'.encode("latin-1"))
    refused(platoon("sweep", sweep, "--out", tmp_path / "out", cwd=workdir),
            f"sweep file {sweep}: not UTF-8 text: byte 0xfc at line 2")


def test_a_config_with_a_utf8_byte_order_mark_is_read(workdir: Path, tmp_path: Path) -> None:
    """Accepted silently, as Python's utf-8-sig does: the mark is no part of the TOML."""
    text = "[platoon]\ncount = 3\n[simulation]\nstop_time = 1.0\n"
    config = tmp_path / "bom.toml"
    config.write_bytes(b"\xef\xbb\xbf" + text.encode())
    result = platoon("run", config, "-q", "--out", tmp_path / "bom.mcap", cwd=workdir)
    assert result.returncode == 0, result.stderr
    trace = load(tmp_path / "bom.mcap")
    assert trace.vehicles() == ["vehicle1", "vehicle2", "vehicle3"]
    assert trace.metadata["platoon.config"]["toml"] == text  # stored as read, without the mark


@pytest.mark.parametrize("assignment, key", [(b"description=\xff", "description"), (b"name=r\xfcn", "name"),
                                             (b'vehicles.1.connect=["tcp/\xff"]', "vehicles.1.connect[0]")])
def test_a_set_value_that_is_not_utf8_exits_2(assignment: bytes, key: str, workdir: Path, tmp_path: Path) -> None:
    """A non-UTF-8 argument reaches Python with lone surrogates: refused, not a traceback when the
    trace metadata is encoded."""
    result = subprocess.run([str(PLATOON), "run", str(PAPER), *SHORT, "-q", "--set", assignment, "--out",
                             str(tmp_path / "never.mcap")], cwd=workdir, capture_output=True, text=True, timeout=120,
                            env={**os.environ, "PYTHONPATH": str(REPO), "NO_COLOR": "1"})
    line = refused(result, f"{key} = ")
    assert "must be valid UTF-8 text" in line or "must be letters, digits" in line, line
    assert not (tmp_path / "never.mcap").exists()


@pytest.mark.parametrize("every", ["101", "100000000000000000000000000000"])
def test_trace_every_above_the_step_count_exits_2(every: str, workdir: Path, tmp_path: Path) -> None:
    result = platoon("run", PAPER, *SHORT, "--trace-every", every, "--out", tmp_path / "never.mcap", cwd=workdir)
    refused(result, f"simulation.trace_every = {every}: expected at most the run's 100 steps")
    assert not (tmp_path / "never.mcap").exists()


def test_trace_every_equal_to_the_step_count_records_both_ends(workdir: Path, tmp_path: Path) -> None:
    result = platoon("run", PAPER, *SHORT, "--trace-every", "100", "-q", "--out", tmp_path / "ends.mcap", cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert list(load(tmp_path / "ends.mcap").component("vehicle1")["t"]) == pytest.approx([0.0, 1.0])


@pytest.mark.parametrize("where", ["set", "file"])
def test_a_nul_in_the_name_exits_2(where: str, workdir: Path, tmp_path: Path) -> None:
    config = tmp_path / "nul.toml"
    config.write_text('name = "a\\u0000b"\n' if where == "file" else "")
    sets = ["--set", 'name="a\\u0000b"'] if where == "set" else []
    refused(platoon("run", config, *sets, *SHORT, "-q", cwd=workdir), "name = 'a\\x00b': must be letters, digits")
    assert not (workdir / "runs").exists() or not any((workdir / "runs").glob("a*"))


@pytest.mark.parametrize("key, text", [
    ("description", 'description = "ring\\u0007 the bell"'),
    ("vehicles.1.zenoh_config", '[vehicles.1]\nzenoh_config = "a\\u0000.json5"'),
])
def test_control_characters_in_free_text_exit_2(key: str, text: str, workdir: Path, tmp_path: Path) -> None:
    config = tmp_path / "control.toml"
    config.write_text(text + "\n")
    refused(platoon("run", config, *SHORT, "-q", cwd=workdir), f"{key} = ", "must be text without control characters")


@pytest.mark.parametrize("extra", [[], ["--no-measure"]])
def test_analyze_at_d_star_equal_to_the_diameter_exits_2_with_the_reason(extra: list[str], workdir: Path) -> None:
    result = platoon("analyze", PAPER, *extra, "--set", "platoon.d_star=100.0", cwd=workdir)
    refused(result, "platoon.d_star = 100.0: expected less than 2 * path.radius = 100.0", "equilibrium is degenerate")


@pytest.mark.parametrize("corner", [
    {"platoon": {"k_v": 1e-3, "speed": 1e-3, "d_star": 1e-3}, "path": {"radius": 1e6}},
    {"platoon": {"k_v": 1e3, "speed": 1e3, "d_star": 1e-3}, "path": {"radius": 1e6},
     "simulation": {"max_substep": 1e-3}},
    {"platoon": {"d_star": 1.999e-3}, "path": {"radius": 1e-3}},
    {"platoon": {"d_star": 1e6}, "path": {"radius": 1e6}},
], ids=["slow", "fast", "tiny circle", "huge circle"])
def test_analyze_reports_at_the_corners_of_the_ranges(corner: dict[str, Any]) -> None:
    """Whatever the config accepts, the linearization gives a verdict (no division by ~0)."""
    from orchestrator.analysis.linear import eigen_report

    report = eigen_report(config_from_mapping({"name": "corner", **corner}))
    assert "verdict: exponentially stable" in report, report


def test_analyze_just_inside_the_diameter_reports(workdir: Path) -> None:
    result = platoon("analyze", PAPER, "--no-measure", "--set", "platoon.d_star=99.9", cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert "verdict:" in result.stdout and "speed chain" in result.stdout


# --- 11: smaller ones ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../../x", "/tmp/x", "a/b", ".hidden", "-rf", "a\nb", "", "a" * 101, "é" * 101])
def test_a_name_that_is_not_a_file_name_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match=r"^name = .*: must be letters, digits"):
        config_from_mapping({"name": name})


@pytest.mark.parametrize("name", ["platoon", "my run (2)", "Düsseldorf-ring_3.b", "a" * 100])
def test_ordinary_names_are_accepted(name: str) -> None:
    assert config_from_mapping({"name": name}).name == name


def test_a_name_with_dots_and_slashes_writes_nothing_outside_runs(workdir: Path, tmp_path: Path) -> None:
    cwd = tmp_path / "a" / "b"
    cwd.mkdir(parents=True)
    (cwd / "build").symlink_to(workdir / "build")
    result = platoon("run", PAPER, *SHORT, "-q", "--set", 'name="../../x"', cwd=cwd)
    refused(result, "name = '../../x'")
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == []


@pytest.mark.parametrize("text", ["3 x=1", "3\nx=1", "3 # seven", "3, 4", '"a" b', "[1, 2] 3", "true x"])
def test_extra_toml_after_a_set_value_is_an_error(text: str) -> None:
    with pytest.raises(ConfigError, match="is not one TOML value"):
        parse_value(text)


@pytest.mark.parametrize("text, value", [
    ("3", 3), ("0.5", 0.5), ("true", True), ('"x y"', "x y"), ("[10.0, 0.0]", [10.0, 0.0]),
    ("{x = 1.0, y = 2.0}", {"x": 1.0, "y": 2.0}), ("regular", "regular"), ("hello world", "hello world"),
    ("[1,\n 2]", [1, 2]), ("", ""),
])
def test_one_set_value_still_parses_as_before(text: str, value: Any) -> None:
    assert parse_value(text) == value


@pytest.mark.parametrize("assignment", ["platoon.count=3 x=1", "platoon.count=3\nsimulation.stop_time=1"])
def test_extra_toml_after_a_set_value_exits_2(assignment: str, workdir: Path, tmp_path: Path) -> None:
    refused(platoon("run", PAPER, *SHORT, "--set", assignment, "--out", tmp_path / "never.mcap", cwd=workdir),
            f"--set {assignment!r}", "is not one TOML value")


def strip(fmu: Path, drop: str) -> None:
    """Rewrite ``fmu`` without the entries whose names start with ``drop`` (the GUID stays)."""
    with zipfile.ZipFile(fmu) as archive:
        entries = [(item, archive.read(item)) for item in archive.infolist() if not item.filename.startswith(drop)]
    with zipfile.ZipFile(fmu, "w") as archive:
        for item, data in entries:
            archive.writestr(item, data)


def corrupt(fmu: Path, drop: str) -> None:
    """Flip a byte inside the compressed data of the entry ``drop`` (its CRC then fails)."""
    with zipfile.ZipFile(fmu) as archive:
        info = archive.getinfo(drop)
    data = bytearray(fmu.read_bytes())
    data[info.header_offset + 30 + len(info.filename.encode()) + len(info.extra) + info.compress_size // 2] ^= 0xFF
    fmu.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["no binary", "no resources", "bad CRC"])
def test_an_fmu_with_the_right_guid_but_damaged_is_rebuilt(damage: str, workdir: Path, tmp_path: Path) -> None:
    from fmpy import platform, sharedLibraryExtension

    out = tmp_path / "fmus"
    PYTHONFMU.build(out, names=ALL_FMUS)
    fmu = out / "Vehicle.fmu"
    binary = f"binaries/{platform}/Vehicle{sharedLibraryExtension}"
    if damage == "no binary":
        strip(fmu, binary)
    elif damage == "no resources":
        strip(fmu, "resources/fmus/model/")
    else:
        corrupt(fmu, binary)
    result = platoon("build", "--out", out, cwd=workdir)
    assert result.returncode == 0, result.stderr
    states = {Path(line.split()[0]).name: line.split("(", 1)[1] for line in result.stdout.splitlines()
              if Path(line.split()[0]).parent == out}  # the pythonfmu FMUs (not out/native, out/fmi3)
    assert states == {"Vehicle.fmu": "built)", "VirtualTarget.fmu": "up to date)", "Link.fmu": "up to date)",
                      "LiveVehicle.fmu": "up to date)", "RemoteVehicle.fmu": "up to date)"}
    with zipfile.ZipFile(fmu) as archive:
        assert archive.testzip() is None and archive.getinfo(binary).file_size > 0
    assert all(b.rebuilt is False for b in PYTHONFMU.build(out, names=ALL_FMUS)), "a repaired build is up to date"


def extraction_folders(temp: Path) -> list[Path]:
    """Folders in ``temp`` that hold an extracted FMU (whatever they are called)."""
    return sorted(p.parent for p in temp.glob("*/modelDescription.xml"))


def test_a_sigkilled_run_leaves_no_extracted_fmus_behind(workdir: Path, tmp_path: Path) -> None:
    """Without the FMU cache (PLATOON_FMU_CACHE=off, or when it cannot serve) a run extracts privately."""
    temp = tmp_path / "tmp"
    temp.mkdir()
    private = {"TMPDIR": str(temp), "PLATOON_FMU_CACHE": "off"}
    environment = {**os.environ, "PYTHONPATH": str(REPO), **private}
    victim = subprocess.Popen([str(PLATOON), "run", PAPER, "-q", "--set", "simulation.stop_time=10000",
                               "--out", tmp_path / "killed.mcap"], cwd=workdir, env=environment,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while len(extraction_folders(temp)) < len(FMU_NAMES) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(extraction_folders(temp)) == len(FMU_NAMES), "the run never extracted its FMUs"
    finally:
        victim.send_signal(signal.SIGKILL)
        victim.wait()
    assert len(extraction_folders(temp)) == len(FMU_NAMES)  # nothing can clean up at SIGKILL itself ...
    result = platoon("run", PAPER, *SHORT, "-q", "--out", tmp_path / "next.mcap", cwd=workdir, env=private)
    assert result.returncode == 0, result.stderr
    assert extraction_folders(temp) == []  # ... but the next run sweeps them, and removes its own


def test_a_sigkilled_run_leaves_the_fmu_cache_usable(workdir: Path, tmp_path: Path) -> None:
    """With the cache, a run extracts nothing into the temp folder; killed while it holds its FMUs, it
    leaves the cache as it was: the next run uses the same entries."""
    temp, cache = tmp_path / "tmp", tmp_path / "cache"
    temp.mkdir()
    cached = {"TMPDIR": str(temp), "PLATOON_FMU_CACHE": str(cache)}
    victim = subprocess.Popen([str(PLATOON), "run", PAPER, "-q", "--set", "simulation.stop_time=10000",
                               "--out", tmp_path / "killed.mcap"], cwd=workdir,
                              env={**os.environ, "PYTHONPATH": str(REPO), **cached},
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        partial = tmp_path / "killed.mcap.partial"  # claimed empty first, written once the FMUs are held
        while not (partial.exists() and partial.stat().st_size > 0) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert partial.stat().st_size > 0, "the run never started"
    finally:
        victim.send_signal(signal.SIGKILL)
        victim.wait()
    made = sorted(cache.iterdir())
    assert len(made) == len(FMU_NAMES) and extraction_folders(temp) == []
    result = platoon("run", PAPER, *SHORT, "-q", "--out", tmp_path / "next.mcap", cwd=workdir, env=cached)
    assert result.returncode == 0, result.stderr
    assert sorted(cache.iterdir()) == made and extraction_folders(temp) == []


def test_a_live_owners_scratch_folder_is_never_swept(tmp_path: Path) -> None:
    """Another process holds its folder: sweeping leaves it; once SIGKILLed, the sweep removes it."""
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from orchestrator.support.scratch import ScratchDir; "
                               "d = ScratchDir('holder'); print(d.path, flush=True); time.sleep(600)"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO), "TMPDIR": str(tmp_path)}, stdout=subprocess.PIPE, text=True)
    try:
        folder = Path(holder.stdout.readline().strip())
        assert folder.parent == tmp_path and folder.is_dir()
        assert sweep(tmp_path) == [] and folder.is_dir()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert sweep(tmp_path) == [folder] and not folder.exists()


def test_a_scratch_folder_is_removed_by_its_owner(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    with ScratchDir("own") as folder:
        assert folder.parent == tmp_path and sweep(tmp_path) == []
    assert list(tmp_path.iterdir()) == []


def test_analyze_prints_disturbance_literally(workdir: Path) -> None:
    result = platoon("analyze", PAPER, cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert "the config has no [[disturbance]]; add one" in result.stdout


def test_user_text_is_printed_as_written_not_as_rich_markup(workdir: Path, tmp_path: Path) -> None:
    """Paths and names with brackets: rich would take [red] or [x] for markup and drop them."""
    out = tmp_path / "[x]" / "[red]trace.mcap"
    result = platoon("run", PAPER, *SHORT, "--set", 'name="ring [bold]"', "--out", out, cwd=workdir)
    refused(result, "name = 'ring [bold]'")  # brackets are not in a name's character set ...
    result = platoon("run", PAPER, *SHORT, "--out", out, cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert f"trace: {out}  (" in result.stdout  # ... but a path may hold them
    report = platoon("report", out, cwd=workdir)
    assert report.returncode == 0, report.stderr
    assert "[red]trace.mcap: sine law (completed)" in report.stdout
    assert "[m/s]" in report.stdout  # the table's units, which rich took for markup too
    built = platoon("build", "--out", tmp_path / "[b]", cwd=workdir)
    assert f"{tmp_path / '[b]' / 'Vehicle.fmu'}  {{" in built.stdout
