"""Remote vehicles: FMUs served by `platoon serve` processes on 127.0.0.1, stepped over Zenoh.

What a user relies on: a platoon whose vehicles all run in servers ends with the very numbers of the local
run (bit for bit, both FMU kinds); a server that dies mid-run ends the run with exit 1 within its step
timeout, one line naming the vehicle and the server, and a trace that loads to the last step; a served
instance obeys only the run that opened it, once per request and in order.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest

from bridge import fmu_wire as wire
from tests.conftest import free_port
from orchestrator.components.fmu import UnpackedFmu
from orchestrator.components.served import ServedInstance
from orchestrator.trace import load
from tests.test_cli import error_line, platoon
from tests.test_hil import _env, end_process

REPO = Path(__file__).resolve().parent.parent
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = REPO / "configs" / "paper" / "platoon.toml"


@contextmanager
def server(name: str, port: int, kind: str, scratch: Path, fmu: str = "Vehicle") -> Iterator[subprocess.Popen]:
    """`platoon serve Vehicle` (or the FMU file ``fmu``) as ``name`` on 127.0.0.1:``port``, ready (its "ready"
    line seen); always stopped."""
    log = scratch / f"serve-{name}.log"
    with open(log, "w") as stream:
        process = subprocess.Popen([str(PLATOON), "serve", fmu, "--name", name, "--fmus", kind,
                                    "--listen", f"tcp/127.0.0.1:{port}"], cwd=REPO, env=_env(),
                                   stdout=stream, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while "ready" not in log.read_text():
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, f"{name} did not start: {log.read_text()}"
            time.sleep(0.05)
        yield process
    finally:
        if process.poll() is None:
            end_process(process)


def remote_sets(ports: dict[int, int]) -> list[str]:
    sets = []
    for vehicle, port in ports.items():
        sets += ["--set", f"vehicles.{vehicle}.endpoint=remote",
                 "--set", f'vehicles.{vehicle}.connect=["tcp/127.0.0.1:{port}"]']
    return sets


def platoon_run(config: Path, trace: Path, kind: str, *options: str) -> subprocess.Popen:
    return subprocess.Popen([str(PLATOON), "run", str(config), "--out", str(trace), "--fmus", kind, "--quiet", *options],
                            cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def thread_names(pid: int) -> set[str]:
    """The names of the threads of process ``pid`` (Linux /proc)."""
    return {(Path("/proc") / str(pid) / "task" / task / "comm").read_text().strip()
            for task in os.listdir(f"/proc/{pid}/task")}


def outputs(trace: Path) -> dict[str, np.ndarray]:
    loaded = load(trace)
    return {f"{component}.{name}": np.asarray(values) for component, channel in loaded.channels.items()
            for name, values in channel.items()}


@pytest.mark.parametrize("kind", ["python", "native"])
def test_every_vehicle_remote_gives_the_local_numbers_bit_for_bit(kind: str, tmp_path: Path, fmu_dir: Path,
                                                                 native_fmu_dir: Path) -> None:
    """The paper's platoon (shortened to 20 s to keep the suite quick; docs/remote.md reports the full
    100 s) with each of its four vehicles in a `platoon serve` of its own."""
    stop = ["--set", "simulation.stop_time=20"]
    local = tmp_path / "local.mcap"
    process = platoon_run(PAPER, local, kind, *stop)
    assert process.communicate(timeout=300)[1] == "" and process.returncode == 0
    ports = {vehicle: free_port() for vehicle in (1, 2, 3, 4)}
    with ExitStack() as stack:
        for vehicle, port in ports.items():
            serving = stack.enter_context(server(f"vehicle{vehicle}", port, kind, tmp_path))
            # its Zenoh on one thread (bridge.session.one_zenoh_thread): none of the default runtimes' threads
            threads = thread_names(serving.pid)
            assert "app-0" in threads and not threads & {"rx-0", "rx-1", "tx-0", "net-0", "acc-0"}, threads
        remote = tmp_path / "remote.mcap"
        process = platoon_run(PAPER, remote, kind, *stop, *remote_sets(ports))
        _, err = process.communicate(timeout=300)
        assert process.returncode == 0, err
    here, there = outputs(local), outputs(remote)
    assert here.keys() == there.keys() and len(here["vehicle4.t"]) > 100
    for name in here:
        assert np.array_equal(here[name], there[name]), name  # bit for bit, not to a tolerance


@pytest.mark.parametrize("fmi", ["2.0", "3.0"])
def test_a_killed_server_ends_the_run_within_its_timeout(fmi: str, tmp_path: Path, native_fmu_dir: Path,
                                                         request: pytest.FixtureRequest) -> None:
    """kill -9 of vehicle 2's server mid-run: exit 1 within step_timeout + 1 s, one line naming vehicle 2 and
    its server, and the trace loads up to the last step before the kill. The same whether the servers step
    the native FMI 2.0 or FMI 3.0 Vehicle FMU."""
    fmu = "Vehicle" if fmi == "2.0" else str(request.getfixturevalue("fmi3_fmu_dir") / "Vehicle.fmu")
    ports = {1: free_port(), 2: free_port()}
    trace = tmp_path / "killed.mcap"
    with server("vehicle1", ports[1], "native", tmp_path, fmu), \
            server("vehicle2", ports[2], "native", tmp_path, fmu) as victim:
        process = platoon_run(PAPER, trace, "native", "--set", "platoon.count=2", "--set", "simulation.stop_time=5000",
                              "--set", "remote.step_timeout=1.0", *remote_sets(ports))
        partial = trace.with_name(trace.name + ".partial")
        deadline = time.monotonic() + 120
        while not (partial.exists() and partial.stat().st_size > 200_000):  # stepping for a while
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "the run did not step"
            time.sleep(0.05)
        victim.kill()
        killed = time.monotonic()
        _, err = process.communicate(timeout=60)
        took = time.monotonic() - killed
    assert process.returncode == 1, err
    assert took <= 1.0 + 1.0, f"the run took {took:.2f} s after the kill (timeout 1 s)"
    assert "vehicle2" in err and f"tcp/127.0.0.1:{ports[2]}" in err and "platoon/fmu/vehicle2" in err, err
    loaded = load(trace)
    assert loaded.run["status"] == "failed"
    times = loaded.component("vehicle2")["t"]
    assert len(times) > 100 and np.all(np.diff(times) > 0)


@pytest.fixture(params=["python", "fmi3"])
def instance(request: pytest.FixtureRequest) -> Iterator[ServedInstance]:
    """A served Vehicle: the pythonfmu FMI 2.0 one, and the native FMI 3.0 one (the rules are the server's)."""
    folder = request.getfixturevalue("fmu_dir" if request.param == "python" else "fmi3_fmu_dir")
    fmu = UnpackedFmu.open(folder / "Vehicle.fmu")
    served = ServedInstance(fmu)
    yield served
    served.close()
    fmu.cleanup()


def _ok(reply: bytes) -> bytes:
    ok, body = wire.parse_reply(reply)
    assert ok, body.decode()
    return body


def _refused(reply: bytes) -> str:
    ok, body = wire.parse_reply(reply)
    assert not ok
    return body.decode()


def test_only_the_run_that_opened_an_instance_may_use_it(instance: ServedInstance) -> None:
    mine, stranger = b"m" * wire.TOKEN_SIZE, b"s" * wire.TOKEN_SIZE
    opened = wire.parse_json(_ok(instance.handle(wire.request(wire.OPEN, mine, 0, wire.json_body(
        {"name": "vehicle1", "start": 0.0, "parameters": {}})))), "open")
    assert "speed" in " ".join(opened["outputs"])
    assert "another run" in _refused(instance.handle(wire.request(wire.OPEN, stranger, 0, wire.json_body(
        {"name": "x", "start": 0.0, "parameters": {}}))))
    for op, body in ((wire.EXCHANGE, b""), (wire.STEP, wire.step_body(0.0, 0.01, [0.0] * len(opened["inputs"]))),
                     (wire.FREE, b"")):
        assert "another run's" in _refused(instance.handle(wire.request(op, stranger, 1, body)))
    _ok(instance.handle(wire.request(wire.EXCHANGE, mine, 1)))  # still ours, untouched by the stranger


def test_requests_execute_once_and_in_order(instance: ServedInstance) -> None:
    token = b"t" * wire.TOKEN_SIZE
    opened = wire.parse_json(_ok(instance.handle(wire.request(wire.OPEN, token, 0, wire.json_body(
        {"name": "vehicle1", "start": 0.0, "parameters": {}})))), "open")
    _ok(instance.handle(wire.request(wire.END_INIT, token, 1)))
    step = wire.step_body(0.0, 0.01, opened["input_defaults"])
    first = _ok(instance.handle(wire.request(wire.STEP, token, 2, step)))
    assert _ok(instance.handle(wire.request(wire.STEP, token, 2, step))) == first  # a retry: the same reply
    assert instance.steps == 1  # ... and not a second step
    assert "out of order" in _refused(instance.handle(wire.request(wire.STEP, token, 4, step)))
    assert "out of order" in _refused(instance.handle(wire.request(wire.STEP, token, 1, step)))
    second = _ok(instance.handle(wire.request(wire.STEP, token, 3, wire.step_body(0.01, 0.01, opened["input_defaults"]))))
    assert instance.steps == 2 and second != first
    assert "malformed" in _refused(instance.handle(b"\x04short"))


def test_a_step_or_exchange_with_the_wrong_number_of_inputs_is_refused(instance: ServedInstance) -> None:
    """The server copies the inputs' bytes into its FMU as they came: a request with more or fewer than one f64
    per input is refused, saying how many it expected, and nothing is set or stepped."""
    token = b"t" * wire.TOKEN_SIZE
    opened = wire.parse_json(_ok(instance.handle(wire.request(wire.OPEN, token, 0, wire.json_body(
        {"name": "vehicle1", "start": 0.0, "parameters": {}})))), "open")
    _ok(instance.handle(wire.request(wire.END_INIT, token, 1)))
    n = len(opened["inputs"])
    short = instance.handle(wire.request(wire.STEP, token, 2, wire.step_body(0.0, 0.01, [0.0] * (n - 1))))
    assert f"expected {n} f64" in _refused(short) and instance.steps == 0
    # a refused request is not executed, so the next one keeps its number
    assert f"expected {n} f64" in _refused(instance.handle(wire.request(wire.EXCHANGE, token, 2, wire.floats([1.0]))))
    assert "whole f64" in _refused(instance.handle(wire.request(wire.STEP, token, 2, wire.step_body(0.0, 0.01, []) + b"x")))
    first = _ok(instance.handle(wire.request(wire.STEP, token, 2, wire.step_body(0.0, 0.01, opened["input_defaults"]))))
    assert len(first) == 8 * len(opened["outputs"]) and instance.steps == 1


def test_a_silent_run_loses_its_instance_after_the_lease(fmu_dir: Path) -> None:
    now = [0.0]
    fmu = UnpackedFmu.open(fmu_dir / "Vehicle.fmu")
    served = ServedInstance(fmu, lease=5.0, clock=lambda: now[0])
    try:
        open_body = wire.json_body({"name": "v", "start": 0.0, "parameters": {}})
        _ok(served.handle(wire.request(wire.OPEN, b"a" * wire.TOKEN_SIZE, 0, open_body)))
        now[0] = 4.0
        served.expire()
        assert "another run" in _refused(served.handle(wire.request(wire.OPEN, b"b" * wire.TOKEN_SIZE, 0, open_body)))
        now[0] = 9.5
        served.expire()
        _ok(served.handle(wire.request(wire.OPEN, b"b" * wire.TOKEN_SIZE, 0, open_body)))
    finally:
        served.close()
        fmu.cleanup()


REMOTE = REPO / "configs" / "remote" / "platoon.toml"


def test_what_cannot_work_with_remote_vehicles_is_one_line_and_exit_2(tmp_path: Path) -> None:
    """The native engine and a file that is not an FMU are refused before anything is written, in one line
    naming what (an SSP export gives the remote vehicles client FMUs: tests/test_remote_fmu.py)."""
    native = platoon("run", REMOTE, "--engine", "native", "--out", tmp_path / "x.mcap", cwd=tmp_path)
    assert native.returncode == 2 and "vehicle1, vehicle2, vehicle3, vehicle4 is remote" in error_line(native)
    (tmp_path / "not.fmu").write_text("hello")
    bad = platoon("serve", tmp_path / "not.fmu", "--name", "v", cwd=tmp_path)
    assert bad.returncode == 2 and "not.fmu: not an FMU" in error_line(bad)
    assert not list(tmp_path.glob("x.*"))


def test_a_run_is_refused_an_instance_another_run_holds(tmp_path: Path, native_fmu_dir: Path) -> None:
    """Two runs name the same server: the second one fails at its start with one line saying the server is busy."""
    port = free_port()
    sets = ["--set", "platoon.count=1", *remote_sets({1: port})]
    with server("vehicle1", port, "native", tmp_path):
        first = platoon_run(PAPER, tmp_path / "first.mcap", "native", "--set", "simulation.stop_time=5000", *sets)
        partial = tmp_path / "first.mcap.partial"
        deadline = time.monotonic() + 120
        while not (partial.exists() and partial.stat().st_size > 50_000):  # the first run steps
            assert first.poll() is None and time.monotonic() < deadline, first.communicate()
            time.sleep(0.05)
        second = platoon_run(PAPER, tmp_path / "second.mcap", "native", *sets)
        _, err = second.communicate(timeout=120)
        first.send_signal(signal.SIGINT)
        first.communicate(timeout=60)
    assert second.returncode == 1 and "busy: this server's instance belongs to another run" in err, err
    assert "vehicle1" in err and "platoon/fmu/vehicle1" in err


def test_a_reply_that_breaks_the_layout_fails_the_run_naming_the_server(fmu_dir: Path) -> None:
    """A server (or an impostor on its key) answering garbage: one ComponentError naming the vehicle and the
    server, never a ValueError from deep inside (a real Zenoh session on 127.0.0.1 and a queryable that lies)."""
    import zenoh

    from bridge.fmu_client import RemoteComponent, RemoteHost
    from bridge.session import open_session, zenoh_config
    from fmus.component import ComponentError

    port = free_port()
    fmu = UnpackedFmu.open(fmu_dir / "Vehicle.fmu")
    served = ServedInstance(fmu)
    bad_step = [False]

    def answer(query: zenoh.Query) -> None:
        payload = query.payload.to_bytes()
        reply = served.handle(payload)
        if wire.parse_request(payload)[0] == wire.STEP and bad_step[0]:
            reply = wire.reply_ok(b"\x01\x02\x03")  # not a whole number of f64
        query.reply(query.key_expr, reply)

    with open_session(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"]), "liar") as session:
        queryable = session.declare_queryable("platoon/fmu/vehicle1", answer)  # noqa: F841
        variables = fmu.description.modelVariables
        inputs = [v.name for v in variables if v.causality == "input"]
        starts = fmu.start_values()
        component = RemoteComponent("vehicle1", "platoon/fmu/vehicle1", f"tcp/127.0.0.1:{port}", {}, inputs,
                                    [v.name for v in variables if v.causality == "output"],
                                    [float(starts[n]) for n in inputs], RemoteHost((f"tcp/127.0.0.1:{port}",)))
        try:
            component.initialize(0.0)
            component.end_initialization()
            component.set_inputs(component.input_defaults)
            component.step(0.0, 0.01)
            assert len(component.get_outputs()) == len(component.outputs)
            bad_step[0] = True
            component.step(0.01, 0.01)
            with pytest.raises(ComponentError, match=r"^vehicle1 failed at t = 0.01 s: step from t = 0.01 s: outputs: "
                                                     r"3 bytes .* \(server platoon/fmu/vehicle1 at tcp/127.0.0.1:\d+\)$"):
                component.get_outputs()
        finally:
            component.close()
            served.close()
            fmu.cleanup()


@pytest.mark.parametrize("on_zenoh_thread", [True, False])
def test_a_server_answers_on_zenohs_thread_only_when_told_and_steps_the_same(on_zenoh_thread: bool, fmu_dir: Path) -> None:
    """``serve(..., on_zenoh_thread=True)`` (what `platoon serve` passes) answers every request on the Zenoh
    thread that read it, not on zenoh-python's callback thread (docs/remote.md, "One round trip per step");
    without it, on a thread of zenoh-python's. Either way the FMU (a pythonfmu one here: Python called from
    the FMU, on that thread) steps to the local instance's numbers, bit for bit."""
    import threading

    from bridge.fmu_client import RemoteComponent, RemoteHost
    from bridge.session import open_session, zenoh_config
    from orchestrator.components.fmu import FmuComponent
    from orchestrator.components.served import serve

    answered: list[int] = []

    class Recording(ServedInstance):
        def handle(self, payload: bytes) -> bytes:
            answered.append(threading.get_native_id())
            return super().handle(payload)

    port = free_port()
    fmu = UnpackedFmu.open(fmu_dir / "Vehicle.fmu")
    variables = fmu.description.modelVariables
    inputs = [v.name for v in variables if v.causality == "input"]
    outputs = [v.name for v in variables if v.causality == "output"]
    stop = threading.Event()
    with open_session(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"]), "server") as session:
        serving = threading.Thread(target=serve, args=(Recording(fmu), session, "platoon/fmu/vehicle1", stop, on_zenoh_thread))
        serving.start()
        starts = fmu.start_values()
        defaults = [float(starts[n]) for n in inputs]
        remote = RemoteComponent("vehicle1", "platoon/fmu/vehicle1", f"tcp/127.0.0.1:{port}", {}, inputs, outputs,
                                 defaults, RemoteHost((f"tcp/127.0.0.1:{port}",)))
        local = FmuComponent("vehicle1", fmu, {})
        try:
            for component in (remote, local):
                component.initialize(0.0)
                component.end_initialization()
            for k in range(5):
                for component in (remote, local):
                    component.set_inputs([value + 0.1 * k for value in defaults])
                    component.step(k * 0.01, 0.01)
                assert remote.get_outputs() == local.get_outputs()
            names = {(Path("/proc/self/task") / str(native) / "comm").read_text().strip() for native in answered}
        finally:
            remote.close()
            local.close()
            stop.set()
            serving.join(10)
    fmu.cleanup()
    assert len(answered) >= 7 and threading.main_thread().native_id not in answered
    zenohs = {name for name in names if name.split("-")[0] in ("rx", "tx", "net", "acc", "app")}  # Zenoh's runtimes
    assert (zenohs == names) if on_zenoh_thread else not zenohs, names
