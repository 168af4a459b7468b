"""Reading a sweep's output folder (store.py writes it): the records of its finished runs, and one key's
value in a record. The one reader for whatever draws or analyses a finished sweep (``platoon
sweep-plot``: plot.py; ``platoon stability-map``: stability_map.py).

The runs are those of DIR/results.csv, in its order; each run's record is its result file
(DIR/results/<id>.json: values, status, metrics, trace and the resolved config). A key is a run's varied
value, else its resolved config's, or ``d_star/R`` (platoon.d_star / path.radius).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

RATIO = "d_star/R"  # a derived key: platoon.d_star / path.radius


class ResultsError(ValueError):
    """The folder holds no readable results; the message names the folder and what is missing."""


def read_records(folder: Path) -> list[dict[str, Any]]:
    """The result records of the runs results.csv lists, in its order; ``ResultsError`` (one line) when
    there is no results.csv, no run in it, or a run whose result file does not read."""
    table = folder / "results.csv"
    try:
        with open(table, newline="") as file:
            ids = [row["id"] for row in csv.DictReader(file)]
    except OSError:
        raise ResultsError(f"{folder}: no results.csv (not a platoon sweep --out folder, or no run finished yet)") from None
    found = []
    for identifier in ids:
        try:
            found.append(json.loads((folder / "results" / f"{identifier}.json").read_text()))
        except (OSError, ValueError):
            raise ResultsError(f"{folder}: results.csv names run {identifier}, whose results/{identifier}.json is unreadable") from None
    if not found:
        committed = len(list((folder / "results").glob("*.json"))) if (folder / "results").is_dir() else 0
        if committed:  # the rows are what was lost, not the runs: each run's result file is its commit
            raise ResultsError(f"{folder}/results.csv: lists no run, but results/ holds {committed} committed run(s): "
                               "the table was emptied or cut; run the sweep's command again to resume, which rebuilds it")
        raise ResultsError(f"{folder}/results.csv: no finished run yet")
    return found


def lookup(record: dict[str, Any], key: str) -> Any:
    """``key`` for one run: its varied value, else its resolved config's, else None."""
    if key in record["values"]:
        return record["values"][key]
    node: Any = record.get("config")
    if node is None:
        return None
    if key == RATIO:
        return node["platoon"]["d_star"] / node["path"]["radius"]
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node
