"""A config's platoon in a few words, for run headers, the trace's first log line and figure titles: the laws,
then the imperfect links if any."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .config import Config


def header_text(config: Config) -> str:
    """The laws, then the imperfect links if any: what a run's header says of the platoon."""
    links = links_text(config)
    return f"{laws_text(config)}, {links}" if links else laws_text(config)

def links_text(config: Config) -> str:
    """The run's imperfect links in a few words, "" when every link is perfect (run headers and the
    trace's first log line, beside the laws): "8 imperfect links (delay 0.1-0.12 s, 10% lost, beacons
    every 0.1 s on 4)", so that a lossy run's header does not read as a perfect-link run's."""
    links = [config.resolve_link(direction, vehicle) for direction, vehicle in config.linked()]
    if not links:
        return ""

    def span(values: list[float], unit: str = " s", form: str = "g") -> str:
        low, high = min(values), max(values)
        return f"{low:{form}}{unit}" if low == high else f"{low:{form}}-{high:{form}}{unit}"

    parts = []
    if any(link.delay + link.jitter > 0.0 for link in links):
        parts.append("delay " + span([link.delay for link in links] + [link.delay + link.jitter for link in links]))
    if any(link.loss > 0.0 for link in links):
        parts.append(span([link.loss for link in links], "", ".0%") + " lost")
    beacons = [link.period for link in links if link.period > 0.0]
    if beacons:
        parts.append("beacons every " + span(beacons) + ("" if len(beacons) == len(links) else f" on {len(beacons)}"))
    return f"{len(links)} imperfect link{'s' if len(links) > 1 else ''} ({', '.join(parts)})"

def laws_text(config: Config) -> str:
    """The guidance law and, when not the paper's alone, the speed laws: "sine law", "sine law, acc
    speed law", "sine law, speed laws paper (1), acc (2-4)" (run headers and the trace's first log line)."""
    laws = [config.speed_law_of(i) for i in range(1, config.platoon.count + 1)]
    text = f"{config.platoon.law} law"
    if set(laws) == {"paper"}:
        return text
    if len(set(laws)) == 1:
        return f"{text}, {laws[0]} speed law"
    runs: list[tuple[str, int, int]] = []  # (law, first vehicle, last vehicle)
    for vehicle, law in enumerate(laws, start=1):
        if runs and runs[-1][0] == law:
            runs[-1] = (law, runs[-1][1], vehicle)
        else:
            runs.append((law, vehicle, vehicle))
    parts = [f"{law} ({first})" if first == last else f"{law} ({first}-{last})" for law, first, last in runs]
    return f"{text}, speed laws {', '.join(parts)}"
