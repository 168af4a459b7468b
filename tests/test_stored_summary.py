"""`platoon report` of a trace that stores its run's summary (orchestrator/analysis/stored_summary.py) prints
what reading the rows back prints, to the character, and falls back to the rows wherever the stored summary
cannot be trusted: another code's, a damaged file, a recovered one.

A `platoon run -q` stores no summary (it computes none), so the same run twice, once quiet, gives the two
paths over the same rows (the runs are deterministic: tests/test_runs.py).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from orchestrator.analysis.link_stats import LinkStats
from orchestrator.analysis.stored_summary import RECORD, StoredSummary, stored_summary, summary_record
from orchestrator.analysis.summary_fields import VehicleSummary
from orchestrator.analysis.validity import Departure

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper"
CLI = [sys.executable, "-c", "from orchestrator.cli import main; main()"]
SHORT = ("--set", "simulation.stop_time=20.0")
# vehicle 2 pushed 15 m/s faster for 3 s: its speed passes a stated 30 m/s (a departure the report names)
PUSHED = ("--set", 'disturbance=[{vehicle=2,kind="speed",start=2.0,duration=3.0,value=15.0}]',
          "--set", "validity.max_speed=30.0")
CASES = {
    "paper": ("platoon.toml", SHORT),
    "lossy links": ("platoon_lossy.toml", SHORT),  # the links' table
    "left the model": ("platoon.toml", (*SHORT, *PUSHED)),  # the departures' lines
}


def env() -> dict[str, str]:
    out = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    out.pop("FORCE_COLOR", None)
    return out


def platoon(*args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *map(str, args)], cwd=cwd, env=env(), capture_output=True, text=True, timeout=180)


def metadata(trace: Path) -> dict[str, dict[str, str]]:
    """The trace's metadata records, read by the mcap package's own reader."""
    with open(trace, "rb") as stream:
        return {item.name: dict(item.metadata) for item in make_reader(stream).iter_metadata()}


@pytest.fixture
def work(tmp_path: Path, fmu_dir: Path) -> Path:
    (tmp_path / "build").symlink_to(REPO / "build", target_is_directory=True)
    return tmp_path


def two_traces(work: Path, config: str, settings: tuple[str, ...]) -> tuple[Path, Path]:
    """The same run written twice under one file name: with its summary stored, and quiet (none stored)."""
    traces = []
    for folder, quiet in (("stored", ()), ("rows", ("-q",))):
        (work / folder).mkdir()
        trace = work / folder / "run.mcap"
        done = platoon("run", PAPER / config, *settings, *quiet, "--out", trace, cwd=work)
        assert done.returncode == 0, done.stderr
        traces.append(trace)
    assert RECORD in metadata(traces[0]) and RECORD not in metadata(traces[1])
    return traces[0], traces[1]


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_stored_summary_reports_what_the_rows_report(case: str, work: Path) -> None:
    stored, rows = two_traces(work, *CASES[case])
    for options in ((), ("--json",)):
        told = [platoon("report", trace, *options, cwd=work) for trace in (stored, rows)]
        assert [t.returncode for t in told] == [0, 0], [t.stderr for t in told]
        if options:  # the same JSON, but for the trace's own path
            first, second = (json.loads(t.stdout) for t in told)
            assert first.pop("trace") == str(stored) and second.pop("trace") == str(rows)
            assert first == second
        else:
            assert told[0].stdout == told[1].stdout and told[0].stderr == told[1].stderr
    text = platoon("report", stored, cwd=work).stdout
    if case == "lossy links":
        assert "links (docs/links.md)" in text
    if case == "left the model":
        assert "vehicle2 reached" in text and "beyond 30 m/s" in text


def test_the_data_section_crc_is_one_the_mcap_package_checks(work: Path) -> None:
    """The writer records the data section's CRC (DataEnd): the mcap package's stream reader checks it, and
    refuses the file with one byte of a chunk changed."""
    trace = work / "run.mcap"
    assert platoon("run", PAPER / "platoon.toml", *SHORT, "--out", trace, "-q", cwd=work).returncode == 0
    with open(trace, "rb") as stream:
        records = list(StreamReader(stream, validate_crcs=True).records)
    assert any(type(record).__name__ == "DataEnd" and record.data_section_crc != 0 for record in records)
    damaged = bytearray(trace.read_bytes())
    damaged[len(damaged) // 3] ^= 0x01
    (work / "damaged.mcap").write_bytes(bytes(damaged))
    with open(work / "damaged.mcap", "rb") as stream, pytest.raises(Exception, match="(?i)crc"):
        list(StreamReader(stream, validate_crcs=True).records)


def inside_a_body_chunk(trace: Path) -> int:
    """An offset inside the middle one of the chunks that hold vehicle 1's rows (what the report reads)."""
    with open(trace, "rb") as stream:
        summary = make_reader(stream).get_summary()
    bodies = [c for c in summary.chunk_indexes
              if any(summary.channels[cid].topic == "/platoon/vehicle1" for cid in c.message_index_offsets)]
    middle = bodies[len(bodies) // 2]
    return middle.chunk_start_offset + middle.chunk_length // 2


def test_a_damaged_chunk_is_found_as_when_the_rows_are_read(work: Path) -> None:
    stored, _ = two_traces(work, *CASES["paper"])
    data = bytearray(stored.read_bytes())
    data[inside_a_body_chunk(stored)] ^= 0x10
    damaged = work / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    refused = platoon("report", damaged, cwd=work)
    assert refused.returncode == 2 and f"platoon trace recover {damaged}" in refused.stderr, refused.stdout


def test_a_changed_stored_summary_is_not_printed(work: Path) -> None:
    """A digit of the stored summary changed in place (the file's length and structure intact): the data
    section's CRC no longer checks, and the report is that of the rows."""
    stored, rows = two_traces(work, *CASES["paper"])
    data = stored.read_bytes()
    vehicles = metadata(stored)[RECORD]["vehicles"].encode()
    at = data.index(vehicles) + vehicles.index(b"path_offset") + len(b'path_offset": ') + 3  # a digit
    assert data[at:at + 1].isdigit()
    changed = bytearray(data)
    changed[at] = ord("1") if data[at] != ord("1") else ord("2")
    forged = work / "forged" / "run.mcap"
    forged.parent.mkdir()
    forged.write_bytes(bytes(changed))
    assert metadata(forged)[RECORD]["vehicles"] != metadata(stored)[RECORD]["vehicles"]
    assert platoon("report", forged, cwd=work).stdout == platoon("report", rows, cwd=work).stdout


def test_a_recovered_trace_is_reported_from_its_rows(work: Path) -> None:
    """`platoon trace recover` keeps the metadata records, the stored summary among them, but not the rows of a
    damaged chunk: the report reads the rows that are left (and says what is missing), as for a quiet run's."""
    stored, rows = two_traces(work, *CASES["paper"])
    reports = []
    for trace in (stored, rows):  # the summary record comes last: the chunks lie at the same offsets in both
        data = bytearray(trace.read_bytes())
        data[inside_a_body_chunk(stored)] ^= 0x10
        trace.write_bytes(bytes(data))
        recovered = trace.with_name("recovered.mcap")
        done = platoon("trace", "recover", trace, "--out", recovered, cwd=work)
        assert done.returncode == 0, done.stderr
        reports.append(platoon("report", recovered, cwd=work))
    assert RECORD in metadata(stored.with_name("recovered.mcap"))
    assert reports[0].returncode == 0 and "data is missing between" in reports[0].stdout, reports[0].stderr
    assert reports[0].stdout == reports[1].stdout


def sample() -> StoredSummary:
    return StoredSummary([VehicleSummary("vehicle1", 1e-9, 75.0, 25.0, float("nan"))],
                         [LinkStats("link_backward2", 10, 9, 1, 0.0125)],
                         [Departure("speed", "vehicle2", 2.5, 31.0, 30.0, "vehicle1")])


def test_a_record_round_trips_exactly() -> None:
    back = stored_summary(summary_record(sample()))
    assert back is not None
    assert back.links == sample().links and back.departures == sample().departures
    (vehicle,) = back.vehicles
    assert (vehicle.name, vehicle.path_offset, vehicle.gap, vehicle.speed) == ("vehicle1", 1e-9, 75.0, 25.0)
    assert vehicle.path_error_max != vehicle.path_error_max  # nan stays nan


@pytest.mark.parametrize("change", [
    {"code": "0" * 16},  # computed by other code: an older version, an edited checkout
    {"format": "0"},
    {"vehicles": "[]"},
    {"vehicles": '[{"name": "vehicle1"}]'},
    {"vehicles": '[{"name": 1, "path_offset": 0.0, "gap": 0.0, "speed": 0.0, "path_error_max": 0.0}]'},
    {"links": '[{"name": "l", "sent": "10", "delivered": 9, "lost": 1, "mean_age": 0.0}]'},
    {"departures": "not json"},
])
def test_a_record_of_other_code_or_not_ours_is_not_used(change: dict[str, str]) -> None:
    assert stored_summary({**summary_record(sample()), **change}) is None
    assert stored_summary(None) is None and stored_summary({}) is None
