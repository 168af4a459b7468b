"""Suite ``hil``: round trip and step jitter of hardware in the loop over Zenoh, on loopback.

Everything runs on 127.0.0.1, each peer a separate process on a free port:

* ``transport``: a bare Zenoh ping-pong between this process and a tiny echo process
  (``python -m benchmarks.hil echo ENDPOINT [ZENOH_CONFIG]``): a wheel-command-sized ping out
  on a robot's command key, a pose-sized pong back on its pose key, one every 5 ms, with the
  publishers the bridge uses (express, BLOCK). This is the transport's share of a round trip; once
  over TCP, once over mutual TLS with the access control of ``platoon hil-certs`` (``transport
  TLS+ACL``: the cost of the secure lab, docs/hil.md);
* ``live``: real live runs of ``configs/hil/m3pi_live3.toml`` (vehicle 3 a live robot; ``run_scenario``
  in this process, paced to wall time) against ``platoon m3pi-emulator`` in a subprocess, at step
  0.01 s (100 Hz) and 0.005 s (200 Hz) with the emulator's pose rate 200 Hz (the paper's motion
  capture), and at 100 Hz with poses at 1000 Hz. Each run reports the link's round trip (wheel command
  sent -> first pose whose ``command_seq`` says the robot had applied it, ``LiveVehicle``) and the
  pacer's step jitter (lateness of each communication point after its wall-clock deadline) and overruns;
  the 100 Hz one once more over TLS+ACL;
* ``checks``: what the checks of every message cost, in this process: a pose through the host's
  checks (decode, claim, age, sequence: ``bridge.claim.HostClaim``) and a command through the robot
  side's (``RobotClaim.check``), each against decoding alone.

A pose is taken every 1/rate s, so a command waits up to one pose period for the next pose: the live
round trip is the transport's plus that wait. Each emulator serves one run (its command numbers start
afresh), and is always stopped (terminate, then kill). Times in the JSON are seconds.
"""

from __future__ import annotations

import os
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any


from orchestrator.support.text import ms_text

from .common import BenchError, BenchUsageError, Progress, interleaved

