"""The links' tally while the run steps (orchestrator/analysis/link_stats.py), so that `platoon run` prints
what its links did without reading the trace again (reading back a 100 s lossy run took 4 s here).

Fed the rows the trace records (the same decimation), as the running summary is; the work per block is
one column sum per link, done in the stepping thread.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from orchestrator.analysis.link_stats import AGE, COUNTERS, LinkStats, LinkTally
from orchestrator.observers.base import Observer
from orchestrator.support.rows import RowBlock
from orchestrator.trace.format import is_link


@dataclass(frozen=True)
class _Link:
    tally: LinkTally
    component: int  # its place among the components (``point``'s outputs)
    own: tuple[int, ...]  # sent, delivered, lost, age: their places among its outputs
    columns: tuple[int, ...]  # the same as columns of a flat row (``block``)


class LinkStatsObserver(Observer):
    """Tallies every link component of ``components`` ((name, outputs) in the rows' order)."""

    wants_rows = True

    def __init__(self, components: Sequence[tuple[str, Sequence[str]]], every: int) -> None:
        self.every = every
        self._count = 0
        self.links: list[_Link] = []
        column = 1  # a flat row is [t, outputs...]
        for index, (name, outputs) in enumerate(components):
            if is_link(name):
                own = tuple(list(outputs).index(output) for output in (*COUNTERS, AGE))  # within its outputs
                self.links.append(_Link(LinkTally(name), index, own, tuple(column + k for k in own)))
            column += len(outputs)

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        if self._count % self.every == 0:
            for link in self.links:
                values = outputs[link.component]
                *counters, age = (float(values[k]) for k in link.own)
                link.tally.add(tuple(counters), (age,))  # type: ignore[arg-type]
        self._count += 1

    def block(self, rows: Any) -> None:
        block = RowBlock.coerce(rows)
        if not len(block):
            return
        last, values, width = block.row(-1), block.values, block.width
        for link in self.links:
            *counters, age = link.columns
            link.tally.add(tuple(last[c] for c in counters), values[age::width])  # type: ignore[arg-type]

    def result(self) -> list[LinkStats]:
        return [link.tally.result() for link in self.links]
