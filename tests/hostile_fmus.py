"""Hostile FMI calls on our FMUs (calls out of order, refused values, states): each case in a host process of its own.

    python -m tests.hostile_fmus               # builds the FMUs in build/fmus if needed, runs every case
    python -m tests.hostile_fmus <FMU folder>  # the FMUs in that folder, as they are
    python -m tests.hostile_fmus --native      # the native FMUs (build/fmus/native), held to fmi2Error

prints one line per case and exits 1 if any case found a problem. tests/test_hostile_fmus.py runs
the same cases one by one.

A case is a list of FMI calls a careless host makes on one instance (``tests/hostile_fmu_host.py``
makes them through FMPy and keeps going after an error status). Every case must satisfy:

* the host survives: its process ends normally, within ``TIMEOUT`` seconds, after fmi2FreeInstance;
* no fmi2GetReal answers fmi2OK with a value that is not finite;

and what the case itself expects (a refusal with its reason logged, an instance left unchanged...).

A refused call returns fmi2Error or fmi2Fatal. The FMI status it deserves is fmi2Error; pythonfmu
0.7's binary can only report fmi2Fatal from a Python slave (fmus/slaves/refusal.py), so both count,
and what matters is that the instance stays alive and answers every later call. The native FMUs
(fmus/native) are held to the status itself: a refused call is fmi2Error, a refused step fmi2Error
or fmi2Discard, never fmi2Fatal (``run_host(..., native=True)``, ``--native``).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

DISCARD, ERROR, FATAL = 2, 3, 4
REFUSED = (ERROR, FATAL)
STEP_REFUSED = (DISCARD, ERROR, FATAL)
NATIVE_REFUSED = (ERROR,)  # a native FMU answers the status FMI asks for
NATIVE_STEP_REFUSED = (DISCARD, ERROR)
TIMEOUT = 120.0  # s; a case takes about one second, a hang (fmi2DoStep(t, 1e9) before the fix) hits it
HOST = Path(__file__).resolve().parent / "hostile_fmu_host.py"


@dataclass
class Outcome:
    """What the host process reported."""

    calls: list[dict[str, Any]] = field(default_factory=list)
    logs: list[str] = field(default_factory=list)
    ended: bool = False
    returncode: int | None = None
    stderr: str = ""
    refused: tuple[int, ...] = REFUSED  # the statuses that count as a refused call, resp. step
    step_refused: tuple[int, ...] = STEP_REFUSED

    def call(self, index: int) -> dict[str, Any]:
        """The ``index``-th call of the case (0 = the first of its ``calls``)."""
        return [c for c in self.calls if "args" in c][index]

    def logged(self, text: str) -> bool:
        return any(text in line for line in self.logs)


Check = Callable[[Outcome], list[str]]


@dataclass(frozen=True)
class Case:
    fmu: str  # "Vehicle" | "VirtualTarget"
    title: str
    parameters: dict[str, Any]
    calls: list[list[Any]]
    check: Check


def run_host(unzipped: Path, case: Case, native: bool = False) -> Outcome:
    """Run ``case`` in a host process; ``native``: the FMU is a native one, held to fmi2Error."""
    statuses = {"refused": NATIVE_REFUSED, "step_refused": NATIVE_STEP_REFUSED} if native else {}
    try:
        process = subprocess.run([sys.executable, str(HOST), str(unzipped), json.dumps(
            {"parameters": case.parameters, "calls": case.calls})], capture_output=True, text=True, timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        return Outcome(returncode=None, stderr=f"no answer within {TIMEOUT:g} s", **statuses)
    outcome = Outcome(returncode=process.returncode, stderr=process.stderr[-2000:], **statuses)
    for line in process.stdout.splitlines():
        record = json.loads(line)
        if "log" in record:
            outcome.logs.append(record["log"])
        elif "end" in record:
            outcome.ended = True
        else:
            outcome.calls.append(record)
    return outcome


def problems(case: Case, outcome: Outcome) -> list[str]:
    """Everything wrong with ``outcome``: the checks every case shares, then the case's own."""
    if outcome.returncode is None:
        return [outcome.stderr]
    found = []
    if outcome.returncode != 0 or not outcome.ended:
        found.append(f"the host died (exit status {outcome.returncode}) after {len(outcome.calls)} calls: "
                     f"{outcome.stderr.strip()[-300:]}")
    for record in outcome.calls:
        values = record.get("values")
        if record["status"] == 0 and values is not None and not all(map(math.isfinite, values)):
            found.append(f"{record['call']} {record['args']} answered fmi2OK with non-finite values {values}")
    if not found:
        found += case.check(outcome)
    return found


