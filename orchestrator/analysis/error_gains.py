"""String stability measured: how the errors of a disturbance run grow or shrink from vehicle to vehicle.

A vehicle's errors are its speed and its gap (the true distance to the component ahead, from the
recorded positions: what a link delays is the vehicles' knowledge of each other, not the gap) minus
the undisturbed run's (a reference trace), or minus the steady state (V_c, and the law's equilibrium
gap) when there is none. A disturbance travels one way: with the paper's law from the back to the
front (vehicle i follows vehicle i+1's speed), with acc and cacc from the front to the back. Along
that way, vehicle to vehicle, the gains are

    l2:  ||e_next||_2 / ||e_previous||_2    (||e||_2 = sqrt(integral of e^2 dt) over the window)
    l_inf:  max |e_next| / max |e_previous|

A chain is string stable in the l2 sense when no l2 gain exceeds 1 for any disturbance; a measured gain
is one disturbance's view. For a sinusoid of frequency w held until the response is periodic, the l2
gain over whole periods of the steady state is |G(jw)| (docs/model.md, section 12); ``amplitude_ratios``
measures that directly by fitting the sinusoid.
"""

from __future__ import annotations

import math
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

from orchestrator.analysis.chain_model import ChainModel, chain_model
from orchestrator.analysis.headline import CONFIDENCE, Headline, Mixing, measured_headline, probe_amplitudes
from orchestrator.scenario.config import TARGET_VEHICLE, Config
from orchestrator.scenario.wiring import TARGET

if TYPE_CHECKING:
    from orchestrator.analysis.run_scatter import Scatter
    from orchestrator.trace.reader import Trace

# progress(label, steps) -> a context manager giving a tick(steps done) or None (orchestrator/observers/progress.py)
Progress = Callable[[str, int], AbstractContextManager[Callable[[int], None] | None]]

ERRORS = ("speed", "gap")


def equilibrium_gap(config: Config, vehicle: int) -> float:
    """The steady gap: d* under the paper's law, r + h V_c under acc and cacc (d* with the default r)."""
    p = config.platoon
    if config.speed_law_of(vehicle) == "paper":
        return p.d_star
    return p.resolved_standstill_gap + p.time_gap * p.speed


def _gaps(trace: "Trace", names: list[str]) -> dict[str, np.ndarray]:
    """Each vehicle's distance to the component ahead (the target for vehicle 1), from positions."""
    gaps = {}
    for ahead, name in zip([TARGET] + names, names):
        a, b = trace.component(ahead), trace.component(name)
        gaps[name] = np.hypot(a["x"] - b["x"], a["y"] - b["y"])
    return gaps


def vehicle_errors(trace: "Trace", config: Config, reference: "Trace | None" = None) -> dict[str, dict[str, np.ndarray]]:
    """Per vehicle: ``t`` and its ``speed`` and ``gap`` errors: against ``reference``, else against the
    state recorded last before the first disturbance (a settled run: its steady state as the
    co-simulation has it, which "hold" coupling or a link's sampling shift a little from V_c and the
    law's gap), else, with no disturbance, against V_c and the law's equilibrium gap. The target's
    speed error too (the head of the chain under acc and cacc), with no gap (NaN: nothing is ahead)."""
    names = trace.vehicles()
    gaps = _gaps(trace, names)
    base_gaps = _gaps(reference, names) if reference is not None else None
    first = min((d.start for d in config.disturbance), default=None)
    errors = {TARGET: _target_errors(trace, reference, first, config.platoon.speed)}
    for index, name in enumerate(names, start=1):
        run = trace.component(name)
        if reference is not None:
            base = reference.component(name)
            if len(base["t"]) != len(run["t"]) or not np.allclose(base["t"], run["t"], atol=1e-9):
                raise ValueError(f"the reference trace's {name} is not recorded at the same times")
            speed, gap = base["speed"], base_gaps[name]
        elif first is not None and run["t"][0] <= first + 1e-9:
            before = int(np.searchsorted(run["t"], first + 1e-9)) - 1
            speed, gap = run["speed"][before], gaps[name][before]
        else:
            speed, gap = config.platoon.speed, equilibrium_gap(config, index)
        errors[name] = {"t": run["t"], "speed": run["speed"] - speed, "gap": gaps[name] - gap}
    return errors