CONFIG = Path("configs") / "hil" / "m3pi_live3.toml"
POSE_RATE = 200.0  # Hz, the paper's motion capture
# (step s, emulator pose rate Hz, over TLS+ACL) of the live runs, each once per round
LIVE_RUNS = ((0.01, POSE_RATE, False), (0.005, POSE_RATE, False), (0.01, 1000.0, False), (0.01, POSE_RATE, True))
PING_INTERVAL = 0.005  # s between two pings (200 Hz)
PING_WARMUP = 10  # first pings not counted (connection set-up)
BENCH_ROBOT = 1  # the ping-pong's keys are robot 1's: a command out, a pose back, as the lab's ACL allows them
LAB_HOST, LAB_ROBOT_SIDE = "bench-host", "bench-robot"  # the secure lab's two hosts (robots 1 and 3)
CHECKED_MESSAGES = 20000  # messages per timing of the checks
START_TIMEOUT = 30.0  # s for a helper process to be ready
_SEQ = struct.Struct("<I")
STATS = ("median", "p99", "max")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Helper:
    """A helper process (stderr to a file) that is ready once its stderr holds ``ready``; always stopped.

    Its log is a new file of its own in ``scratch`` (``<name>.<random>.stderr``, made by ``mkstemp``:
    created exclusively, never following a symlink), so by the output rule (orchestrator/support/output.py)
    it never opens or replaces what is there: not an earlier helper's log, not a FIFO (which would block
    the open until someone read it), not a device. A log a helper writes while it runs cannot be renamed
    into place when complete; it is read while it grows, and removed with ``scratch``."""

    def __init__(self, command: list[str], ready: str, scratch: Path, name: str) -> None:
        self.command, self.ready, self.name, self.scratch = command, ready, name, scratch
        self.log: Path | None = None
        self.process: subprocess.Popen | None = None

    def stderr(self) -> str:
        return self.log.read_text()[-2000:] if self.log is not None and self.log.exists() else ""

    def __enter__(self) -> "Helper":
        fd, name = tempfile.mkstemp(prefix=f"{self.name}.", suffix=".stderr", dir=self.scratch)
        self.log = Path(name)
        with os.fdopen(fd, "w") as log:
            self.process = subprocess.Popen(self.command, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log)
        try:
            deadline = time.monotonic() + START_TIMEOUT
            while self.ready not in self.log.read_text():
                if self.process.poll() is not None or time.monotonic() > deadline:
                    state = f"exited {self.process.returncode}" if self.process.returncode is not None else "not ready"
                    raise BenchError(f"{self.name} ({' '.join(self.command)}) {state}:\n{self.stderr()}")
                time.sleep(0.02)
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        process = self.process
        if process is None or process.poll() is not None:
            return
        process.stdin.close()  # the echo leaves on end of input
        process.terminate()
        try:
            process.wait(5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


# -- transport: Zenoh ping-pong ----------------------------------------------------------------------


def _keys() -> Any:
    from bridge.protocol import DEFAULT_PREFIX, RobotKeys

    return RobotKeys(DEFAULT_PREFIX, BENCH_ROBOT)


def make_lab(scratch: Path) -> Path:
    """A secure lab (``platoon hil-certs``) of a run host and a robot side for robots 1 and 3; its folder."""
    from bridge.lab import Lab
    from orchestrator.support.lab_files import write_lab

    folder = scratch / "lab"
    if not (folder / f"{LAB_HOST}.json5").exists():
        write_lab(Lab(run_hosts={LAB_HOST: {BENCH_ROBOT, 3}}, robot_sides={LAB_ROBOT_SIDE: {BENCH_ROBOT, 3}}), folder, 1)
    return folder


def echo(endpoint: str, config_file: str | None = None) -> None:
    """Echo side: listen on ``endpoint``, answer every ping with a pose-sized pong, until stdin ends."""
    import zenoh

    from bridge.protocol import POSE_SIZE
    from bridge.session import open_session, zenoh_config

    keys = _keys()
    with open_session(zenoh_config(listen=[endpoint], config_file=config_file), "bench echo") as session:
        pong = session.declare_publisher(keys.pose, congestion_control=zenoh.CongestionControl.BLOCK, express=True)
        answer = session.declare_subscriber(  # noqa: F841  (kept: a subscriber lives as long as its handle)
            keys.wheels, lambda sample: pong.put(sample.payload.to_bytes()[:_SEQ.size].ljust(POSE_SIZE, b"\0")))
        token = session.liveliness().declare_token(keys.alive)  # noqa: F841
        print(f"echo ready on {endpoint}", file=sys.stderr, flush=True)
        sys.stdin.read()


def ping_pong(seconds: float, scratch: Path, secure: bool = False) -> dict[str, Any]:
    """Round trips of pings to an echo process, one every ``PING_INTERVAL`` for ``seconds`` s (over mutual
    TLS with the lab's access control if ``secure``)."""
    import zenoh

    from fmus.component import percentile_summary
    from bridge.protocol import WHEELS_SIZE
    from bridge.session import open_session, zenoh_config

    endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_port()}"
    lab = make_lab(scratch) if secure else None
    echo_config = [str(lab / f"{LAB_ROBOT_SIDE}.json5")] if lab else []
    keys = _keys()
    sent: dict[int, float] = {}
    trips: list[tuple[int, float]] = []  # (ping number, round trip s)
    answered = threading.Event()

    def on_pong(sample: zenoh.Sample) -> None:
        received = time.perf_counter()
        seq = _SEQ.unpack_from(sample.payload.to_bytes())[0]
        if seq in sent:
            trips.append((seq, received - sent.pop(seq)))
            answered.set()

    count = PING_WARMUP + max(1, round(seconds / PING_INTERVAL))
    config = zenoh_config(connect=[endpoint], config_file=str(lab / f"{LAB_HOST}.json5") if lab else None)
    with Helper([sys.executable, "-m", "benchmarks.hil", "echo", endpoint, *echo_config], "echo ready", scratch,
                "echo") as helper, open_session(config, "bench ping") as session:
        answers = session.declare_subscriber(keys.pose, on_pong)  # noqa: F841
        ping = session.declare_publisher(keys.wheels, congestion_control=zenoh.CongestionControl.BLOCK, express=True)
        deadline = time.monotonic() + START_TIMEOUT
        while not any(reply.ok is not None for reply in session.liveliness().get(keys.alive, timeout=1.0)):
            if time.monotonic() > deadline:
                raise BenchError(f"the echo process on {endpoint} did not appear:\n{helper.stderr()}")
            time.sleep(0.05)
        started = time.perf_counter()
        for seq in range(1, count + 1):
            answered.clear()
            sent[seq] = time.perf_counter()
            ping.put(_SEQ.pack(seq).ljust(WHEELS_SIZE, b"\0"))
            answered.wait(1.0)
            sent.pop(seq, None)  # unanswered within 1 s: lost
            pause = started + seq * PING_INTERVAL - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
    counted = [trip for seq, trip in trips if seq > PING_WARMUP]
    if not counted:
        raise BenchError(f"no pong came back from the echo process on {endpoint}:\n{helper.stderr()}")
    return {"kind": "transport", "secure": secure, "pings": count - PING_WARMUP, "lost": count - len(trips),
            "link": percentile_summary("round_trip", counted)}