# --- what cases expect ------------------------------------------------------------------------------


def refused_for_good(reason: str) -> Check:
    """exitInitializationMode refused with ``reason`` logged; every later call fails cleanly."""

    def check(outcome: Outcome) -> list[str]:
        found = []
        exit_call = outcome.call(0)
        if exit_call["status"] not in outcome.refused:
            found.append(f"exitInitializationMode returned {exit_call['status']}, expected fmi2Error/fmi2Fatal")
        if not outcome.logged(reason):
            found.append(f"no log line says {reason!r}: {outcome.logs}")
        for record in [c for c in outcome.calls if "args" in c][1:]:
            expected = outcome.step_refused if record["call"] == "step" else outcome.refused
            if record["status"] not in expected:
                found.append(f"{record['call']} {record['args']} after the failed initialization returned "
                             f"{record['status']}, expected one of {expected}")
        return found

    return check


AFTER_FAILURE = [["step", 0.0, 0.01], ["get"], ["get"], ["set", "max_substep", 0.01], ["step", 0.0, 0.01],
                 ["get_state"], ["get"]]


def step_refused_state_kept(reason: str, step_index: int = 2) -> Check:
    """The step (call ``step_index``) is refused with ``reason`` logged, and the outputs read before
    (call ``step_index - 1``) and after (the call that follows) are the same: nothing moved."""

    def check(outcome: Outcome) -> list[str]:
        found = []
        step, before, after = outcome.call(step_index), outcome.call(step_index - 1), outcome.call(step_index + 1)
        if step["status"] not in outcome.step_refused:
            found.append(f"doStep{tuple(step['args'])} returned {step['status']}, expected fmi2Discard/fmi2Error")
        if not outcome.logged(reason):
            found.append(f"no log line says {reason!r}: {outcome.logs}")
        if before["status"] != 0 or after["status"] != 0 or before["values"] != after["values"]:
            found.append(f"the outputs changed across the refused step: {before} -> {after}")
        return found

    return check


def set_refused_instance_alive(name: str) -> Check:
    """Setting a non-finite value is refused naming the variable; the instance then steps normally."""

    def check(outcome: Outcome) -> list[str]:
        found = []
        if outcome.call(1)["status"] not in outcome.refused:
            found.append(f"setting {name} to a non-finite value returned {outcome.call(1)['status']}")
        if not outcome.logged(f"{name} = "):
            found.append(f"no log line names {name}: {outcome.logs}")
        if [outcome.call(i)["status"] for i in (2, 3)] != [0, 0]:
            found.append(f"the instance did not step on normally: {outcome.calls}")
        return found

    return check


def huge_input_never_ok_with_non_finite(outcome: Outcome) -> list[str]:
    """An input of 1e308 (finite) may make outputs overflow: the step is then refused with the
    reason, and the outputs are refused or finite (the shared check) - never inf with fmi2OK."""
    step = outcome.call(2)
    if step["status"] == 0:
        read = outcome.call(3)
        return [] if read["status"] == 0 else [f"the step was accepted, then its outputs refused: {read}"]
    return [] if outcome.logged("not finite") else [f"the refused step logged no reason: {outcome.logs}"]