def _target_errors(trace: "Trace", reference: "Trace | None", first: float | None, speed: float) -> dict[str, np.ndarray]:
    """The target's speed error, as ``vehicle_errors`` takes a vehicle's; its gap error NaN."""
    run = trace.component(TARGET)
    if reference is not None:
        base = reference.component(TARGET)["speed"]
    elif first is not None and run["t"][0] <= first + 1e-9:
        base = run["speed"][int(np.searchsorted(run["t"], first + 1e-9)) - 1]
    else:
        base = speed
    return {"t": run["t"], "speed": run["speed"] - base, "gap": np.full(len(run["t"]), math.nan)}


def law_of(config: Config, component: int) -> str:
    """The speed law of vehicle ``component``; for 0, the target, its lead's (what decides how it moves)."""
    return config.speed_law_of(max(component, 1))


def component_name(component: int) -> str:
    """Vehicle ``component``'s name, or the target's for 0."""
    return TARGET if component == TARGET_VEHICLE else f"vehicle{component}"


def component_index(name: str, names: list[str]) -> int:
    """The inverse of ``component_name`` over the trace's vehicle ``names``: 0 for the target."""
    return TARGET_VEHICLE if name == TARGET else names.index(name) + 1


def propagation(config: Config, names: list[str], source: int) -> list[str]:
    """The components in the order a disturbance on vehicle ``source`` travels: toward the front under the
    paper's law, toward the back under acc and cacc, from the target itself (``source`` 0) when it is
    pushed. Under the paper's law a push on the target reaches no vehicle."""
    if law_of(config, source) == "paper":
        return names[:source][::-1] if source > 0 else [TARGET]
    return [TARGET] + names if source == TARGET_VEHICLE else names[source - 1:]


def norms(t: np.ndarray, error: np.ndarray, window: tuple[float, float]) -> tuple[float, float]:
    """(l2, l_inf) of ``error`` over ``window`` (trapezoidal integral of e^2 over the recorded points)."""
    inside = (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)
    e, times = error[inside], t[inside]
    if len(e) < 2:
        raise ValueError(f"fewer than two recorded points in the window {window[0]:g} to {window[1]:g} s")
    return math.sqrt(float(np.sum(0.5 * (e[1:] ** 2 + e[:-1] ** 2) * np.diff(times)))), float(np.max(np.abs(e)))


def ratio(b: float, a: float) -> float:
    """b / a; inf where a is 0, NaN where either is (the target's gap, which does not exist)."""
    if math.isnan(a) or math.isnan(b):
        return math.nan
    return b / a if a > 0 else math.inf


@dataclass(frozen=True)
class LinkGains:
    """Gains from ``sender`` to ``receiver``, the next vehicle the disturbance reaches."""

    sender: str
    receiver: str
    l2: dict[str, float]  # per error kind (ERRORS)
    linf: dict[str, float]


def link_gains(errors: dict[str, dict[str, np.ndarray]], order: list[str], window: tuple[float, float]) -> list[LinkGains]:
    """The l2 and l_inf gains of every error kind along ``order`` (vehicle names) over ``window``."""
    measured = {name: {kind: norms(errors[name]["t"], errors[name][kind], window) for kind in ERRORS} for name in order}
    return [LinkGains(a, b, {k: ratio(measured[b][k][0], measured[a][k][0]) for k in ERRORS},
                      {k: ratio(measured[b][k][1], measured[a][k][1]) for k in ERRORS})
            for a, b in zip(order, order[1:])]


