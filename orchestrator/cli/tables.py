"""The per-vehicle summary as a rich table: what `platoon run` prints after its run, and `platoon report`.

Apart from the typer commands' shared options (cli/common.py), so that `platoon run`, which starts
without typer (cli/launch.py), prints its table without importing typer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING


if TYPE_CHECKING:
    from rich.table import Table

    from orchestrator.scenario.config import Config


def summary_table(summaries, config: Config, title: str) -> Table:
    """The per-vehicle summary (the consoles print text literally: the units "[m]" are not markup); the same
    quantities, keys and units as `platoon report --json` (metrics.SUMMARY_COLUMNS, summary_rows)."""
    from rich.table import Table

    from orchestrator.analysis.summary_fields import STEADY_FRACTION, SUMMARY_COLUMNS, path_error_interval, summary_rows

    _, interval = path_error_interval(config)  # max |path error| is taken from the first disturbance on (metrics.py)
    table = Table(title=title, title_justify="left", caption_justify="left",
                  caption=f"path offset, gap, speed: means over the last {STEADY_FRACTION:.0%} of the recorded time")
    table.add_column("vehicle", justify="left")
    for column in SUMMARY_COLUMNS:
        header = f"{column.label} [{column.unit}]" + (f", {interval}" if column.key == "path_error_max" else "")
        table.add_column(header, justify="right",
                         min_width=len(column.label) if column.key == "path_error_max" else None,  # unbroken
                         max_width=len("path offset") if column.key == "path_offset" else None)  # fits 80 columns
    for row in summary_rows(summaries, config):  # deviations signed; the largest |error| is a magnitude
        table.add_row(str(row["name"]), *(f"{row[c.key]:.3e}" if c.key == "path_error_max" else f"{row[c.key]:+.3e}"
                                           for c in SUMMARY_COLUMNS))
    return table


def link_table(stats) -> Table:
    """What each link did (orchestrator/analysis/link_stats.py): `platoon run` and `platoon report` print it
    under the summary of a run with imperfect links; the same numbers as `platoon report --json`'s "links"."""
    from rich.table import Table

    table = Table(title="links (docs/links.md)", title_justify="left", caption_justify="left",
                  caption="mean age: of the message in use at the receiver (its time minus the message's "
                          "sending time), over the recorded rows")
    table.add_column("link", justify="left")
    for header in ("sent", "delivered", "lost", "lost %", "mean age [s]"):
        table.add_column(header, justify="right")
    for link in stats:
        share = "-" if link.sent == 0 else f"{100.0 * link.lost_share:.1f}"
        table.add_row(link.name, str(link.sent), str(link.delivered), str(link.lost), share, f"{link.mean_age:.4f}")
    return table
