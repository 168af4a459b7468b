"""One run of a scenario, from the claimed trace path to the finalized file: an ``Execution``.

As in libcosim, the execution owns what is the same for every engine: the start (FMUs checked and
opened, the trace writer chosen and opened, the metadata written), the observers the engine feeds,
the stop conditions (the planned number of steps, a component failure, Ctrl-C or SIGTERM between two
steps), the timing of the phases, and the end: the engine closed, the trace finalized with how the
run ended (``platoon.run`` metadata: completed, failed with the component, time and reason, or
interrupted), whatever happened. The engine (orchestrator/execution/engine.py) only steps.
"""

from __future__ import annotations

import signal
import time as clock
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from fmus.builders import DEFAULT_OUT
from fmus.errors import ComponentError
from orchestrator.components.fmu import UnpackedFmu
from orchestrator.components.kinds import ensure_fmus, resolve_fmu_kind, run_fmu_names
from orchestrator.components.live import check_live_options, live_names
from orchestrator.components.remote import check_remote_options
from orchestrator.execution.engine import EngineSetup, default_engine, engine_class
from orchestrator.execution.signals import StopRequest
from orchestrator.observers.base import Observers, WaitClock
from orchestrator.observers.progress import ProgressDisplay
from orchestrator.observers.trace import TraceObserver, choose_trace_writer, open_trace_writer, signal_text
from orchestrator.scenario.scenario import build_scenario, step_count
from orchestrator.scenario.raw_config import recorded_rows
from orchestrator.support.versions import tool_versions
from orchestrator.trace.foxglove import SCENE_RATE
from orchestrator.trace.format import BLOCK
from orchestrator.trace.output import Claim, claim
from orchestrator.trace.worker import WORKER_BLOCK, TraceProcess, TraceWorkerError, discard_prestarted, take_prestarted
from orchestrator.trace.writer_base import NullTraceWriter, TraceWriteError
from orchestrator.scenario.config_text import header_text

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from orchestrator.analysis.link_stats import LinkStats
    from orchestrator.analysis.metrics import VehicleSummary
    from orchestrator.analysis.validity import Departure
    from orchestrator.observers.foxglove_view import FoxgloveView
    from orchestrator.observers.hil_link import LinkReporter
    from orchestrator.observers.link_stats import LinkStatsObserver
    from orchestrator.observers.summary import SummaryObserver
    from orchestrator.observers.validity import ValidityObserver

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
    summary: "list[VehicleSummary] | None" = None
    fmus: str = ""  # the FMU kind stepped: "native" or "python" (orchestrator/components/kinds.py)

    @property
    def working_time(self) -> float:
        """Wall seconds of the run without its waits for a viewer or a robot: what "N steps in X s" says."""
        return self.wall_time - self.waited
    # run_scenario(..., summarize=True): what each link did (sent, delivered, lost, mean age of information)
    links: "list[LinkStats]" = field(default_factory=list)
    # of wall_time, the seconds the start waited for a viewer (--live-wait) or a live robot: not the run's work
    waited: float = 0.0
    # where the recorded run left the model (orchestrator/analysis/validity.py): each vehicle's first collision,
    # pass, impossible speed; empty inside it (and for a run that records nothing)
    departures: "list[Departure]" = field(default_factory=list)


@dataclass
class _Outcome:
    """How the run is ending, as the stepping and then the finalization decide."""

    status: str = "completed"
    error: str | None = None
    signum: int | None = None
    failed_at: float | None = None

    def fail(self, error: str, at: float | None = None) -> None:
        self.status, self.error, self.failed_at = "failed", error, at


def _descriptions(fmu: UnpackedFmu) -> dict[str, str]:
    return {
        v.name: f"{v.description} [{v.unit}]" if v.unit else v.description
        for v in fmu.description.modelVariables
        if v.causality == "output"
    }


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


def _trace_process(lock: int) -> TraceProcess:
    """The run's trace writer process, holding the trace's ``lock``: the one started with the command
    (orchestrator/cli/trace_forecast.py), or a new one if there is none or it is gone."""
    early = take_prestarted()
    if early is not None:
        try:
            early.share(lock)
            return early
        except OSError:  # it died before the run needed it: start another, as without it
            early.close()
    process = TraceProcess()
    try:
        process.share(lock)
    except BaseException:
        process.close()
        raise
    return process