def garbage_state_refused(outcome: Outcome) -> list[str]:
    found = []
    if outcome.call(2)["status"] not in outcome.refused:
        found.append(f"an unreadable FMU state was accepted: {outcome.call(2)}")
    if not outcome.logged("cannot be read"):
        found.append(f"no log line says the state cannot be read: {outcome.logs}")
    if outcome.call(3)["status"] != 0 or outcome.call(3)["values"] != outcome.call(1)["values"]:
        found.append("the instance changed or died after the refused state")
    return found


def init_read_refused(reason: str) -> Check:
    def check(outcome: Outcome) -> list[str]:
        first = outcome.call(0)
        found = [] if first["status"] in outcome.refused else [f"reading outputs with invalid parameters returned {first}"]
        return found + ([] if outcome.logged(reason) else [f"no log line says {reason!r}: {outcome.logs}"])

    return check


# --- the cases ----------------------------------------------------------------------------------------


# Real parameters declared with min = 0 that may be 0 (the others must be > 0): acc's standstill gap, and the dead-band
# and latencies of a robot that is not its nominal model (0: the nominal robot), the kinematic speed limit (0: none).
MAY_BE_ZERO = ("standstill_gap", "m3pi.wheel_deadband", "m3pi.command_latency", "m3pi.pose_latency", "speed_max")


def invalid_parameter_cases() -> list[Case]:
    """Every parameter constraint of both FMUs, broken one at a time (item 12 and its siblings):
    each Real parameter declared with min = 0 must be > 0 (``MAY_BE_ZERO``: >= 0), each String is one of a list, the circle's
    direction is 1 or -1, and the target's d* is a chord of its circle (d* <= 2 R)."""
    from fmus.slaves.Vehicle import Vehicle
    from fmus.slaves.VirtualTarget import VirtualTarget

    cases = []
    for cls in (Vehicle, VirtualTarget):
        for info in cls.variables:
            if info.causality != "parameter":
                continue
            if info.type == "Real" and info.name in MAY_BE_ZERO:
                bad: list[Any] = [-1.0]
            elif info.type == "Real" and info.min == 0.0:
                bad = [0.0, -1.0] if info.name == "d_star" else [0.0]
                if info.name == "path.radius":
                    bad = [0.0]
            elif info.type == "String":
                bad = ["bogus"]
            elif info.type == "Integer":
                bad = [0]
            else:
                continue
            for value in bad:
                cases.append(Case(cls.__name__, f"{info.name} = {value!r}", {info.name: value},
                                  [["exit"], *AFTER_FAILURE], refused_for_good(f"{info.name} = {value!r}")))
    cases.append(Case("Vehicle", "m3pi.pose_latency = 2.0 > 1 s", {"m3pi.pose_latency": 2.0}, [["exit"], *AFTER_FAILURE],
                      refused_for_good("m3pi.pose_latency = 2.0: must be a finite number >= 0 and <= 1")))
    cases.append(Case("VirtualTarget", "d_star = 120 > 2 R = 100", {"d_star": 120.0}, [["exit"], *AFTER_FAILURE],
                      refused_for_good("must be <= 2 R = 100.0")))
    return cases


def step_cases() -> list[Case]:
    """Impossible communication steps (item 13): refused, the instance untouched."""
    cases = []
    for fmu in ("Vehicle", "VirtualTarget"):
        for h, reason in ((-0.01, "step size must be > 0"), (0.0, "step size must be > 0"),
                          (1e9, "RK4 substeps"), (math.inf, "must be finite"), (math.nan, "must be finite")):
            cases.append(Case(fmu, f"doStep(0, {h})", {}, [["exit"], ["get"], ["step", 0.0, h], ["get"]],
                              step_refused_state_kept(reason)))
        cases.append(Case(fmu, "doStep(nan, 0.01)", {}, [["exit"], ["get"], ["step", math.nan, 0.01], ["get"]],
                          step_refused_state_kept("must be finite")))
        cases.append(Case(fmu, "doStep before exitInitializationMode", {}, [["get"], ["get"], ["step", 0.0, 0.01],
                                                                             ["get"]],
                          step_refused_state_kept("not initialized")))
    return cases