def amplitude_ratios(errors: dict[str, dict[str, np.ndarray]], order: list[str], frequency: float,
                     window: tuple[float, float], kind: str = "speed") -> list[float]:
    """|G(jw)| per link as measured: the amplitude of the sinusoid of ``frequency`` (rad/s) fitted by least
    squares (with an offset) to each vehicle's error over ``window``, divided by the sender's."""
    amplitudes = []
    for name in order:
        t, e = errors[name]["t"], errors[name][kind]
        inside = (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)
        basis = np.column_stack([np.cos(frequency * t[inside]), np.sin(frequency * t[inside]), np.ones(int(inside.sum()))])
        (c, s, _), *_ = np.linalg.lstsq(basis, e[inside], rcond=None)
        amplitudes.append(math.hypot(c, s))
    return [ratio(b, a) for a, b in zip(amplitudes, amplitudes[1:])]


def gains_lines(gains: list[LinkGains], clean: list[str] | None = None) -> list[str]:
    """The gains as a table, one line per link; then, without ``clean``, the verdict of the largest l2 gain
    past the disturbed vehicle (with ``clean``, the caller states the verdict from those links)."""
    lines = [f"  {'from -> to':22s} {'speed l2':>9s} {'speed l_inf':>11s} {'gap l2':>9s} {'gap l_inf':>9s}"]
    for g in gains:
        lines.append(f"  {g.sender + ' -> ' + g.receiver:22s} {g.l2['speed']:9.4f} {g.linf['speed']:11.4f} "
                     f"{_cell(g.l2['gap'], 9)} {_cell(g.linf['gap'], 9)}")
    if gains and clean is None:
        worst = max(g.l2["speed"] for g in gains[1:] or gains)
        word = "grows" if worst > 1.0 else "does not grow"
        lines.append(f"  largest speed l2 gain past the disturbed vehicle: {worst:.4f}: this disturbance {word} along "
                     "the platoon (the l2 gain decides, the error's energy, which |G(jw)| bounds; the l_inf column, "
                     "the peaks, may shrink while it grows; string stability asks it of every disturbance: platoon "
                     "analyze has the bound)")
    return lines


def _cell(gain: float, width: int) -> str:
    """A gain in a table column; "-" where there is none (NaN: the target has no gap)."""
    return f"{'-':>{width}s}" if math.isnan(gain) else f"{gain:{width}.4f}"


def first_disturbance_vehicle(config: Config) -> int:
    return min(config.disturbance, key=lambda d: d.start).vehicle


def window_of(config: Config, trace: "Trace", start: float | None, end: float | None) -> tuple[float, float]:
    """The window the gains are taken over: from the first disturbance (or ``start``) to the end (or ``end``)."""
    first = min((d.start for d in config.disturbance), default=0.0)
    last = float(trace.component(trace.vehicles()[0])["t"][-1])
    return (first if start is None else start, last if end is None else end)