class Execution:
    """One run of ``config`` (see the module's docstring); ``run()`` once.

    ``out``: the trace path (claimed here: ``orchestrator.trace.output.claim`` raises ``OutputError``
    for a path in use by another run or holding a file that is not a trace), a ``Claim`` made by the
    caller, or None (record nothing). Whatever fails while the execution is made (an unknown engine, a
    live vehicle the engine cannot step, FMUs that cannot be built) leaves no lock and no aside file.
    """

    def __init__(self, config: Config, config_text: str, out: Path | Claim | None, engine: str | None = None,
                 fmu_dir: Path = DEFAULT_OUT, tick: Tick | None = None, foxglove: bool = True,
                 scene_rate: float = SCENE_RATE, trace_writer: str = "auto", summarize: bool = False,
                 live_view: "FoxgloveView | None" = None) -> None:
        self.config, self.config_text, self.tick = config, config_text, tick
        self.foxglove, self.scene_rate, self.summarize, self.live_view = foxglove, scene_rate, summarize, live_view
        self.target = claim(out) if isinstance(out, (str, Path)) else out
        self.trace_process: TraceProcess | None = None
        try:  # whatever fails before the run starts: no lock kept, no empty aside file left behind
            self._prepare(engine, fmu_dir, trace_writer)
        except BaseException:
            if self.trace_process is not None:
                self.trace_process.close()
            _release(self.target)
            raise

    def _prepare(self, engine: str | None, fmu_dir: Path, trace_writer: str) -> None:
        config, sim = self.config, self.config.simulation
        self.engine_name = engine or default_engine(config)
        self.engine_class = engine_class(self.engine_name)
        check_live_options(config, self.engine_name, trace_writer)
        check_remote_options(config, self.engine_name)
        self.scenario = build_scenario(config)
        self.steps = step_count(sim.stop_time, sim.step)
        self.live = live_names(config) if self.engine_name == "python" else set()
        self.writer_kind = "inline" if self.live else choose_trace_writer(
            trace_writer, recorded_rows(self.steps, sim.trace_every), len(self.scenario.components))
        # the trace writer process starts first (or started with the command: prestart): its start-up
        # overlaps loading the config and the FMUs; it holds the trace's lock, so the path stays claimed
        # while it still writes
        self.opening = clock.perf_counter()
        if self.target is not None and self.writer_kind == "process":
            self.trace_process = _trace_process(self.target.fd)
        else:
            discard_prestarted()  # started with the command on a forecast this run did not confirm (e.g. live robots)
        self.fmu_kind = resolve_fmu_kind(sim.fmus, fmu_dir)
        announce = self.tick.building if isinstance(self.tick, ProgressDisplay) else None  # a first run builds them
        self.fmus = {name: UnpackedFmu.open_cached(path)
                     for name, path in ensure_fmus(fmu_dir, self.fmu_kind, run_fmu_names(self.scenario), announce).items()}

    def run(self) -> RunResult:
        """Start, step to the end or the first stop, finalize; the result says how it ended."""
        started = clock.perf_counter()
        marks = {"start": started}  # phase boundaries, for RunResult.timings
        opened = started - self.opening  # FMUs checked and unpacked, trace writer process started (not in wall_time)
        outcome, stop, observers = _Outcome(), StopRequest(), Observers()
        self.trace: TraceObserver | None = None
        self.engine: Any = None
        self.reporter: "LinkReporter | None" = None
        self.summary_feed: "SummaryObserver | None" = None
        self.link_feed: "LinkStatsObserver | None" = None
        self.validity: "ValidityObserver | None" = None
        self.wait_clock = WaitClock()  # a robot's wait; the viewer's the view measures itself
        try:
            stop.install()
            setup = self._observe(observers, stop)
            marks["setup"] = clock.perf_counter()
            self.engine = self.engine_class(setup)
            self._report_links(observers)
            self.engine.start(observers, stop.check)
            observers.stepping()
            marks["initialize"] = clock.perf_counter()
            self.engine.advance(self.steps, observers, stop.check)
        except ComponentError as failure:
            if stop.forced:  # a second signal, raised inside an FMU call, made it fail: an interruption
                outcome.signum, outcome.status = stop.signum, "interrupted"
            else:
                outcome.fail(str(failure), failure.time)
        except KeyboardInterrupt as interruption:
            outcome.signum, outcome.status = getattr(interruption, "signum", signal.SIGINT), "interrupted"
        except TraceWorkerError as failure:  # the trace writer process died: the run cannot be recorded further
            outcome.fail(str(failure).splitlines()[0])
        except TraceWriteError as failure:  # the trace cannot be written (e.g. a full disk): stop, keep what is on disk
            outcome.fail(str(failure))
        except Exception as unexpected:  # a bug, not a component failure: keep the trace, say so, re-raise
            outcome.fail(f"{type(unexpected).__name__}: {unexpected}")
            raise
        finally:
            marks["steps"] = clock.perf_counter()
            stop.armed = False  # from here on a signal is only noted: the trace gets finalized first
            try:
                live_summary = self._finish(outcome, stop, observers)
            finally:
                stop.restore()
                _release(self.target)
        marks["finish"] = clock.perf_counter()
        feed = self.summary_feed
        summary = feed.result() if feed is not None and outcome.status == "completed" else None
        return RunResult(self.target.where() if self.target is not None else None, self.steps, marks["finish"] - started,
                         outcome.status, outcome.error, outcome.signum, {"open": opened, **_phase_durations(marks)},
                         live_summary, summary, self.fmu_kind,
                         self.link_feed.result() if self.link_feed is not None else [],
                         self.wait_clock.waited + (self.live_view.waited if self.live_view is not None else 0.0),
                         self.validity.result() if self.validity is not None else [])

    def _observe(self, observers: Observers, stop: StopRequest) -> EngineSetup:
        """Open the trace and the other observers, write the run's metadata; what the engine is built from."""
        config, sim, scenario = self.config, self.config.simulation, self.scenario
        outputs = {spec.name: [v.name for v in self.fmus[spec.fmu].description.modelVariables if v.causality == "output"]
                   for spec in scenario.components}
        components = [(spec.name, outputs[spec.name]) for spec in scenario.components]
        descriptions = {spec.name: _descriptions(self.fmus[spec.fmu]) for spec in scenario.components}
        if self.target is None:
            writer: Any = NullTraceWriter()
        else:
            writer = open_trace_writer(self.writer_kind, self.target.aside, components, descriptions, config,
                                       every=sim.trace_every, scene_rate=self.scene_rate, foxglove=self.foxglove,
                                       process=self.trace_process, publish=self.target.final,
                                       native=self.engine_name == "native", paced=bool(self.live))
        self.trace = trace = TraceObserver(writer)
        observers.add(trace)  # first: every other observer sees a point once the trace holds it
        observers.add(self.wait_clock)
        if self.live_view is not None:  # the view sees what the trace records; a live robot's run is paced already
            from orchestrator.observers.hil_link import live_streams

            self.live_view.open(config, components, descriptions, sim.trace_every, self.scene_rate,
                                on_wall_clock=bool(self.live), check=stop.check, streams=live_streams(sorted(self.live)))
            observers.add(self.live_view)
        self._write_start(observers, trace)
        if config.disturbance:  # a log line when each starts and ends
            from orchestrator.observers.disturbance_log import DisturbanceLog

            observers.add(DisturbanceLog(config, observers.log))
        if self.target is not None or self.summarize:  # a line in the log where the run leaves the model
            from orchestrator.observers.validity import ValidityObserver

            self.validity = ValidityObserver(config, components, observers.log, paced=bool(self.live))
            observers.add(self.validity)
        if self.summarize:
            from orchestrator.observers.summary import SummaryObserver

            self.summary_feed = SummaryObserver(config, components, self.steps, sim.trace_every,
                                                on_thread=trace.in_a_process)
            observers.add(self.summary_feed)
            if config.linked():  # what the links did, beside the summary (docs/links.md)
                from orchestrator.observers.link_stats import LinkStatsObserver

                self.link_feed = LinkStatsObserver(components, sim.trace_every)
                observers.add(self.link_feed)
        if config.ros2.publish:  # every vehicle's pose to ROS 2 (docs/hil.md, "Publishing the run to ROS 2")
            from orchestrator.observers.ros2 import ros2_publisher

            observers.add(ros2_publisher(config, components))
        if self.tick is not None:
            from orchestrator.observers.progress import ProgressObserver

            observers.add(ProgressObserver(self.tick))
        return EngineSetup(config, scenario, self.fmus, outputs,
                           WORKER_BLOCK if self.writer_kind == "process" else BLOCK, self.live)

    def _write_start(self, observers: Observers, trace: TraceObserver) -> None:
        config, sim = self.config, self.config.simulation
        # an optional key left absent (simulation.fmus) stays absent: a null in a stored config stands for a
        # number that was not finite (orchestrator/scenario/stored_config.py)
        trace.metadata("platoon.config", {"toml": self.config_text, "resolved": config.model_dump_json(exclude_none=True)})
        trace.metadata("platoon.fmus", {kind: fmu.guid for kind, fmu in self.fmus.items()})
        trace.metadata("platoon.tool", tool_versions())
        trace.metadata("platoon.start", {"engine": self.engine_name, "fmus": self.fmu_kind, "master": sim.master,
                                         "trace_every": str(sim.trace_every),
                                         "trace_writer": self.writer_kind,
                                         "trace_encoder": trace.encoder,
                                         "scene_rate": repr(float(self.scene_rate)) if self.foxglove else "",
                                         "started": clock.strftime("%Y-%m-%dT%H:%M:%S%z")})
        observers.log(0.0, "Info", f"run started: {config.name}, {config.platoon.count} vehicles, {header_text(config)}, "
                                   f"{self.engine_name} engine ({sim.master}), {self.fmu_kind} FMUs, step {sim.step:g} s, "
                                   f"stop {sim.stop_time:g} s")

    def _report_links(self, observers: Observers) -> None:
        """With live robots: their links' events and statistics go to the other observers after each point."""
        pacer = getattr(self.engine, "pacer", None)
        if pacer is None or self.trace is None:
            return
        from orchestrator.observers.hil_link import LinkReporter

        self.reporter = LinkReporter(self.engine.components, observers, pacer, self.trace.metadata)
        for component in self.reporter.live:  # their start's waits (robot, key, endpoint, s left) go to the observers
            component.on_wait = observers.waiting
        observers.add(self.reporter)
        observers.log(0.0, "Info", f"live: {', '.join(sorted(self.live))} on Zenoh; the run is paced to wall-clock time")

    def _finish(self, outcome: _Outcome, stop: StopRequest, observers: Observers) -> dict[str, dict]:
        """Close the engine, let the observers finish, finalize the trace, free the FMUs; the links' summary."""
        engine, live_summary = self.engine, {}
        if engine is not None:
            try:
                engine.close()
            except ComponentError as closing:  # a live robot that obeyed someone else while it stopped
                if outcome.status == "completed":
                    outcome.fail(str(closing), closing.time)
            except Exception as closing:  # still finalize the trace; say what went wrong
                if outcome.status == "completed":
                    outcome.fail(f"closing the FMUs failed: {closing}")
        if self.reporter is not None:  # stamped at the last communication point the engine reached
            live_summary = self.reporter.close_links(engine.time if engine is not None else 0.0)
        try:
            observers.finish()
        except Exception as finishing:  # an observer that cannot let go (a closing session): the trace comes first
            if outcome.status == "completed":
                outcome.fail(f"an observer failed to finish: {type(finishing).__name__}: {finishing}")
        if self.trace is not None:
            if outcome.status == "completed":
                self._store_summary()
            self._finalize_trace(outcome, stop, observers)
        if self.trace_process is not None:
            self.trace_process.close()  # only if no writer took it (the writer was never created)
        for fmu in self.fmus.values():
            fmu.cleanup()
        return live_summary

    def _store_summary(self) -> None:
        """The summary the run computed from its recorded rows, into the trace (``platoon.summary``), for
        `platoon report` to print without reading the rows back (orchestrator/analysis/stored_summary.py)."""
        vehicles = self.summary_feed.result() if self.summary_feed is not None else None
        if vehicles is None or self.trace is None:  # a quiet run computes none; an end not the planned one
            return
        from orchestrator.analysis.stored_summary import RECORD, StoredSummary, summary_record

        self.trace.metadata(RECORD, summary_record(StoredSummary(
            vehicles, self.link_feed.result() if self.link_feed is not None else [],
            self.validity.result() if self.validity is not None else [])))

    def _finalize_trace(self, outcome: _Outcome, stop: StopRequest, observers: Observers) -> None:
        trace = self.trace
        assert trace is not None
        stop.finishing = trace.in_a_process  # a signal may end the wait for the worker
        try:
            if stop.finishing and stop.forced and trace.stalled():
                # The user insisted (a second signal, which may have been spent breaking a send into
                # the full pipe of a worker that takes nothing: the native FMUs fill it in a moment)
                # and the worker still takes nothing: finalizing would block on that pipe again.
                trace.abandon()
                raise KeyboardInterrupt
            outcome.status, outcome.error = trace.finalize(outcome.status, outcome.error, outcome.failed_at,
                                                           outcome.signum, self.engine_name, self.config.simulation.master,
                                                           observers.log)  # the last line: the live view shows it too
        except KeyboardInterrupt as interruption:  # while the trace writer process finished the file
            outcome.signum = outcome.signum or getattr(interruption, "signum", signal.SIGINT)
            outcome.status = "interrupted"
            outcome.error = (f"{signal_text(outcome.signum)} while the trace writer process finished the file; its "
                             f"complete chunks are in {self.target.aside if self.target else '?'} (`platoon trace recover`)")
        finally:
            stop.finishing = False