# -- live runs against the emulator -------------------------------------------------------------------


def live_run(step: float, rate: float, seconds: float, scratch: Path, secure: bool = False) -> dict[str, Any]:
    """One paced live run of ``CONFIG`` (step ``step``, ``seconds`` long) against a fresh emulator at ``rate``
    (over mutual TLS with the lab's access control if ``secure``)."""
    from orchestrator.scenario.config import load_config
    from orchestrator.execution.run import run_scenario

    from .scenarios import platoon_command

    endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_port()}"
    connect = f'vehicles.3.connect=["{endpoint}"]'
    # a measurement, not a safety test: a busy machine's stall of a few hundred ms must not end the run
    overrides = [f"simulation.step={step!r}", f"simulation.stop_time={seconds!r}", connect, "hil.pose_timeout=5.0"]
    emulator = [*platoon_command(), "m3pi-emulator", "--config", str(CONFIG), "--set", connect, "--rate", f"{rate:g}",
                "--duration", f"{seconds + 120:g}"]  # --duration: never outlives a bench that was killed
    if secure:
        lab = make_lab(scratch)
        overrides.append(f'vehicles.3.zenoh_config="{lab / f"{LAB_HOST}.json5"}"')
        emulator += ["--zenoh-config", str(lab / f"{LAB_ROBOT_SIDE}.json5")]
    parsed, _ = load_config(CONFIG, overrides)
    with Helper(emulator, "configured", scratch, "m3pi-emulator") as helper:
        result = run_scenario(parsed, CONFIG.read_text(), None, engine="python")
        if result.status != "completed":
            raise BenchError(f"live run (step {step:g} s, poses at {rate:g} Hz) {result.status}: {result.error}\n"
                             f"emulator: {helper.stderr()}")
    links = {name: stats for name, stats in result.live.items() if name != "pacing"}
    return {"kind": "live", "step": step, "pose_rate": rate, "secure": secure, "seconds": seconds,
            "pacing": result.live["pacing"],
            "link": next(iter(links.values())), "vehicles": sorted(links), "wall_s": result.wall_time}


def label(sample: dict[str, Any]) -> str:
    """``transport``, or ``step 100 Hz, poses 200 Hz`` for a live run; `` TLS+ACL`` added over the secure lab."""
    secure = ", TLS+ACL" if sample.get("secure") else ""
    if sample["kind"] == "transport":
        return "transport" + secure
    return f"step {1 / sample['step']:g} Hz, poses {sample['pose_rate']:g} Hz" + secure


def _seconds_per_call(timings: dict[str, tuple[Any, list[Any], Any]], repeats: int = 5) -> dict[str, float]:
    """Best of ``repeats`` timings, per item (s), of each ``name: (function, items, reset)``, taken in turn
    (so that a busy moment of the machine hits all of them alike); ``reset`` runs before each timing."""
    best = {name: float("inf") for name in timings}
    for _ in range(repeats):
        for name, (function, items, reset) in timings.items():
            reset()
            started = time.perf_counter()
            for item in items:
                function(item)
            best[name] = min(best[name], (time.perf_counter() - started) / len(items))
    return best


