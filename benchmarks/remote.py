"""Suite ``remote``: what a macro step costs when the vehicles are remote, on loopback.

``max(N)`` ``platoon serve Vehicle`` processes are started (native FMUs, each a process of its own on a
free 127.0.0.1 port); for each N this process opens N of them as a run would (``RemoteComponent``, one
Zenoh session) and times a macro step of N vehicles four ways, interleaved, in the same sitting:

* ``lockstep``: as the Jacobi master steps them: every step request sent, then every reply collected
  (one round trip for all N);
* ``one by one``: each vehicle asked and answered before the next (what a master that waits per call
  costs: N round trips);
* ``local``: the same N Vehicle FMUs in this process (``FmuComponent``), no network;
* ``round trip``: a bare ping to one server (the protocol's PING: Zenoh there and back, no FMU).

Each server's own work (a native step is about a microsecond) is small against a round trip, so
lockstep/one-by-one shows how much of the N round trips overlap. Beside each remote variant, the CPU
it cost per macro step, this process's (``time.process_time``) and the N servers' together (their
/proc/<pid>/stat, Linux): on 2 cores a lockstep step cannot take less wall time than half their sum, so
the CPU columns say whether the step is bound by CPU or by waiting. Times in the JSON are seconds.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from .common import BenchError, Progress, interleaved
from .hil import Helper, free_port

VARIANTS = ("lockstep", "one by one", "local", "round trip")
STEP = 0.01


def served(name: str, port: int, scratch: Path) -> Helper:
    """A ``platoon serve Vehicle`` on 127.0.0.1:``port``, stopped when its block ends."""
    return Helper([sys.executable, "-m", "orchestrator", "serve", "Vehicle", "--name", name, "--fmus", "native",
                   "--listen", f"tcp/127.0.0.1:{port}"], "ready", scratch, name)


def _per_step(components: list[Any], steps: int, lockstep: bool) -> float:
    """Seconds per macro step of ``components`` (inputs at their defaults)."""
    for component in components:
        component.set_inputs(component.input_defaults)
    started = time.perf_counter()
    for k in range(steps):
        if lockstep:
            for component in components:
                component.step(k * STEP, STEP)
            for component in components:
                component.get_outputs()
        else:
            for component in components:
                component.step(k * STEP, STEP)
                component.get_outputs()
    return (time.perf_counter() - started) / steps


def _cpu_seconds(pids: list[int]) -> float:
    """CPU seconds (user + system) the processes ``pids`` have used so far (0 where /proc cannot say)."""
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return 0.0
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of stat)
    return total / os.sysconf("SC_CLK_TCK")


def _round_trip(host: Any, key: str, count: int) -> float:
    """Median seconds of ``count`` bare pings to the server at ``key``."""
    from bridge import fmu_wire as wire
    from bridge.fmu_client import first_reply

    times = []
    for _ in range(count):
        started = time.perf_counter()
        if first_reply(host.ask(key, wire.request(wire.PING, bytes(wire.TOKEN_SIZE), 0), 2.0)) is None:
            raise BenchError(f"no reply to a ping from {key}")
        times.append(time.perf_counter() - started)
    return statistics.median(times)


class _Fleet:
    """N vehicles, remote (opened on the servers) and local, ready to step."""

    def __init__(self, n: int, endpoints: list[str], fmu: Any) -> None:
        from bridge.fmu_client import RemoteComponent, RemoteHost
        from bridge.fmu_wire import fmu_key
        from orchestrator.components.fmu import FmuComponent

        self.host = RemoteHost(tuple(endpoints[:n]))  # as a run's (orchestrator/components/remote.py)
        self.key = fmu_key("platoon", "vehicle1")
        inputs = [v.name for v in fmu.description.modelVariables if v.causality == "input"]
        outputs = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
        starts = fmu.start_values()
        defaults = [float(starts[name]) for name in inputs]
        self.remote = [RemoteComponent(f"vehicle{i + 1}", fmu_key("platoon", f"vehicle{i + 1}"), endpoints[i], {},
                                       inputs, outputs, defaults, self.host, step_timeout=5.0) for i in range(n)]
        self.local = [FmuComponent(f"vehicle{i + 1}", fmu, {}) for i in range(n)]
        for component in (*self.remote, *self.local):
            component.initialize(0.0)
            component.end_initialization()

    def close(self) -> None:
        for component in (*self.remote, *self.local):
            component.close()


def run(counts: list[int], steps: int = 500, rounds: int = 3, progress: Progress | None = None) -> dict[str, Any]:
    from orchestrator.components.fmu import UnpackedFmu
    from orchestrator.components.kinds import ensure_fmus
    from fmus.builders import DEFAULT_OUT

    started = time.perf_counter()
    fmu = UnpackedFmu.open(ensure_fmus(DEFAULT_OUT, "native", ("Vehicle",))["Vehicle"])  # built once, before the servers
    with tempfile.TemporaryDirectory(prefix="bench-remote-") as scratch, ExitStack() as stack:
        ports = [free_port() for _ in range(max(counts))]
        servers = [stack.enter_context(served(f"vehicle{i + 1}", port, Path(scratch))) for i, port in enumerate(ports)]
        pids = [server.process.pid for server in servers]
        endpoints = [f"tcp/127.0.0.1:{port}" for port in ports]
        fleets: dict[int, _Fleet] = {}

        def measure(n: int, variant: str) -> dict[str, Any]:
            if n not in fleets:
                for old in fleets.values():
                    old.close()
                fleets.clear()
                fleets[n] = _Fleet(n, endpoints, fmu)
            fleet = fleets[n]
            if variant == "round trip":
                return {"n": n, "variant": variant, "seconds": _round_trip(fleet.host, fleet.key, steps)}
            if variant == "local":
                return {"n": n, "variant": variant, "seconds": _per_step(fleet.local, steps, False)}
            run_cpu, servers_cpu = time.process_time(), _cpu_seconds(pids[:n])
            seconds = _per_step(fleet.remote, steps, variant == "lockstep")
            return {"n": n, "variant": variant, "seconds": seconds, "run_cpu": (time.process_time() - run_cpu) / steps,
                    "servers_cpu": (_cpu_seconds(pids[:n]) - servers_cpu) / steps}

        def describe(sample: dict[str, Any]) -> str:
            cpu = (f"  (CPU: run {sample['run_cpu'] * 1e3:.3f}, servers {sample['servers_cpu'] * 1e3:.3f} ms)"
                   if "run_cpu" in sample else "")
            return f"N = {sample['n']:>3}  {sample['variant']:<11} {sample['seconds'] * 1e3:8.3f} ms{cpu}"

        try:
            samples = interleaved(rounds, counts, VARIANTS, measure, describe, progress)
        finally:
            for fleet in fleets.values():
                fleet.close()
    fmu.cleanup()
    medians = {n: {v: statistics.median(s["seconds"] for s in samples if s["n"] == n and s["variant"] == v)
                   for v in VARIANTS} for n in counts}
    cpu = {n: {f"{v} {side}": statistics.median(s[side] for s in samples if s["n"] == n and s["variant"] == v)
               for v in ("lockstep", "one by one") for side in ("run_cpu", "servers_cpu")} for n in counts}
    return {"steps": steps, "rounds": rounds, "counts": counts, "medians": medians, "cpu": cpu,
            "lockstep_over_one_by_one": {n: m["lockstep"] / m["one by one"] for n, m in medians.items()},
            "samples": samples, "wall_s": time.perf_counter() - started}


def render(result: dict[str, Any]) -> Any:
    from rich.table import Table

    table = Table(title=f"cost per macro step, ms (median of {result['rounds']} rounds x {result['steps']} steps; "
                        "servers on 127.0.0.1, native Vehicle FMUs)", title_justify="left",
                  caption="lockstep: every remote vehicle asked at once (the Jacobi master); one by one: each "
                          "answered before the next is asked; local: the FMUs in this process; round trip: a bare "
                          "Zenoh query to one server and its reply; lockstep CPU: ms of CPU per lockstep step, this "
                          "process's and the servers' together (on 2 cores the step takes at least half their sum)",
                  caption_justify="left")
    for column in ("N", *VARIANTS, "lockstep / one by one", "lockstep CPU: run + servers"):
        table.add_column(column, justify="right")
    for n, values in result["medians"].items():
        cpu = result["cpu"][n]
        table.add_row(str(n), *(f"{values[v] * 1e3:.3f}" for v in VARIANTS),
                      f"{result['lockstep_over_one_by_one'][n]:.2f}",
                      f"{cpu['lockstep run_cpu'] * 1e3:.2f} + {cpu['lockstep servers_cpu'] * 1e3:.2f}")
    return table
