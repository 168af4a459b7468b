"""What each communication link of a run did (docs/links.md): messages sent, delivered and lost, and the
mean age of information its receiver worked with, over the recorded rows.

A lossy run's summary says this beside the vehicles' table: a user comparing a lossy run with a perfect
one reads from it how much the links lost and how old what the vehicles used was. The counters are the
Link FMU's own outputs at the last recorded row; the mean age is the mean of its ``age`` output over the
recorded rows (evenly spaced in time: a time average). ``LinkTally`` folds them, from the rows while the
run steps (orchestrator/observers/link_stats.py) or from a trace read back (``link_stats_of_trace``).
No numpy here: the running tally sits in the stepping process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable

from orchestrator.trace.format import is_link

if TYPE_CHECKING:
    from orchestrator.trace import Trace

COUNTERS = ("sent", "delivered", "lost")  # the Link FMU's counts so far (sent - delivered - lost in flight)
AGE = "age"  # s: the link's time minus the output_time of the message in use


@dataclass(frozen=True)
class LinkStats:
    name: str  # the link's component: link_backward2, link_forward3 ...
    sent: int
    delivered: int
    lost: int
    mean_age: float  # s, nan when nothing was recorded

    @property
    def lost_share(self) -> float:
        """Lost messages as a share of those sent (nan when none was sent)."""
        return self.lost / self.sent if self.sent else math.nan


class LinkTally:
    """One link's counters at the latest row folded, and the sum and number of the ages seen."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.counters = (0.0, 0.0, 0.0)
        self.age_sum = 0.0
        self.rows = 0

    def add(self, counters: tuple[float, float, float], ages: Iterable[float]) -> None:
        """``counters``: sent, delivered, lost at the last of the rows; ``ages``: each row's age."""
        self.counters = counters
        for age in ages:
            self.age_sum += age
            self.rows += 1

    def result(self) -> LinkStats:
        sent, delivered, lost = (int(value) for value in self.counters)
        return LinkStats(self.name, sent, delivered, lost, self.age_sum / self.rows if self.rows else math.nan)


def link_stats_of_trace(trace: "Trace") -> list[LinkStats]:
    """Every link of a trace read back (`platoon report`), in the trace's order."""
    stats = []
    for name in trace.channels:
        if is_link(name):
            channel = trace.component(name)
            tally = LinkTally(name)
            if len(channel["t"]):
                tally.add(tuple(float(channel[key][-1]) for key in COUNTERS), channel[AGE].tolist())  # type: ignore[arg-type]
            stats.append(tally.result())
    return stats


def link_rows(stats: list[LinkStats]) -> list[dict[str, float | int | str]]:
    """The links as `platoon report --json` gives them (mean age in s, lost share as a fraction; null for
    what cannot be told: nothing sent, nothing recorded), valid JSON whatever the run."""
    def number(value: float) -> float | None:
        return value if math.isfinite(value) else None

    return [{"name": s.name, "sent": s.sent, "delivered": s.delivered, "lost": s.lost,
             "lost_share": number(s.lost_share), "mean_age": number(s.mean_age)} for s in stats]