def check_costs(count: int = CHECKED_MESSAGES) -> dict[str, float]:
    """Seconds per message: a pose through the host's checks and a command through the robot side's, each
    beside decoding alone (the reference, timed in the same run)."""
    from bridge.claim import HostClaim, RobotClaim
    from bridge.lab_key import LabKey, new_secret
    from bridge.protocol import Pose, RobotKeys, WheelCommand, check_pose_time, decode_pose, decode_wheels, \
        encode_pose, encode_wheels

    now = time.time()
    host = HostClaim()
    key, wheels = LabKey(new_secret(), Path("bench.key")), RobotKeys("platoon", 3).wheels
    robot = RobotClaim(key, wheels)  # the MAC check included, as every robot side does it
    poses = [encode_pose(Pose(seq, seq, now, 0.5, 0.5, 1.0, host.claim)) for seq in range(1, count + 1)]
    commands = [encode_wheels(WheelCommand(seq, now + 3.0, 0.3, 0.3, host.claim), key, wheels)
                for seq in range(1, count + 1)]
    request = encode_wheels(WheelCommand(0, now + 3.0, 0.0, 0.0, host.claim), key, wheels)

    def host_checks(payload: bytes) -> None:  # as LiveVehicle._on_pose
        pose = decode_pose(payload)
        host.source(pose)
        check_pose_time(pose, now, 1.0)
        host.accept(pose, count)

    def new_host() -> None:
        host.__init__(claim=host.claim)  # type: ignore[misc]  (a fresh claim state: sequences from 1)

    def new_claim() -> None:  # a fresh robot side granting the claim (an ended claim is never granted again)
        robot.__init__(key, wheels)  # type: ignore[misc]
        robot.host_appeared(host.claim, now)
        robot.check(request, now, "robot")

    def nothing() -> None:
        pass

    return _seconds_per_call({"pose.decode": (decode_pose, poses, nothing),
                              "pose.checks": (host_checks, poses, new_host),
                              "command.decode": (decode_wheels, commands, nothing),
                              "command.checks": (lambda payload: robot.check(payload, now, "robot"), commands,
                                                 new_claim)})


# -- the suite -----------------------------------------------------------------------------------------


def run(seconds: float = 10.0, rounds: int = 1, progress: Progress | None = None) -> dict[str, Any]:
    if not CONFIG.is_file():
        raise BenchUsageError(f"no {CONFIG} in {Path.cwd()} (run from the repository)")
    from .platoon import fmu_files

    fmu_files()  # build once, as the first `platoon run` would
    started = time.perf_counter()
    variants = [("transport", None, None, False), ("transport", None, None, True),
                *(("live", step, rate, secure) for step, rate, secure in LIVE_RUNS)]

    def describe(sample: dict[str, Any]) -> str:
        line = f"{label(sample):<34} round trip median {ms_text(sample['link'].get('round_trip.median'))} ms"
        if sample["kind"] == "live":
            pacing = sample["pacing"]
            line += f", jitter median {ms_text(pacing.get('jitter.median'))} ms, overruns {pacing['overruns']}"
        return line

    with tempfile.TemporaryDirectory(prefix="bench-hil-") as scratch:
        def measure(_: Any, variant: tuple) -> dict[str, Any]:
            kind, step, rate, secure = variant
            if kind == "transport":
                return ping_pong(seconds / 2, Path(scratch), secure)
            return live_run(step, rate, seconds, Path(scratch), secure)

        samples = interleaved(rounds, [None], variants, measure, describe, progress)
    medians: dict[str, dict[str, Any]] = {}
    for name in dict.fromkeys(label(s) for s in samples):
        mine = [s for s in samples if label(s) == name]
        numbers = [{**{k: v for k, v in s["link"].items() if k.startswith("round_trip.")}, **s.get("pacing", {})}
                   for s in mine]
        medians[name] = {"step": mine[0].get("step"), "pose_rate": mine[0].get("pose_rate"),
                         "secure": mine[0]["secure"],
                         **{key: statistics.median(n[key] for n in numbers) for key in numbers[0]}}
    transport = medians["transport"]["round_trip.median"]
    ratios = {name: values["round_trip.median"] / transport for name, values in medians.items() if name != "transport"}
    checks = check_costs()
    return {"config": str(CONFIG), "seconds": seconds, "rounds": rounds, "ping_interval": PING_INTERVAL,
            "live_runs": [{"step": step, "pose_rate": rate, "secure": secure} for step, rate, secure in LIVE_RUNS],
            "medians": medians, "round_trip_over_transport": ratios, "checks": checks,
            "checks_over_decode": {"pose": checks["pose.checks"] / checks["pose.decode"],
                                   "command": checks["command.checks"] / checks["command.decode"]},
            "samples": samples, "wall_s": time.perf_counter() - started}