def string_stability_report(config: Config, config_text: str, progress: Progress | None = None) -> str:
    """`platoon analyze`'s measured part: the scenario with and without its disturbances; per vehicle the
    peak path, gap and speed deviations, the path's peak ratios (the lateral chain, front to back), and
    the l2 and l_inf gains of the speed and gap errors along the way the speed chain carries them.

    ``progress(label, steps)``: a context manager giving each of the two runs its tick (the caller's
    bar or progress lines), None for none.
    """
    from orchestrator.analysis.metrics import path_errors
    from orchestrator.execution.run import run_scenario
    from orchestrator.scenario.scenario import step_count
    from orchestrator.support.scratch import ScratchDir
    from orchestrator.trace import load

    if not config.disturbance:
        return "string stability: the config has no [[disturbance]]; add one to measure the gains from vehicle to vehicle"
    start = min(d.start for d in config.disturbance)
    steps = step_count(config.simulation.stop_time, config.simulation.step)
    shown = progress or (lambda label, total: nullcontext())
    with ScratchDir("analyze") as scratch, shown("disturbed run (1/2)", steps) as tick:  # scratch: removed by the next run if this one is killed
        result = run_scenario(config, config_text, scratch / "analysis.mcap", tick=tick)
        if result.status != "completed":
            return f"string stability: the run {result.status}: {result.error}"
        from orchestrator.analysis.validity import departures_lines, split_at

        if departures := split_at(result.departures, start)[1]:  # one that left it while settling came back
            return "\n".join([f"string stability: no gains, the disturbed run left the model after t = {start:g} s",
                              *departures_lines(departures)])
        trace = load(result.trace)
    reference_config = config.model_copy(update={"disturbance": []})
    with ScratchDir("analyze") as scratch, shown("undisturbed run (2/2)", steps) as tick:
        reference = load(run_scenario(reference_config, config_text, scratch / "reference.mcap", tick=tick).trace)
    errors = vehicle_errors(trace, config, reference)
    window = window_of(config, trace, None, None)
    lines = [f"string stability (peak deviation from the undisturbed run after t = {start:g} s):",
             f"  {'vehicle':10s} {'path [m]':>12s} {'gap [m]':>12s} {'speed [m/s]':>12s}"]
    paths = []
    for name in trace.vehicles():
        a, b = trace.component(name), reference.component(name)
        inside = a["t"] >= start
        paths.append(float(np.abs(path_errors(config, a["x"], a["y"]) - path_errors(config, b["x"], b["y"]))[inside].max()))
        peaks = [norms(errors[name]["t"], errors[name][kind], window)[1] for kind in ("gap", "speed")]
        lines.append(f"  {name:10s} {paths[-1]:12.4e} {peaks[0]:12.4e} {peaks[1]:12.4e}")
    first = first_disturbance_vehicle(config)
    behind = max(first, 1)  # a push on the target: the path ratios from vehicle 1
    ratios = ", ".join(f"{ratio(b, a):.3f}" for a, b in zip(paths[behind - 1:], paths[behind:]))
    lines.append(f"  path peak ratios behind vehicle {behind}, vehicle i+1 / i: {ratios or 'none (last vehicle)'}")
    order = propagation(config, trace.vehicles(), first)
    lines.append(f"  gains of the errors from vehicle to vehicle, the way the {law_of(config, first)} law carries "
                 f"them (l2, and l_inf = peak ratio):")
    lines += gains_lines(link_gains(errors, order, window))
    return "\n".join(lines)


SETTLE = 60.0  # s after a sinusoid starts before its gains are read (the chain's transients: poles >= 0.2 1/s)


def probe_frequencies(config: Config) -> list[float]:
    """The distinct frequencies of the config's sinusoidal disturbances (rad/s), lowest first."""
    return sorted({d.frequency for d in config.disturbance if d.frequency > 0.0})


def steady_window(config: Config, end: float) -> tuple[float, float]:
    """Where the sinusoids' response is periodic: whole periods of the lowest frequency, ending where the
    sinusoids (or the record, ``end``) end, starting at least min(SETTLE, half their span) after they start."""
    sines = [d for d in config.disturbance if d.frequency > 0.0]
    if not sines:
        raise ValueError("its config has no sinusoidal disturbance (a frequency > 0)")
    start = max(d.start for d in sines)
    stop = min(min(d.start + d.duration for d in sines), end)
    period = 2.0 * math.pi / min(d.frequency for d in sines)
    whole = math.floor((stop - start - min(SETTLE, 0.5 * (stop - start))) / period + 1e-3)
    if whole < 1:
        raise ValueError(f"the sinusoids leave no whole period of {period:.4g} s after their transient")
    return stop - whole * period, stop


def disturbed(config: Config) -> set[int]:
    return {d.vehicle for d in config.disturbance}


