"""Run a scenario end to end: build the FMUs if needed, wire, step, trace; or the monolithic reference.

Whatever happens, the trace keeps every step recorded so far and says how the run ended
(``platoon.run`` metadata: completed, failed with the component, time and reason, or interrupted).
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import signal
import threading
import time as clock
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import fmus
from fmus.build import DEFAULT_OUT, FMU_NAMES
from fmus.model.factory import target_stepper, vehicle_stepper
from fmus.model.platoon import PlatoonSystem

from . import __version__
from .components import ComponentError, FmuComponent, UnpackedFmu
from .config import Config
from .fmu_kinds import resolve_fmu_kind
from .live import LiveReporter, check_live_options, live_component, live_names
from .master import Master
from .metrics import RunningSummary, VehicleSummary, running_summary
from .realtime import Pacer
from .native import NativeComponent, NativeMaster, available as native_available
from .scenario import Scenario, build_scenario, step_count
from .trace.foxglove import SCENE_RATE, FoxgloveChannels, SceneSettings
from .trace.output import Claim, claim, claim_new
from .trace.writer import NullTraceWriter, TraceWriteError, TraceWriter
from .trace.format import BLOCK, FLUSH_INTERVAL
from .trace.worker import WORKER_BLOCK, TraceProcess, TraceWorker, TraceWorkerError

if TYPE_CHECKING:
    from .live_view import LiveView

# Where the trace is encoded: "inline" in the stepping process, "process" in a second process
# (orchestrator/trace/worker.py), "auto": a second process when the machine has a spare core and the
# run records enough messages that encoding them outweighs the worker's start-up (about 0.5-1 s).
TRACE_WRITERS = ("auto", "inline", "process")
WORKER_MESSAGES = 10_000  # recorded rows x components from which "auto" picks "process" (docs/performance.md)

# "native": the compiled stepping core (orchestrator/native); "python": the same master in Python on
# FMPy; "monolithic": the whole platoon as one system, no FMUs stepped (the accuracy reference).
ENGINES = ("native", "python", "monolithic")


def choose_trace_writer(requested: str, rows: int, components: int) -> str:
    """"inline" or "process" for a run recording ``rows`` points of ``components`` components."""
    if requested not in TRACE_WRITERS:
        raise ValueError(f"unknown trace writer {requested!r}; expected one of {', '.join(TRACE_WRITERS)}")
    if requested != "auto":
        return requested
    spare_core = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1) >= 2
    return "process" if spare_core and rows * components >= WORKER_MESSAGES else "inline"


def default_engine(config: Config | None = None) -> str:
    """The native engine when its extension is built (bit-identical results), else the Python one; the
    Python one for a config with a live vehicle (the native core steps FMUs only)."""
    if config is not None and config.live_vehicles():
        return "python"
    return "native" if native_available() else "python"

Tick = Callable[[int], None]


@dataclass
class RunResult:
    trace: Path | None  # None when run without a trace
    steps: int
    wall_time: float
    status: str  # "completed" | "failed" | "interrupted"
    error: str | None = None
    signal: int | None = None  # SIGINT or SIGTERM when interrupted
    # wall seconds by phase: "open" (FMUs checked and unpacked, before wall_time starts), "setup" (trace
    # writer, metadata), "initialize" (instantiate, initialization
    # mode), "steps" (the stepping loop, recording included), "finish" (FMUs closed, trace finalized)
    timings: dict[str, float] = field(default_factory=dict)
    # with live vehicles: "pacing" (step jitter, overruns) and each live vehicle's link statistics
    live: dict[str, dict] = field(default_factory=dict)
    # run_scenario(..., summarize=True) of a completed run: the summary of the recorded rows, as
    # `platoon report` computes it from the trace (None otherwise)
    summary: list[VehicleSummary] | None = None
    fmus: str = ""  # the FMU kind stepped: "native" or "python" (orchestrator/fmu_kinds.py)


def tool_versions() -> dict[str, str]:
    return {
        "platoon-cosim": __version__,
        "fmus": fmus.__version__,
        # from the installed metadata: importing pythonfmu only for its version costs ~80 ms of start-up
        "fmpy": importlib.metadata.version("fmpy"),
        "pythonfmu": importlib.metadata.version("pythonfmu"),
        "python": platform.python_version(),
    }


def _descriptions(fmu: UnpackedFmu) -> dict[str, str]:
    return {
        v.name: f"{v.description} [{v.unit}]" if v.unit else v.description
        for v in fmu.description.modelVariables
        if v.causality == "output"
    }


def _open_fmus(fmu_dir: Path, kind: str) -> dict[str, UnpackedFmu]:
    from .fmu_kinds import ensure_fmus

    return {name: UnpackedFmu.open_cached(path) for name, path in ensure_fmus(fmu_dir, kind, FMU_NAMES).items()}


def open_trace_writer(
    kind: str,
    path: Path,
    components: list[tuple[str, list[str]]],
    descriptions: dict[str, dict[str, str]] | None,
    config: Config,
    every: int = 1,
    scene_rate: float = SCENE_RATE,
    foxglove: bool = True,
    process: TraceProcess | None = None,
    publish: Path | None = None,
    native: bool = False,
) -> "TraceWriter | TraceWorker":
    """A run's trace writer, encoding in this process ("inline") or in a worker ("process"): same file.

    ``foxglove`` adds the Foxglove channels at ``scene_rate``; ``process`` is a worker started earlier;
    ``publish``: the final path, ``path`` being the aside file renamed onto it once finalized;
    ``native``: float64 blocks (the native engine's) are encoded in C (orchestrator/trace/native_rows.py).
    """
    if kind == "process":
        return TraceWorker(path, components, descriptions, every=every, process=process, publish=publish,
                           foxglove=(SceneSettings.of(config), components, scene_rate) if foxglove else None,
                           native=native)
    return TraceWriter(path, components, descriptions, every=every, publish=publish, native=native,
                       foxglove=FoxgloveChannels(config, components, scene_rate) if foxglove else None)


def _trace_encoder(writer: Any) -> str:
    """"native" when the trace's rows are encoded in C (orchestrator/trace/native_rows.py), else "python"."""
    return "native" if getattr(getattr(writer, "traced", writer), "native", False) else "python"  # behind a live view's tee


def _finalize_trace(writer: "TraceWriter | TraceWorker | NullTraceWriter", status: str, error: str | None,
                    failed_at: float | None, signum: int | None, engine: str, master: str) -> tuple[str, str | None]:
    """Write the run's last log line and ``platoon.run`` record, and close the file; returns (status, error).

    A non-finite output in the last buffered block turns the run into a failure here. If the trace
    writer process died, the file keeps its complete chunks (recoverable) and the run is a failure.
    """
    try:
        try:
            writer.flush()
        except ComponentError as failure:  # a non-finite output in the last block
            status, error, failed_at = "failed", str(failure), failure.time
        last = writer.last_time
        if status == "interrupted":
            error = f"{_signal_text(signum or signal.SIGINT)} at t = {last if last is not None else 0.0:.6g} s"
            writer.log(last or 0.0, "Warning", f"run {error}")
        elif status == "failed":
            writer.log(failed_at if failed_at is not None else (last or 0.0), "Error", f"run failed: {error}")
        else:
            writer.log(last or 0.0, "Info", f"run completed: {writer.rows_recorded} points recorded")
        run_record = {"status": status, "error": error or "", "engine": engine, "master": master,
                      "steps_recorded": writer.rows_recorded, "last_time": "" if last is None else repr(float(last))}
        if signum is not None:
            run_record["signal"] = signal.Signals(signum).name
        writer.metadata("platoon.run", run_record)
        writer.close()
    except TraceWorkerError as failure:
        if status != "interrupted":
            status, error = "failed", str(failure).splitlines()[0]
    except TraceWriteError as failure:  # e.g. a full disk: the file keeps its complete chunks
        status, error = "failed", str(failure)
    return status, error


def _monolithic_system(scenario: Scenario, fmus_by_kind: dict[str, UnpackedFmu]) -> PlatoonSystem:
    """The same steppers the FMUs would hold, from the same parameter values (FMU defaults + config)."""
    steppers = []
    for spec in scenario.components:
        values = {**fmus_by_kind[spec.fmu].start_values(), **spec.parameters}
        steppers.append(target_stepper(values, 0.0) if spec.fmu == "VirtualTarget" else vehicle_stepper(values, 0.0))
    return PlatoonSystem(steppers[0], steppers[1:])


class Interrupted(KeyboardInterrupt):
    """A run stopped by a signal (SIGINT or SIGTERM) at a communication point."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


STALLED_WRITER_GRACE = 2.0  # s a trace writer process may take nothing after a second signal before it is stopped


class _StopRequest:
    """Signal handlers for the length of a run.

    The first SIGINT or SIGTERM only raises a flag, which the observer checks after recording each
    communication point: the run stops between two steps, never inside an FMU call (pythonfmu FMUs
    run Python code, where a KeyboardInterrupt would turn into an FMU error). A second signal while
    the loop still runs raises at once, in case a component hangs. After the loop, signals are only
    noted until the trace is finalized (except while waiting for a trace writer process, which a
    further signal stops: ``finishing``); then the previous handlers come back. A second signal raised
    inside an FMU call makes that call fail: ``forced`` tells the run it was an interruption.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signum = 0
        self.armed = False
        self.forced = False  # a second signal raised Interrupted, possibly inside an FMU call
        self.finishing = False  # waiting for the trace writer process: any further signal ends the wait
        self._previous: dict[int, object] = {}

    def _handler(self, signum: int, frame: object) -> None:
        if self.signum and (self.armed or self.finishing):
            self.forced = True
            raise Interrupted(signum)
        self.signum = self.signum or signum

    def check(self) -> None:
        """Raise ``Interrupted`` once a signal arrived: called between two steps (never inside an FMU)."""
        if self.signum:
            raise Interrupted(self.signum)

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # signal handlers can only be set from the main thread; the caller keeps its own
        for signum in self.SIGNALS:
            if signal.getsignal(signum) is signal.SIG_IGN:
                continue  # ignored by whoever started us (e.g. SIGINT for a background job): keep it so
            self._previous[signum] = signal.signal(signum, self._handler)
        self.armed = True

    def restore(self) -> None:
        self.armed = False
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()


def _signal_text(signum: int) -> str:
    return "interrupted by SIGINT (Ctrl-C)" if signum == signal.SIGINT else f"terminated by {signal.Signals(signum).name}"


def run_scenario(
    config: Config,
    config_text: str,
    out: Path | Claim | None,
    engine: str | None = None,
    fmu_dir: Path = DEFAULT_OUT,
    tick: Tick | None = None,
    foxglove: bool = True,
    scene_rate: float = SCENE_RATE,
    trace_writer: str = "auto",
    summarize: bool = False,
    live_view: "LiveView | None" = None,
) -> RunResult:
    """Run ``config`` with ``engine`` and write the trace to ``out`` (``None``: record nothing).

    ``out`` is a path (claimed here: ``orchestrator.trace.output.claim``, which raises ``OutputError``
    for a path in use by another run or holding a file that is not a trace) or a ``Claim`` made by
    the caller. The trace is written aside (``<out>.partial``) and put in place once finalized;
    ``RunResult.trace`` is where the data ended up.

    ``foxglove`` adds the Foxglove channels (scene at ``scene_rate`` Hz of simulated time, errors,
    transforms, log). SIGINT and SIGTERM stop the run at the next communication point with status
    "interrupted"; the trace is finalized with every point recorded up to there. ``trace_writer``:
    where the trace is encoded (``TRACE_WRITERS``); both give the same file. ``summarize``: accumulate
    the per-vehicle summary of the recorded rows while stepping (``RunResult.summary``), so printing it
    needs no second read of the trace. ``live_view``: a started ``LiveView`` (orchestrator/live_view.py)
    that shows what the trace records, the run paced as it says; the caller closes it.
    """
    target = claim(out) if isinstance(out, (str, Path)) else out
    trace_process: TraceProcess | None = None
    try:  # whatever fails before the run starts: no lock kept, no empty aside file left behind
        engine = engine or default_engine(config)
        if engine not in ENGINES:
            raise ValueError(f"unknown engine {engine!r}; expected one of {', '.join(ENGINES)}")
        check_live_options(config, engine, trace_writer)
        scenario = build_scenario(config)
        sim = config.simulation
        steps = step_count(sim.stop_time, sim.step)
        live = live_names(config) if engine == "python" else set()
        writer_kind = "inline" if live else choose_trace_writer(trace_writer, steps // sim.trace_every + 1,
                                                                len(scenario.components))
        # the trace writer process starts first: its start-up overlaps unpacking and instantiating the FMUs;
        # it inherits the trace's lock, so the path stays claimed while it still writes
        opening = clock.perf_counter()
        if target is not None and writer_kind == "process":
            trace_process = TraceProcess(keep_fds=(target.fd,))
        fmu_kind = resolve_fmu_kind(config.simulation.fmus, fmu_dir)
        fmus_by_kind = _open_fmus(fmu_dir, fmu_kind)
    except BaseException:
        if trace_process is not None:
            trace_process.close()
        _release(target)
        raise
    started = clock.perf_counter()
    marks = {"start": started}  # phase boundaries, for RunResult.timings
    opened = started - opening  # FMUs checked and unpacked, trace writer process started (not in wall_time)
    writer: TraceWriter | TraceWorker | NullTraceWriter | None = None
    master = None
    reporter: LiveReporter | None = None
    live_summary: dict[str, dict] = {}
    status, error, signum, failed_at = "completed", None, None, None
    stop = _StopRequest()
    try:
        stop.install()
        kinds = {spec.name: fmus_by_kind[spec.fmu] for spec in scenario.components}
        outputs = {
            spec.name: [v.name for v in kinds[spec.name].description.modelVariables if v.causality == "output"]
            for spec in scenario.components
        }
        components = [(spec.name, outputs[spec.name]) for spec in scenario.components]
        descriptions = {name: _descriptions(fmu) for name, fmu in kinds.items()}
        if target is None:
            writer = NullTraceWriter()
        else:
            writer = open_trace_writer(writer_kind, target.aside, components, descriptions, config,
                                       every=sim.trace_every, scene_rate=scene_rate, foxglove=foxglove,
                                       process=trace_process, publish=target.final, native=engine == "native")
        if live_view is not None:  # the view sees what the trace records; a live robot's run is paced already
            live_view.open(config, components, descriptions, sim.trace_every, scene_rate, on_wall_clock=bool(live),
                           check=stop.check)
            writer = live_view.tee(writer)
        # an optional key left absent (simulation.fmus) stays absent: a null in a stored config stands for a
        # number that was not finite (orchestrator/stored_config.py)
        writer.metadata("platoon.config", {"toml": config_text, "resolved": config.model_dump_json(exclude_none=True)})
        writer.metadata("platoon.fmus", {kind: fmu.guid for kind, fmu in fmus_by_kind.items()})
        writer.metadata("platoon.tool", tool_versions())
        writer.metadata("platoon.start", {"engine": engine, "fmus": fmu_kind, "master": sim.master,
                                          "trace_every": str(sim.trace_every),
                                          "trace_writer": writer_kind,
                                          "trace_encoder": _trace_encoder(writer),
                                          "scene_rate": repr(float(scene_rate)) if foxglove else "",
                                          "started": clock.strftime("%Y-%m-%dT%H:%M:%S%z")})
        writer.log(0.0, "Info", f"run started: {config.name}, {config.platoon.count} vehicles, {config.platoon.law} law, "
                                f"{engine} engine ({sim.master}), {fmu_kind} FMUs, step {sim.step:g} s, stop {sim.stop_time:g} s")
        record = writer.record
        feed = _SummaryFeed(config, components, steps, sim.trace_every) if summarize else None
        if feed is not None:
            record = feed.tee(record)
        marks["setup"] = clock.perf_counter()

        def observe(t: float, values: list[list[float]]) -> None:
            if "initialize" not in marks:  # the first call: the initial point, right after initialization
                marks["initialize"] = clock.perf_counter()
            record(t, values)
            if reporter is not None:
                reporter(t)
            stop.check()

        if engine == "python":
            python_components = [
                live_component(spec, kinds[spec.name], config, index) if spec.name in live
                else FmuComponent(spec.name, kinds[spec.name], spec.parameters)
                for index, spec in enumerate(scenario.components)
            ]
            pacer = Pacer() if live else None
            master = Master(python_components, scenario.connections, scenario.schedules, sim.master, pacer=pacer)
            if pacer is not None:
                reporter = LiveReporter(python_components, writer, pacer)
                writer.log(0.0, "Info", f"live: {', '.join(sorted(live))} on Zenoh; the run is paced to wall-clock time")
            master.run(sim.stop_time, sim.step, observe, steps, tick=tick)
        elif engine == "native":
            # the C loop fills blocks of decimated rows; the writer encodes them (here or in its worker)
            native_components = [NativeComponent(spec.name, kinds[spec.name], spec.parameters) for spec in scenario.components]
            master = NativeMaster(native_components, scenario.connections, scenario.schedules, sim.master)
            master.initialize(0.0)
            marks["initialize"] = clock.perf_counter()
            sink = None if out is None else writer.write_block
            if feed is not None:
                sink = feed.tee_blocks(sink)
            delivery = {"tick": tick, "deliver_interval": FLUSH_INTERVAL / 2}
            if live_view is not None:  # blocks at the view's frame rate, the run paced between them
                delivery = live_view.block_options(sim.step, tick, FLUSH_INTERVAL / 2)
            master.run_blocks(sim.step, steps, sink, every=sim.trace_every,
                              block=WORKER_BLOCK if writer_kind == "process" else BLOCK, check=stop.check,
                              initialize=False, **delivery)
        else:
            _run_monolithic(scenario, outputs, fmus_by_kind, observe, steps, tick)
    except ComponentError as failure:
        if stop.forced:  # a second signal, raised inside an FMU call, made it fail: an interruption
            signum, status = stop.signum, "interrupted"
        else:
            status, error, failed_at = "failed", str(failure), failure.time
    except KeyboardInterrupt as interruption:
        signum = getattr(interruption, "signum", signal.SIGINT)
        status = "interrupted"
    except TraceWorkerError as failure:  # the trace writer process died: the run cannot be recorded further
        status, error = "failed", str(failure).splitlines()[0]
    except TraceWriteError as failure:  # the trace cannot be written (e.g. a full disk): stop, keep what is on disk
        status, error = "failed", str(failure)
    except Exception as unexpected:  # a bug, not a component failure: keep the trace, say so, re-raise
        status, error = "failed", f"{type(unexpected).__name__}: {unexpected}"
        raise
    finally:
        marks["steps"] = clock.perf_counter()
        stop.armed = False  # from here on a signal is only noted: the trace gets finalized first
        try:
            if master is not None:
                try:
                    master.close()
                except Exception as closing:  # still finalize the trace; say what went wrong
                    if status == "completed":
                        status, error = "failed", f"closing the FMUs failed: {closing}"
            if reporter is not None:  # stamped at the last communication point the master reached
                live_summary = reporter.finish(master.time if master is not None else 0.0)
            if writer is not None:
                worker = getattr(writer, "traced", writer)  # behind a live view's tee
                stop.finishing = isinstance(worker, TraceWorker)  # a signal may end the wait for the worker
                try:
                    if stop.finishing and stop.forced and worker.stalled(STALLED_WRITER_GRACE):
                        # The user insisted (a second signal, which may have been spent breaking a send into
                        # the full pipe of a worker that takes nothing: the native FMUs fill it in a moment)
                        # and the worker still takes nothing: finalizing would block on that pipe again.
                        worker.abandon("stopped: it took no data after a second signal")
                        raise KeyboardInterrupt
                    status, error = _finalize_trace(writer, status, error, failed_at, signum, engine, sim.master)
                except KeyboardInterrupt as interruption:  # while the trace writer process finished the file
                    signum = signum or getattr(interruption, "signum", signal.SIGINT)
                    status = "interrupted"
                    error = (f"{_signal_text(signum)} while the trace writer process finished the file; its "
                             f"complete chunks are in {target.aside if target else '?'} (`platoon trace recover`)")
                finally:
                    stop.finishing = False
            if trace_process is not None:
                trace_process.close()  # only if no writer took it (the writer was never created)
            for fmu in fmus_by_kind.values():
                fmu.cleanup()
        finally:
            stop.restore()
            _release(target)
    marks["finish"] = clock.perf_counter()
    summary = feed.result() if feed is not None and status == "completed" else None
    return RunResult(target.where() if target is not None else None, steps, marks["finish"] - started, status, error,
                     signum, {"open": opened, **_phase_durations(marks)}, live_summary, summary, fmu_kind)


class _SummaryFeed:
    """Hands the rows the trace records (same decimation) to a ``RunningSummary``, in blocks."""

    BLOCK = 1024

    def __init__(self, config: Config, components: list[tuple[str, list[str]]], steps: int, every: int) -> None:
        step = config.simulation.step
        # the last recorded point is the last multiple of ``every`` steps; rows are every * step apart
        expected_end = (steps // every) * every * step
        self.summary: RunningSummary = running_summary(config, components, 0.0, expected_end, margin=0.5 * every * step)
        self.every = every
        self._count = 0
        self._rows: list[list[float]] = []

    def tee(self, record: Callable[[float, list[list[float]]], None]) -> Callable[[float, list[list[float]]], None]:
        """``record``, also feeding the summary."""
        def both(t: float, outputs: list[list[float]]) -> None:
            record(t, outputs)
            if self._count % self.every == 0:
                row = [t]
                for values in outputs:
                    row.extend(values)
                self._rows.append(row)
                if len(self._rows) >= self.BLOCK:
                    self._flush()
            self._count += 1
        return both

    def tee_blocks(self, sink: Callable[[object], None] | None) -> Callable[[object], None]:
        """``sink`` (may be None) for the native loop's decimated blocks, also feeding the summary."""
        def both(rows: object) -> None:
            if sink is not None:
                sink(rows)
            self.summary.add(rows)
        return both

    def _flush(self) -> None:
        if self._rows:
            self.summary.add(self._rows)
            self._rows = []

    def result(self) -> list[VehicleSummary] | None:
        self._flush()
        return self.summary.result()


def _release(target: Claim | None) -> None:
    """Drop the trace path's lock; an aside file that never got a byte is removed (no litter)."""
    if target is None:
        return
    try:
        if target.aside.exists() and target.aside.stat().st_size == 0:
            target.aside.unlink()
    except OSError:
        pass
    target.release()


def _phase_durations(marks: dict[str, float]) -> dict[str, float]:
    """Seconds per phase from the marks reached (a run that failed early has fewer)."""
    durations, previous = {}, marks["start"]
    for phase in ("setup", "initialize", "steps", "finish"):
        if phase in marks:
            durations[phase] = marks[phase] - previous
            previous = marks[phase]
    return durations


def _run_monolithic(
    scenario: Scenario,
    outputs: dict[str, list[str]],
    fmus_by_kind: dict[str, UnpackedFmu],
    observe: Callable[[float, list[list[float]]], None],
    steps: int,
    tick: Tick | None,
) -> None:
    sim = scenario.config.simulation
    system = _monolithic_system(scenario, fmus_by_kind)
    names = [spec.name for spec in scenario.components]
    order = [outputs[name] for name in names]
    vehicle_names = names[1:]

    def disturbances(t: float) -> list[tuple[float, float]]:
        values = {name: [0.0, 0.0] for name in vehicle_names}
        for schedule in scenario.schedules:
            slot = 0 if schedule.input.endswith("lateral_acceleration") else 1
            values[schedule.component][slot] += schedule.value_at(t)
        return [tuple(values[name]) for name in vehicle_names]

    def record(t: float, y: list[float]) -> None:
        rows = system.outputs(t, y)
        observe(t, [[row[key] for key in keys] for row, keys in zip(rows, order)])

    y = system.initial_state()
    t = 0.0
    try:
        system.set_disturbances(disturbances(t))
        record(t, y)
        for k in range(steps):
            t, t_next = k * sim.step, (k + 1) * sim.step
            system.set_disturbances(disturbances(t))
            y = system.advance(t, y, t_next - t, sim.max_substep)
            record(t_next, y)
            if tick is not None:
                tick(k + 1)
    except (ValueError, ZeroDivisionError, OverflowError) as failure:
        raise ComponentError("platoon (monolithic)", t, str(failure)) from None


def default_trace_path(config: Config, engine: str | None = None) -> Claim:
    """Claim a fresh ``runs/<name>[-monolithic]-<time>.mcap`` (``-2``, ``-3`` ... when two runs of one
    config start in the same second): never a path another run or an existing file uses."""
    stamp = clock.strftime("%Y%m%d-%H%M%S")
    suffix = "-monolithic" if engine == "monolithic" else ""
    return claim_new(Path("runs"), f"{config.name}{suffix}-{stamp}")


def resolved_json(config: Config) -> str:
    return json.dumps(json.loads(config.model_dump_json()), indent=2)