def render(result: dict[str, Any]) -> Any:
    """Two rich tables: round trips (with the transport's share), then the step jitter of the live runs."""
    from rich.console import Group
    from rich.table import Table

    medians, rounds = result["medians"], result["rounds"]
    over = f"median of {rounds} rounds" if rounds > 1 else "1 round"
    trips = Table(title=f"round trip, ms ({over}; loopback, emulator in its own process)", title_justify="left",
                  caption="transport: bare Zenoh ping-pong between two processes; live runs: wheel command sent -> "
                          f"first pose taken after the robot applied it; a pose is taken every period (emulator at "
                          f"{POSE_RATE:g} Hz = the paper's motion capture, and at 1000 Hz)",
                  caption_justify="left")
    for column in ("measurement", "period", "median", "p99", "max", "x transport"):
        trips.add_column(column, justify="left" if column == "measurement" else "right")
    for name, values in medians.items():
        rate = values["pose_rate"]
        ratio = result["round_trip_over_transport"].get(name)
        trips.add_row(name, ms_text(1 / rate) if rate else "-", *(ms_text(values[f"round_trip.{s}"]) for s in STATS),
                      f"{ratio:.1f}" if ratio else "-")
    jitter = Table(title=f"step jitter, ms: lateness of each communication point after its deadline ({over})",
                   title_justify="left")
    for column in ("live run", "median", "p99", "max", "overruns"):
        jitter.add_column(column, justify="left" if column == "live run" else "right")
    for name, values in medians.items():
        if "jitter.median" in values:
            jitter.add_row(name, *(ms_text(values[f"jitter.{s}"]) for s in STATS),
                           f"{values['overruns']:g} of {values['points']:g}")
    checks = Table(title="checks per message, us (this process; best of 5 over "
                         f"{CHECKED_MESSAGES} messages)", title_justify="left",
                   caption="checks: decode, claim, age or deadline, sequence (bridge.claim); the reference is "
                           "decoding alone", caption_justify="left")
    for column in ("message", "decode", "all checks", "x decode"):
        checks.add_column(column, justify="left" if column == "message" else "right")
    for kind, where in (("pose", "pose at the host"), ("command", "command at the robot side")):
        values = result["checks"]
        checks.add_row(where, f"{values[f'{kind}.decode'] * 1e6:.2f}", f"{values[f'{kind}.checks'] * 1e6:.2f}",
                       f"{result['checks_over_decode'][kind]:.1f}")
    return Group(trips, jitter, checks)



if __name__ == "__main__":  # the echo side of the ping-pong, started by `platoon bench hil`
    from orchestrator.support.internal_entry import check_arguments

    check_arguments(sys.argv[1:], "python -m benchmarks.hil echo ENDPOINT [ZENOH_CONFIG] (the benchmark: "
                    "platoon bench hil)", "The echo process of `platoon bench hil`'s Zenoh ping-pong; the benchmark "
                    "starts it.", fits=lambda args: len(args) in (2, 3) and args[0] == "echo")
    echo(sys.argv[2], sys.argv[3] if len(sys.argv) > 3 else None)