def source_vehicle(config: Config) -> int:
    """The pushed vehicle the law carries a disturbance from: the last pushed under the paper's law (it
    carries toward the front), the first under acc and cacc (0: the target)."""
    pushed = sorted(disturbed(config))
    return pushed[-1] if law_of(config, pushed[-1]) == "paper" else pushed[0]


def clean_order(config: Config, names: list[str]) -> list[str]:
    """The vehicles along the way a disturbance travels that measure the chain itself: not pushed, and not
    the first two receivers of the pushed one. A push is held over each step, a staircase whose jumps the
    sender's rates do not carry: the first receiver's extrapolation turns it into ripple at multiples of
    2 pi/step, which beacons at a multiple of the step fold back exactly onto the push's frequencies (the
    study's cacc with 0.3 s links at 0.1 rad/s: the target -> vehicle 1 gain is 1.4 % above the chain's,
    vehicle 1 -> 2 0.14 %, 2 -> 3 0.01 %)."""
    order = propagation(config, names, source_vehicle(config))
    pushed = {component_name(v) for v in disturbed(config)}
    clean = [name for name in order if name not in pushed]
    return clean[2:]


def frequency_gains(errors: dict[str, dict[str, np.ndarray]], order: list[str], frequencies: list[float],
                    window: tuple[float, float]) -> list[list[float]]:
    """Per frequency, per link along ``order``: the speed error's amplitude ratio at that frequency (all
    frequencies and an offset fitted jointly by least squares over ``window``)."""
    amplitudes = probe_amplitudes(errors, order, frequencies, window)
    return [[ratio(b[k], a[k]) for a, b in zip(amplitudes, amplitudes[1:])] for k in range(len(frequencies))]


def predicted_gains(config: Config, names: list[str], clean: list[str], frequencies: list[float],
                    chain: ChainModel | None = None) -> list[list[float]] | None:
    """Per frequency, per link along ``clean``: the gain the sampled-data cascade predicts for this run
    (its pushes, its links, its records); None where the cascade does not apply. ``chain``: the config's
    ``chain_model`` where the caller has it."""
    from orchestrator.analysis.sampled_chain import cascade_speeds

    chain = chain or chain_model(config)
    if chain.missing is not None:
        return None
    source = source_vehicle(config)
    order = [component_index(name, names) for name in propagation(config, names, source)]
    order = order if law_of(config, source) != "paper" else list(range(config.platoon.count, order[-1] - 1, -1))
    result = []
    for w in frequencies:
        speeds = dict(zip(order, cascade_speeds(chain, order, w, config.simulation.trace_every)))
        amplitudes = [abs(speeds[component_index(name, names)]) for name in clean]
        result.append([ratio(b, a) for a, b in zip(amplitudes, amplitudes[1:])])
    return result


def stretch_growth(gains: "list[list[float]] | np.ndarray") -> float:
    """The headline number of gains per probe frequency, per link along the clean links: at each probe the
    geometric mean of the links' gains, i.e. the last vehicle's amplitude over the first's, per link (the
    growth per link of the whole stretch, what the cascade's growth per link far down the string predicts);
    the largest over the probes. One link's gain carries the noise that link adds; over the stretch the
    links' noises average (the largest single gain of a lossy run is the noisiest, biased up)."""
    return max(math.prod(row) ** (1.0 / len(row)) for row in gains)


def run_headline(config: Config, errors: dict[str, dict[str, np.ndarray]], clean: list[str],
                 steady: tuple[float, float], chain: ChainModel | None = None) -> Headline:
    """The run's headline over the stretch ``clean`` (orchestrator/analysis/headline.py): its growth per link at
    the probes, the scatter of a single run's value, the weak probes (the paper law's V d*/d mixes probes).
    ``chain``: the config's ``chain_model`` where the caller has it."""
    frequencies = probe_frequencies(config)
    mixing = None
    if law_of(config, source_vehicle(config)) == "paper":
        mixing = Mixing(config.platoon.speed, {name: equilibrium_gap(config, int(name[len("vehicle"):]))
                                               for name in clean if name != TARGET})
    scatter = predicted_run_scatter(config, clean, steady, chain)
    predicted = None if isinstance(scatter, str) else scatter
    return measured_headline(errors, clean, frequencies, steady, 2.0 * math.pi / min(frequencies), mixing,
                             predicted and predicted.sigma, predicted and predicted.buried())