def input_cases() -> list[Case]:
    """Non-finite and overflowing inputs (item 13)."""
    cases = []
    for fmu, name in (("Vehicle", "target.x"), ("Vehicle", "follower.gap"), ("VirtualTarget", "lead.gap")):
        for value in (math.inf, -math.inf, math.nan):
            cases.append(Case(fmu, f"{name} = {value}", {}, [["exit"], ["set", name, value], ["step", 0.0, 0.01],
                                                              ["get"]], set_refused_instance_alive(name)))
    for fmu, name in (("Vehicle", "target.x"), ("Vehicle", "target.speed"), ("Vehicle", "follower.speed"),
                      ("VirtualTarget", "lead.speed"), ("VirtualTarget", "lead.gap_rate")):
        for value in (1e308, -1e308):
            parameters = {"is_last": False} if name.startswith("follower.") else {}  # the last one ignores it
            cases.append(Case(fmu, f"{name} = {value:g}", parameters, [["exit"], ["set", name, value], ["step", 0.0, 0.01],
                                                                ["get"], ["step", 0.01, 0.01], ["get"]],
                              huge_input_never_ok_with_non_finite))
    cases.append(Case("Vehicle", "initial.x = nan", {"initial.x": math.nan}, [["exit"], ["get"], ["step", 0.0, 0.01],
                                                                            ["get"]],
                      lambda o: [] if o.logged("initial.x = nan") and o.calls[1]["status"] in o.refused
                      else [f"a NaN parameter was not refused by name: {o.calls[:2]} {o.logs}"]))
    return cases


def other_cases() -> list[Case]:
    cases = []
    for fmu in ("Vehicle", "VirtualTarget"):
        cases.append(Case(fmu, "unreadable FMU state", {}, [["exit"], ["get"], ["set_state_bytes", "not a state"],
                                                            ["get"]], garbage_state_refused))
    cases.append(Case("Vehicle", "getReal in initialization mode with d_star = 0", {"d_star": 0.0}, [["get"], ["exit"]],
                      init_read_refused("d_star = 0.0")))
    cases.append(Case("VirtualTarget", "getReal in initialization mode with path.radius = 0", {"path.radius": 0.0},
                      [["get"], ["exit"]], init_read_refused("path.radius = 0.0")))
    return cases


def all_cases() -> list[Case]:
    return invalid_parameter_cases() + step_cases() + input_cases() + other_cases()


def unzip(fmu: Path, into: Path) -> Path:
    into.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(into)
    return into


def main(argv: list[str]) -> int:
    import tempfile

    from fmus.builders import DEFAULT_OUT, PYTHONFMU

    native = "--native" in argv
    argv = [arg for arg in argv if arg != "--native"]
    fmu_dir = Path(argv[0]) if argv else DEFAULT_OUT / "native" if native else DEFAULT_OUT
    if not argv:  # a folder given is taken as it is (e.g. FMUs built from older sources)
        if native:
            from fmus.builders import NATIVE_FMI2

            NATIVE_FMI2.build(fmu_dir)
        else:
            PYTHONFMU.build(fmu_dir)
    left = 0
    with tempfile.TemporaryDirectory(prefix="hostile-fmus-") as scratch:
        unzipped = {name: unzip(fmu_dir / f"{name}.fmu", Path(scratch) / name) for name in ("Vehicle", "VirtualTarget")}
        cases = all_cases()
        for case in cases:
            found = problems(case, run_host(unzipped[case.fmu], case, native))
            left += bool(found)
            print(f"{'ok  ' if not found else 'FAIL'} {case.fmu}: {case.title}" + "".join(f"\n     {p}" for p in found),
                  flush=True)
    print(f"{len(cases)} hostile cases{' (native FMUs)' if native else ''}, {left} left")
    return 1 if left else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