def probe_growths(config: Config, trace) -> tuple[list[str], tuple[float, float], np.ndarray]:
    """A whole run's growth per link over its clean stretch at each probe (weak probes included), with the stretch
    and the fitting window: what a run's predicted scatter (``predicted_run_scatter``) is the scatter of."""
    clean = clean_order(config, trace.vehicles())
    window = steady_window(config, config.simulation.stop_time)
    amplitudes = probe_amplitudes(vehicle_errors(trace, config), clean, probe_frequencies(config), window)
    return clean, window, (amplitudes[-1] / amplitudes[0]) ** (1.0 / (len(clean) - 1))


def predicted_run_scatter(config: Config, clean: list[str], window: tuple[float, float],
                          chain: ChainModel | None = None) -> "Scatter | str":
    """The analysis' mean and standard deviation of a single run's growth per link over ``clean``, per probe, over
    its delivery patterns (orchestrator/analysis/run_scatter.py), or why it is not predicted; ``chain``: the
    config's ``chain_model`` where the caller has it."""
    from orchestrator.analysis.run_scatter import Stretch, predicted_scatter

    names = [component_name(i) for i in range(1, config.platoon.count + 1)]
    stretch = Stretch([component_index(name, names) for name in clean], probe_frequencies(config), window,
                      config.simulation.trace_every)
    return predicted_scatter(chain or chain_model(config), stretch)


def scatter_lines(config: Config, chain: ChainModel | None = None) -> list[str]:
    """`platoon analyze`'s lines on a single run's headline: per probe, the cascade's growth over the links that
    measure propagation and the predicted standard deviation of one run's value (none without sinusoids);
    ``chain``: the config's ``chain_model`` where the caller has it."""
    frequencies = probe_frequencies(config)
    if not frequencies:  # no sinusoid: no probe, and no run's headline to predict
        return []
    names = [component_name(i) for i in range(1, config.platoon.count + 1)]
    clean = clean_order(config, names)
    if len(clean) < 2:
        return []
    try:
        window = steady_window(config, config.simulation.stop_time)
    except ValueError:
        return []
    scatter = predicted_run_scatter(config, clean, window, chain)
    head = f"a single run's growth per link over {' -> '.join(clean)} (fitted over {window[0]:g} to {window[1]:g} s)"
    if isinstance(scatter, str):
        return [f"{head}: its scatter {scatter}"]
    buried = scatter.buried()
    values = "; ".join(f"{w:g} rad/s " + (buried[w] if w in buried else f"{g:.4f} +- {s:.2g}")
                       for w, g, s in zip(scatter.frequencies, scatter.growth, scatter.sigma))
    return [f"{head}, its mean over the losses +- its predicted standard deviation: {values} (a single run's verdict "
            f"stands where |growth - 1| is more than {CONFIDENCE:g} of them)"]


def _frequency_lines(config: Config, errors: dict[str, dict[str, np.ndarray]], names: list[str], clean: list[str],
                     window: tuple[float, float], chain: ChainModel) -> tuple[list[str], Headline | None]:
    """Per probe frequency, the measured gains along the clean links beside the cascade's prediction;
    and the run's headline (``run_headline``; None without sinusoids or clean links)."""
    frequencies = probe_frequencies(config)
    if not frequencies or len(clean) < 2:
        return [], None
    try:
        steady = steady_window(config, window[1])
    except ValueError as error:
        return [f"  (no gains per frequency: {error})"], None
    measured = frequency_gains(errors, clean, frequencies, steady)
    predicted = predicted_gains(config, names, clean, frequencies, chain)
    lines = [f"  per frequency, {' -> '.join(clean)} (fitted over {steady[0]:g} to {steady[1]:g} s):"]
    for k, w in enumerate(frequencies):
        expected = "" if predicted is None else "predicted " + ", ".join(f"{g:.4f}" for g in predicted[k]) + "; "
        lines.append(f"    {w:g} rad/s: {expected}measured " + ", ".join(f"{g:.4f}" for g in measured[k]))
    return lines, run_headline(config, errors, clean, steady, chain)


def stability_report(trace: "Trace", config: Config, reference: "Trace | None", window: tuple[float, float]) -> str:
    """`platoon stability TRACE`: the measured gains, and the closed form of the trace's config beside them.

    The headline verdict uses only the links that measure propagation (``clean_order``): a link that
    starts or ends at a pushed vehicle measures the push, and the first receivers of one carry what the
    pushed vehicle's own law made of its push. With sinusoids, it is the largest growth per link at any
    probe frequency over those links (``stretch_growth``; one l2 gain over all of them would be the
    largest probe's alone)."""
    if not config.disturbance:
        raise ValueError("its config has no [[disturbance]]: the gains need a disturbance run")
    from orchestrator.analysis.validity import departures_lines, departures_of_trace, split_at
    from orchestrator.analysis.verdict import closed_form_verdict

    names = trace.vehicles()
    source = source_vehicle(config)
    order = propagation(config, names, source)
    law = law_of(config, source)
    chain = chain_model(config)  # the one chain the verdict, the predicted gains and the scatter read
    verdict = closed_form_verdict(config, chain=chain)
    start = min(d.start for d in config.disturbance)
    settling, departures = split_at(departures_of_trace(trace, config), min(start, window[0]))
    if departures:  # no gains: the run is no linear chain's, whatever its numbers
        return "\n".join([f"string stability measured: {law} law: no gains, the run left the model after t = "
                          f"{min(start, window[0]):g} s", *departures_lines(departures), verdict.line()])
    errors = vehicle_errors(trace, config, reference)
    against = "the reference trace" if reference is not None else f"the state recorded last before t = {start:g} s"
    pushed = ", ".join(str(v) if v else "the target" for v in sorted(disturbed(config)))
    lines = [f"string stability measured: {law} law, carried from {'the target' if source == TARGET_VEHICLE else f'vehicle {source}'} "
             f"(pushed: {pushed}), errors against "
             f"{against}, window {window[0]:g} to {window[1]:g} s; a link that starts or ends at a pushed vehicle "
             "measures the push too"]
    if settling:
        lines += [f"  (it left the model while it settled, before t = {min(start, window[0]):g} s, and came back: the "
                  f"gains are of the settled run) {d.text()}" for d in settling[:3]]
    gains = link_gains(errors, order, window)
    lines += gains_lines(gains)[:-1] if gains else gains_lines(gains)
    clean = clean_order(config, names)
    per_frequency, headline = _frequency_lines(config, errors, names, clean, window, chain)
    stretch = " -> ".join(clean)
    if headline is not None:
        lines.append(f"  largest growth per link at the probe frequencies over the links that measure propagation "
                     f"({stretch}): {headline.text()}")
    elif len(clean) > 1:
        worst = max(g.l2["speed"] for g in link_gains(errors, clean, window))
        word = "grows" if worst > 1.0 else "does not grow"
        lines.append(f"  largest speed l2 gain over the links that measure propagation ({stretch}): {worst:.4f}: "
                     f"this disturbance {word} along the platoon (no scatter: no sinusoid)")
    else:
        lines.append("  no link measures propagation here (too few vehicles past the pushed ones)")
    lines.append(verdict.line())
    return "\n".join(lines + per_frequency)
