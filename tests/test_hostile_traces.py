"""Traces are never lost or corrupted, whatever the user or the machine does.

Every case runs the `platoon` command of this checkout in a real subprocess (``python -c "from
orchestrator.cli import main; main()"`` with this checkout first on PYTHONPATH, so the worktree's code
is what runs) and reads the files back with the ``mcap`` reader. Signals are real signals; a full disk
is a real 1 MB tmpfs mounted in a private mount namespace (``unshare -rm``), skipped, saying why, where
that is not allowed.
"""

from __future__ import annotations

import json
import os
import queue
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from orchestrator.trace import load
from tests.conftest import SPEED_TO_ZERO

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper" / "platoon.toml"
CLI = [sys.executable, "-c", "from orchestrator.cli import main; main()"]
SHORT = ("--set", "simulation.stop_time=2.0")
LONG = ("--set", "simulation.stop_time=10000.0")


def env() -> dict[str, str]:
    out = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    out.pop("FORCE_COLOR", None)
    return out


@pytest.fixture
def work(tmp_path: Path, fmu_dir: Path) -> Path:
    """A working folder whose build/fmus are the repository's (the CLI's default FMU folder)."""
    (tmp_path / "build").symlink_to(REPO / "build", target_is_directory=True)
    shutil.copy(PAPER, tmp_path / "victim.toml")
    return tmp_path


def platoon(*args: object, cwd: Path, timeout: float = 180, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*prefix, *CLI, *map(str, args)], cwd=cwd, env=env(), capture_output=True, text=True,
                          timeout=timeout)


def start(*args: object, cwd: Path) -> subprocess.Popen[str]:
    """A `platoon` command in its own process group, SIGINT at its default (as a terminal job has it)."""
    return subprocess.Popen([*CLI, *map(str, args)], cwd=cwd, env=env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def wait_for_size(trace: Path, size: int, process: subprocess.Popen[str], timeout: float = 120) -> None:
    """Until the run's trace file (its aside file, or the trace itself for code that writes in place)
    holds more than ``size`` bytes."""
    deadline = time.monotonic() + timeout
    while not any(p.is_file() and p.stat().st_size > size for p in (aside(trace), trace)):
        if process.poll() is not None:
            raise AssertionError(f"the run ended early ({process.returncode}): {process.stderr.read()}")
        if time.monotonic() > deadline:
            os.killpg(process.pid, signal.SIGKILL)
            raise AssertionError(f"{trace} (or its aside file) did not grow past {size} bytes")
        time.sleep(0.05)


def one_line_error(result: subprocess.CompletedProcess[str] | tuple[int, str, str], *pieces: str) -> str:
    stderr = result[2] if isinstance(result, tuple) else result.stderr
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    for piece in pieces:
        assert piece in lines[0], (piece, lines[0])
    return lines[0]


def aside(trace: Path) -> Path:
    return trace.with_name(trace.name + ".partial")


def status_of(path: Path) -> str:
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        return {m.name: m.metadata for m in reader.iter_metadata()}["platoon.run"]["status"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> Path:
    """A completed 20 s paper run (several chunks), written by `platoon run`."""
    folder = tmp_path_factory.mktemp("reference")
    (folder / "build").symlink_to(REPO / "build", target_is_directory=True)
    out = folder / "reference.mcap"
    result = platoon("run", PAPER, "--set", "simulation.stop_time=20.0", "--out", out, "-q", cwd=folder)
    assert result.returncode == 0, result.stderr
    return out


def chunk_spans(path: Path, topic: str | None = None) -> list[tuple[int, int, int, int]]:
    """(offset, length, first log time, last log time) of each chunk (holding ``topic``), from the summary."""
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    return [(c.chunk_start_offset, c.chunk_length, c.message_start_time, c.message_end_time)
            for c in summary.chunk_indexes
            if topic is None or any(summary.channels[cid].topic == topic for cid in c.message_index_offsets)]


# --- 1. two runs never write one trace --------------------------------------------------------------

def test_a_second_run_on_a_trace_being_written_is_refused_and_the_first_finishes_intact(work: Path) -> None:
    trace = work / "shared.mcap"
    # every 1000th point recorded: the run keeps writing while the two refusals start (seconds on a loaded
    # machine), and every step it records is read back below (~0.15 ms each: 2 s of every-step writing
    # were ~20 s of reading); at that rate its 10^8 steps (--allow-long: above the 10^6 a run may have
    # unasked) outlast any test
    first = start("run", "victim.toml", "--set", "simulation.stop_time=1000000.0", "--allow-long", "--trace-every",
                  "1000", "--out", trace, "-q", "--trace-writer", "inline", cwd=work)
    try:
        wait_for_size(trace, 100_000, first)
        second = platoon("run", "victim.toml", *SHORT, "--out", trace, "-q", cwd=work)
        assert second.returncode == 2
        one_line_error(second, "another process is writing", str(trace))
        busy = platoon("trace", "recover", aside(trace), cwd=work)  # nor is it recovered while written
        assert busy.returncode == 2
        one_line_error(busy, "a running run is writing it")
    finally:
        os.killpg(first.pid, signal.SIGINT)
        code = first.wait(timeout=120)
    assert code == 130, first.stderr.read()
    loaded = load(trace)  # CRCs checked: nobody else wrote into it
    assert loaded.run["status"] == "interrupted" and len(loaded.component("vehicle1")["t"]) > 10
    assert not aside(trace).exists()


def test_default_paths_of_runs_started_in_the_same_second_differ(work: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from orchestrator.scenario.config import load_config
    from orchestrator.execution.run import default_trace_path

    monkeypatch.chdir(work)
    monkeypatch.setattr(time, "strftime", lambda *args: "20260101-120000")  # one second for both
    config, _ = load_config(PAPER)
    first, second = default_trace_path(config), default_trace_path(config)
    try:
        assert first.final != second.final and first.final.parent == second.final.parent == Path("runs")
    finally:
        first.release()
        second.release()


def test_two_runs_of_one_config_with_the_default_path_both_keep_their_trace(work: Path) -> None:
    runs = [start("run", "victim.toml", *SHORT, "-q", cwd=work) for _ in range(2)]
    outputs = [process.communicate(timeout=180) for process in runs]
    assert [process.returncode for process in runs] == [0, 0], outputs
    traces = sorted((work / "runs").glob("*.mcap"))
    assert len(traces) == 2 and not list((work / "runs").glob("*.partial"))
    for path in traces:
        assert load(path).run["status"] == "completed"


# --- 2. a run writes aside, never replaces what it must not ------------------------------------------

def test_run_never_replaces_its_own_config_even_through_a_link(work: Path) -> None:
    config = work / "victim.toml"
    before = config.read_bytes()
    os.link(config, work / "hard.mcap")
    (work / "soft.mcap").symlink_to(config)
    for target in (config, work / "hard.mcap", work / "soft.mcap"):
        for extra in ((), ("--overwrite",)):
            result = platoon("run", "victim.toml", *SHORT, "--out", target, "-q", *extra, cwd=work)
            assert result.returncode == 2, (target, extra, result.stdout)
            one_line_error(result, "the same file as victim.toml")
            assert config.read_bytes() == before


def test_run_replaces_a_file_that_is_not_a_trace_only_when_told(work: Path) -> None:
    notes = work / "notes.txt"
    notes.write_text("my notes\n")
    result = platoon("run", "victim.toml", *SHORT, "--out", notes, "-q", cwd=work)
    assert result.returncode == 2
    one_line_error(result, "not an MCAP trace", "--overwrite")
    assert notes.read_text() == "my notes\n" and not aside(notes).exists()
    result = platoon("run", "victim.toml", *SHORT, "--out", notes, "-q", "--overwrite", cwd=work)
    assert result.returncode == 0, result.stderr
    assert load(notes).run["status"] == "completed"
    # a failed run's trace is finalized and put in place too (a trace is replaced without being told)
    (work / "failing.toml").write_text(PAPER.read_text() + SPEED_TO_ZERO)
    failed = platoon("run", "failing.toml", *SHORT, "--out", notes, "-q", cwd=work)
    assert failed.returncode == 1
    one_line_error(failed, "run failed", f"trace up to that point: {notes}")
    assert load(notes).run["status"] == "failed" and not aside(notes).exists()


def test_a_killed_run_leaves_the_old_trace_intact_and_its_own_data_recoverable(work: Path) -> None:
    trace = work / "kept.mcap"
    assert platoon("run", "victim.toml", *SHORT, "--out", trace, "-q", cwd=work).returncode == 0
    old = trace.read_bytes()
    run = start("run", "victim.toml", *LONG, "--out", trace, "-q", "--trace-writer", "inline", cwd=work)
    wait_for_size(trace, 300_000, run)
    assert trace.read_bytes() == old  # nothing happens to the old trace while the new one is written
    os.killpg(run.pid, signal.SIGKILL)
    run.wait(timeout=60)
    assert trace.read_bytes() == old
    assert aside(trace).stat().st_size > 300_000
    # the next run on that path does not discard the killed run's data without being told
    refused = platoon("run", "victim.toml", *SHORT, "--out", trace, "-q", cwd=work)
    assert refused.returncode == 2
    one_line_error(refused, f"platoon trace recover {aside(trace)}", "--overwrite")
    recovered = platoon("trace", "recover", aside(trace), cwd=work)
    assert recovered.returncode == 0, recovered.stderr
    fixed = work / "kept-recovered.mcap"
    assert f": {fixed.name}" in recovered.stdout or str(fixed) in recovered.stdout
    suggested = recovered.stdout.strip().splitlines()[-1]  # no layout is written beside it: the command that does
    assert suggested.startswith(f"layout: platoon layout {fixed}  (a Foxglove layout fitted to the run"), suggested
    made = platoon(*suggested.split("  (")[0].split()[2:], cwd=work)  # "layout: platoon" is the CLI itself
    assert made.returncode == 0 and (work / "kept-recovered.layout.json").is_file(), made.stderr
    assert status_of(fixed) == "recovered" and load(fixed).component("vehicle4")["t"][-1] > 0.5
    again = platoon("run", "victim.toml", *SHORT, "--out", trace, "-q", "--overwrite", cwd=work)
    assert again.returncode == 0, again.stderr
    assert load(trace).run["status"] == "completed" and not aside(trace).exists()


# --- 3. one flipped bit loses one chunk, not the rest ------------------------------------------------

def test_recover_keeps_every_intact_chunk_after_a_flipped_bit_and_names_the_lost_time(reference: Path, tmp_path: Path) -> None:
    spans = chunk_spans(reference, "/platoon/vehicle1")  # the bodies' chunks (docs/trace-format.md, "Chunk groups")
    assert len(spans) >= 4
    middle = len(spans) // 2
    offset, length, lost_start, lost_end = spans[middle]
    data = bytearray(reference.read_bytes())
    data[offset + length // 2] ^= 0x10  # one bit inside the middle chunk's compressed records
    damaged = tmp_path / "flipped.mcap"
    damaged.write_bytes(bytes(data))

    for command in (("report", damaged), ("export", damaged, "--csv", tmp_path / "csv")):
        refused = platoon(*command, cwd=tmp_path)
        assert refused.returncode == 2
        one_line_error(refused, f"platoon trace recover {damaged}")

    result = platoon("trace", "recover", damaged, "--out", tmp_path / "fixed.mcap", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    # the stretch named: from the last intact message before the chunk's rows to the first after them,
    # in whichever chunk group (the scene's, at 10 Hz, 0.1 s either side at most) reached least far
    named = re.search(r"data lost between t = ([0-9.e+-]+) \.\. ([0-9.e+-]+) s", result.stdout)
    assert named, result.stdout
    before, after = float(named[1]), float(named[2])
    assert spans[middle - 1][3] * 1e-9 - 0.1 - 1e-9 <= before <= spans[middle - 1][3] * 1e-9
    assert spans[middle + 1][2] * 1e-9 <= after <= spans[middle + 1][2] * 1e-9 + 0.1 + 1e-9
    original, fixed = load(reference), load(tmp_path / "fixed.mcap")
    t = original.component("vehicle2")["t"]
    stamps = np.round(t * 1e9).astype(np.int64)
    survivors = (stamps < lost_start) | (stamps > lost_end)
    for name in ("target", "vehicle1", "vehicle4"):
        for key in ("t", "x", "gap" if name != "target" else "arc_length"):
            assert np.array_equal(fixed.component(name)[key], original.component(name)[key][survivors]), (name, key)
    assert fixed.component("vehicle1")["t"][-1] == t[-1]  # everything after the damage is back
    report = platoon("report", tmp_path / "fixed.mcap", cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    assert f"data is missing between t = {before:.6g} .. {after:.6g} s" in report.stdout


def test_stability_on_a_recovered_trace_with_a_hole_warns_as_report_does(tmp_path: Path, fmu_dir: Path) -> None:
    """The issue's case: a disturbance run loses one chunk of the bodies inside the gains' window; `platoon
    stability` on the recovered file names the lost time (before: other gains, without a word)."""
    (tmp_path / "build").symlink_to(REPO / "build", target_is_directory=True)
    run = tmp_path / "pushed.mcap"
    pushed = platoon("run", PAPER, "--set", "simulation.stop_time=20.0", "--set",
                     'disturbance=[{vehicle=0,kind="speed",start=2.0,duration=16.0,value=0.5,frequency=0.5}]',
                     "--out", run, "-q", cwd=tmp_path)
    assert pushed.returncode == 0, pushed.stderr
    spans = chunk_spans(run, "/platoon/vehicle1")
    offset, length, _, _ = spans[len(spans) // 2]
    data = bytearray(run.read_bytes())
    data[offset + length // 2] ^= 0x10
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    assert platoon("trace", "recover", damaged, "--out", tmp_path / "fixed.mcap", cwd=tmp_path).returncode == 0
    shown = platoon("stability", tmp_path / "fixed.mcap", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert "warning: recovered from a damaged trace; data is missing between t = " in shown.stdout, shown.stdout
    intact = platoon("stability", run, cwd=tmp_path)
    assert intact.returncode == 0 and "warning" not in intact.stdout, intact.stdout


def test_recover_skips_garbage_between_chunks_and_loses_no_message(reference: Path, tmp_path: Path) -> None:
    spans = chunk_spans(reference)
    cut = spans[2][0]
    data = reference.read_bytes()
    garbage = bytes(np.random.default_rng(18).integers(0, 256, 5000, dtype=np.uint8))
    damaged = tmp_path / "garbage.mcap"
    damaged.write_bytes(data[:cut] + garbage + data[cut:])
    result = platoon("trace", "recover", damaged, "--out", tmp_path / "fixed.mcap", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "1 damaged stretch skipped" in result.stdout
    original, fixed = load(reference), load(tmp_path / "fixed.mcap")
    for name in original.channels:
        for key, values in original.component(name).items():
            assert np.array_equal(fixed.component(name)[key], values), (name, key)


# --- 4. trace recover: never its input, never an existing --out, never garbage, streamed --------------

def test_recover_never_overwrites_an_existing_out_or_its_own_input(reference: Path, tmp_path: Path) -> None:
    source = tmp_path / "source.mcap"
    shutil.copy(reference, source)
    original = source.read_bytes()
    existing = tmp_path / "existing.mcap"
    existing.write_bytes(b"someone's file")
    result = platoon("trace", "recover", source, "--out", existing, cwd=tmp_path)
    assert result.returncode == 2
    one_line_error(result, "exists", "--overwrite")
    assert existing.read_bytes() == b"someone's file"
    os.link(source, tmp_path / "hard.mcap")
    (tmp_path / "soft.mcap").symlink_to(source)
    for alias in ("hard.mcap", "soft.mcap"):
        for extra in ((), ("--overwrite",)):
            result = platoon("trace", "recover", source, "--out", tmp_path / alias, *extra, cwd=tmp_path)
            assert result.returncode == 2, (alias, extra)
            one_line_error(result, "the same file as", "source.mcap, which this command reads")
            assert source.read_bytes() == original
    replaced = platoon("trace", "recover", source, "--out", existing, "--overwrite", cwd=tmp_path)
    assert replaced.returncode == 0, replaced.stderr
    assert status_of(existing) == "completed"
    assert not list(tmp_path.glob("*.recovering"))


@pytest.mark.parametrize("content", [b"", b"not a trace at all\n" * 100, b"\x89MCAP0\r\n"])
def test_recover_refuses_empty_or_garbage_input_and_writes_nothing(tmp_path: Path, content: bytes) -> None:
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(content)
    result = platoon("trace", "recover", broken, cwd=tmp_path)
    assert result.returncode == 2
    one_line_error(result, "nothing to recover")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.mcap"]


MEMORY_PROBE = """
import resource, sys
from orchestrator.trace import recover
import mcap.reader, mcap.writer, zstandard
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
recover(sys.argv[1], sys.argv[2])
print(before, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


@pytest.mark.slow  # a 10000-row, 400-column trace, and a minute on a loaded machine; recover's other tests are fast
def test_recover_streams_a_large_trace(tmp_path: Path) -> None:
    """Peak memory of `recover` grows by far less than the input (it held every message before: a peak
    of ~3x the input above the imports on this file, 7.5x on a real trace; docs/trace-format.md)."""
    from orchestrator.trace import TraceWriter

    big = tmp_path / "big.mcap"
    names = [f"vehicle{k}" for k in range(1, 41)]
    writer = TraceWriter(big, [(name, [f"y{j}" for j in range(10)]) for name in names])
    rows = np.random.default_rng(4).standard_normal((2000, 1 + 10 * len(names)))
    for block in range(5):
        rows[:, 0] = np.arange(block * 2000, (block + 1) * 2000) * 0.01
        writer.write_block(rows)
    writer.close()
    size = big.stat().st_size
    assert size > 40_000_000
    probe = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(big), str(tmp_path / "out.mcap")],
                           env=env(), capture_output=True, text=True, timeout=600)
    assert probe.returncode == 0, probe.stderr
    before, peak = (int(v) * 1024 for v in probe.stdout.split())  # ru_maxrss is in KiB on Linux
    assert peak - before < 0.25 * size, (before, peak, size)
    assert len(load(tmp_path / "out.mcap").component("vehicle40")["t"]) == 10_000


# --- 5. a full disk: one clear line, what was written stays recoverable, no litter ------------------

def _tmpfs_prefix(work: Path, size: str) -> tuple[str, ...]:
    """A command prefix running the command with ``work/small`` a tmpfs of ``size`` in a private mount
    namespace, and copying what the command left there to ``work/left`` afterwards."""
    script = work / "on-small-disk.sh"
    script.write_text('#!/bin/sh\nsize=$1; shift\nmount -t tmpfs -o size="$size" tmpfs small || exit 99\n'
                      '"$@"; code=$?\nmkdir -p left && cp -a small/. left/\nexit $code\n')
    script.chmod(0o755)
    (work / "small").mkdir(exist_ok=True)
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size={size} tmpfs {work / 'small'}"],
                           capture_output=True, text=True)
    if shutil.which("unshare") is None or probe.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs in a private namespace here: {probe.stderr.strip()}")
    return ("unshare", "-rm", str(script), size)


@pytest.mark.parametrize("writer", ["inline", "process"])
def test_a_full_disk_ends_the_run_with_one_line_and_the_trace_recoverable(work: Path, writer: str) -> None:
    prefix = _tmpfs_prefix(work, "700k")
    result = platoon("run", "victim.toml", "--set", "simulation.stop_time=30.0", "--out", "small/t.mcap", "-q",
                     "--trace-writer", writer, cwd=work, prefix=prefix)
    assert result.returncode == 1
    one_line_error(result, "No space left on device", "platoon trace recover small/t.mcap.partial")
    assert sorted(p.name for p in (work / "left").iterdir()) == ["t.mcap.partial"]
    recovered = platoon("trace", "recover", work / "left" / "t.mcap.partial", "--out", work / "fixed.mcap", cwd=work)
    assert recovered.returncode == 0, recovered.stderr
    fixed = load(work / "fixed.mcap")
    assert fixed.component("vehicle4")["t"][-1] > 2.0  # several seconds fit in 700 kB; all of them come back


def test_recover_build_export_and_report_on_a_full_disk_end_with_one_line(work: Path, reference: Path) -> None:
    prefix = _tmpfs_prefix(work, "200k")
    result = platoon("trace", "recover", reference, "--out", "small/fixed.mcap", cwd=work, prefix=prefix)
    assert result.returncode == 2
    one_line_error(result, "No space left on device")
    assert list((work / "left").iterdir()) == []
    shutil.rmtree(work / "left")
    result = platoon("build", "--out", "small/fmus", "--force", cwd=work, prefix=prefix)
    assert result.returncode == 2
    one_line_error(result, "No space left on device")
    assert [p.name for p in (work / "left").rglob("*") if p.is_file()] == []
    for command in (("export", reference, "--csv", "small/csv"), ("report", reference, "--plots", "small/plots")):
        result = platoon(*command, cwd=work, prefix=("unshare", "-rm", str(work / "on-small-disk.sh"), "20k"))
        assert result.returncode == 2, command
        one_line_error(result, "No space left on device", command[2])


# --- 8. bad output paths of report, export and recover -----------------------------------------------

def test_bad_output_paths_exit_2_with_one_line(reference: Path, tmp_path: Path) -> None:
    a_file = tmp_path / "a-file"
    a_file.write_text("keep me\n")
    a_folder = tmp_path / "a-folder"
    a_folder.mkdir()
    cases = [
        (("report", reference, "--plots", a_file), "--plots"),
        (("report", reference, "--plots", "/proc/version/plots"), "--plots"),
        (("export", reference, "--csv", a_file), "--csv"),
        (("export", reference, "--csv", "/proc/version/csv"), "--csv"),
        (("trace", "recover", reference, "--out", a_folder), "--out"),
        (("trace", "recover", reference, "--out", "/proc/version/x.mcap"), "--out"),
        (("trace", "recover", reference, "--out", a_file / "x.mcap"), "--out"),
    ]
    for command, option in cases:
        result = platoon(*command, cwd=tmp_path)
        assert result.returncode == 2, (command, result.stdout, result.stderr)
        one_line_error(result, option)
    assert a_file.read_text() == "keep me\n" and list(a_folder.iterdir()) == []


# --- 9. report works on every trace `run` writes -----------------------------------------------------

def rewrite(source: Path, destination: Path, keep_message, metadata) -> None:
    """Copy a trace record by record, keeping the messages ``keep_message(topic)`` accepts and passing
    each metadata record through ``metadata(name, values)``."""
    with open(source, "rb") as stream, open(destination, "wb") as out:
        reader = make_reader(stream)
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="", library="platoon-cosim")
        summary = reader.get_summary()
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas.get(c.schema_id, 0), c.metadata)
                    for cid, c in summary.channels.items()}
        for _, channel, message in reader.iter_messages():
            if keep_message(channel.topic):
                writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                                   message.sequence)
        for item in reader.iter_metadata():
            writer.add_metadata(item.name, metadata(item.name, dict(item.metadata)))
        writer.finish()


def test_report_on_a_failed_run_with_no_recorded_point(reference: Path, tmp_path: Path) -> None:
    empty = tmp_path / "failed-at-start.mcap"

    def failed(name: str, values: dict[str, str]) -> dict[str, str]:
        if name == "platoon.run":
            values.update(status="failed", error="vehicle2 failed at t = 0 s: initialization", steps_recorded="0",
                          last_time="")
        return values

    rewrite(reference, empty, lambda topic: topic == "/platoon/log", failed)
    for extra in ((), ("--json",), ("--plots", tmp_path / "plots")):
        result = platoon("report", empty, *extra, cwd=tmp_path)
        assert result.returncode == 0, (extra, result.stderr)
        assert "Traceback" not in result.stderr
        assert "no recorded communication point" in result.stdout + result.stderr
        assert "vehicle2 failed at t = 0 s: initialization" in result.stdout + result.stderr
    assert json.loads(platoon("report", empty, "--json", cwd=tmp_path).stdout)["status"] == "failed"


def test_report_on_a_run_whose_config_held_inf_and_nan(reference: Path, tmp_path: Path) -> None:
    nulls = tmp_path / "non-finite.mcap"

    def with_nulls(name: str, values: dict[str, str]) -> dict[str, str]:
        if name == "platoon.config":
            resolved = json.loads(values["resolved"])
            resolved["platoon"]["k_v"] = None  # what model_dump_json writes for inf and NaN
            resolved["path"]["center"] = [None, 0.0]
            resolved["simulation"]["stop_time"] = None
            values["resolved"] = json.dumps(resolved)
        return values

    rewrite(reference, nulls, lambda topic: True, with_nulls)
    result = platoon("report", nulls, "--plots", tmp_path / "plots", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    warning = next(line for line in result.stdout.splitlines() if line.startswith("warning:"))
    assert all(key in warning for key in ("platoon.k_v", "path.center", "simulation.stop_time")), warning
    assert "Warning" not in result.stderr, result.stderr  # the nan figures are announced once, not by numpy
    assert "vehicle4" in result.stdout and (tmp_path / "plots" / "gap_errors.png").is_file()


# --- 10. Ctrl-C always means interrupted, and always works --------------------------------------------

def run_record(path: Path) -> dict[str, str]:
    with open(path, "rb") as stream:
        return {m.name: m.metadata for m in make_reader(stream).iter_metadata()}["platoon.run"]


class StderrLines:
    """A process's stderr read line by line in a thread, so a test can wait for a line, then for the end."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(process.stderr,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in stream:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, pattern: str, timeout: float = 120) -> re.Match[str]:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no line matching {pattern!r} in {timeout} s: {''.join(self.seen)}") from None
            if line is None:
                raise AssertionError(f"stderr ended without a line matching {pattern!r}: {''.join(self.seen)}")
            self.seen.append(line)
            if match := re.search(pattern, line):
                return match

    def rest(self, timeout: float = 120) -> str:
        """Everything the process wrote to stderr, once it closed it."""
        self._thread.join(timeout)
        while (line := self.lines.get_nowait()) is not None:
            self.seen.append(line)
        return "".join(self.seen)


def signal_delivered(pid: int, signum: int, timeout: float = 60) -> None:
    """Until the kernel no longer holds ``signum`` pending for process ``pid``: its handler took it.

    Two pending signals of one kind merge into one, so a test that sends a second must first see the
    first taken (a loaded machine may not schedule the process for a while)."""
    bit = 1 << (signum - 1)
    deadline = time.monotonic() + timeout
    while True:
        pending = 0
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("SigPnd:", "ShdPnd:")):
                pending |= int(line.split()[1], 16)
        if not pending & bit:
            return
        assert time.monotonic() < deadline, f"signal {signum} still pending for process {pid} after {timeout} s"
        time.sleep(0.01)


@pytest.mark.parametrize("engine", ["native", "python"])
def test_a_second_ctrl_c_during_a_long_step_is_an_interruption(work: Path, engine: str) -> None:
    """The forced stop (``stop.forced``: orchestrator/execution/execution.py): a second Ctrl-C breaks the FMU call it
    lands in, and the run is still an interruption (exit 130, status interrupted), not an FMU failure.

    The pythonfmu FMUs with 1 s steps of 10 µs RK4 substeps (the most an FMU takes in one step) spend
    seconds of Python code in every step. Once a progress line says K steps are done, the run is inside
    step K + 1: the first Ctrl-C only asks for a stop at the end of that step, the second breaks it.
    So the trace ends at t = K s; a run that waited for the step to finish would end at K + 1.
    The native core calls back (progress) only every 64 steps, except when paced for a live view: there
    a port the system picks on 127.0.0.1 serves it, and it calls back after every step."""
    trace = work / "long-steps.mcap"
    paced = ["--live", "--live-port", "0"] if engine == "native" else []
    run = subprocess.Popen([*CLI, "run", "victim.toml", "--fmus", "python", "--set", "simulation.step=1.0",
                            "--set", "simulation.max_substep=1e-5", "--set", "simulation.stop_time=10.0",
                            "--out", str(trace), "--engine", engine, "--trace-writer", "inline", "--allow-long", *paced],
                           cwd=work, env={**env(), "PLATOON_PROGRESS_SECONDS": "0"}, stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True, start_new_session=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    stderr_lines = StderrLines(run)
    try:
        done = int(stderr_lines.wait_for(r"\((\d+)/10 steps\)").group(1))  # now inside step done + 1
        os.killpg(run.pid, signal.SIGINT)  # noted: the run would stop at the end of this step
        signal_delivered(run.pid, signal.SIGINT)
        time.sleep(0.1)  # not a wait for a result: the handler runs at the step's next Python bytecode
        os.killpg(run.pid, signal.SIGINT)  # the user insists: stop inside the step
        run.wait(timeout=120)
    finally:
        if run.poll() is None:  # never leave a run of 10 slow steps behind
            os.killpg(run.pid, signal.SIGKILL)
            run.wait()
    stderr = stderr_lines.rest()
    assert run.returncode == 130, stderr
    assert f"interrupted by SIGINT (Ctrl-C) at t = {done:g} s" in stderr and "Traceback" not in stderr, stderr
    record = run_record(trace)
    assert record["status"] == "interrupted" and record["signal"] == "SIGINT", record
    assert float(record["last_time"]) == done, (done, record)  # stopped inside step done + 1, not after it
    assert load(trace).component("vehicle1")["t"][-1] == done


def test_a_stalled_trace_writer_process_does_not_hold_the_run(work: Path) -> None:
    trace = work / "stalled.mcap"
    run = start("run", "victim.toml", *LONG, "--out", trace, "-q", "--trace-writer", "process", cwd=work)
    wait_for_size(trace, 200_000, run)
    children = Path(f"/proc/{run.pid}/task/{run.pid}/children").read_text().split()
    workers = [int(pid) for pid in children if b"orchestrator.trace.serve" in Path(f"/proc/{pid}/cmdline").read_bytes()]
    assert len(workers) == 1
    os.kill(workers[0], signal.SIGSTOP)  # the trace writer hangs (a stuck disk, a debugger ...)
    try:
        os.kill(run.pid, signal.SIGINT)
        signal_delivered(run.pid, signal.SIGINT)  # taken, so the second below is a second, not merged into it
        time.sleep(2.0)  # a window to see the run not end: it cannot while its writer takes nothing
        assert run.poll() is None  # waiting for the writer to finish the file, as it should
        os.kill(run.pid, signal.SIGINT)  # the user insists
        _, stderr = run.communicate(timeout=60)  # far below the writer's 600 s close timeout
    finally:
        for pid in (workers[0], run.pid):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert run.returncode == 130, stderr
    one_line_error((run.returncode, "", stderr), "interrupted", "trace writer process")
    assert not Path(f"/proc/{workers[0]}").exists() or "zombie" in Path(f"/proc/{workers[0]}/status").read_text()
    recovered = platoon("trace", "recover", aside(trace), "--out", work / "fixed.mcap", cwd=work)
    assert recovered.returncode == 0, recovered.stderr
    assert load(work / "fixed.mcap").component("vehicle1")["t"][-1] > 0


def test_two_builds_into_one_folder_at_once_both_succeed(tmp_path: Path) -> None:
    """A sibling of case 1: two runs that find the FMUs out of date build them side by side."""
    from fmus.builders import ALL_FMUS, PYTHONFMU, fmu_guid

    builds = [subprocess.Popen([*CLI, "build", "--out", "fmus", "--force"], cwd=tmp_path, env=env(),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outputs = [process.communicate(timeout=300) for process in builds]
    assert [process.returncode for process in builds] == [0, 0], outputs
    assert sorted(p.name for p in (tmp_path / "fmus").iterdir()) == sorted([f"{name}.fmu" for name in ALL_FMUS]
                                                                           + ["fmi3", "native"])
    for kind in ("native", "fmi3"):  # the native twins, FMI 2.0 and 3.0: whole, no .partial left
        assert sorted(p.name for p in (tmp_path / "fmus" / kind).iterdir()) == ["Link.fmu", "Vehicle.fmu", "VirtualTarget.fmu"]
    for name in ALL_FMUS:
        assert fmu_guid(tmp_path / "fmus" / f"{name}.fmu") == PYTHONFMU.expected_guid(name)


def _channel_copy_spans(data: bytes) -> list[tuple[int, int]]:
    """(offset, end) of each platoon.channels metadata record, read record by record from the file's start."""
    import struct

    spans, position = [], 8  # past the magic
    while position < len(data):
        opcode, length = struct.unpack_from("<BQ", data, position)
        end = position + 9 + length
        if opcode == 0x0C and data[position + 13:position + 13 + 16] == b"platoon.channels":
            spans.append((position, end))
        if opcode == 0x06:  # the first chunk: the copies are all before it
            return spans
        position = end
    return spans


def _copy_record(copy: dict[str, str]) -> bytes:
    """A platoon.channels metadata record as MCAP frames it (the name, then the string map)."""
    import struct

    def text(value: str) -> bytes:
        raw = value.encode()
        return struct.pack("<I", len(raw)) + raw

    pairs = b"".join(text(k) + text(v) for k, v in copy.items())
    content = text("platoon.channels") + struct.pack("<I", len(pairs)) + pairs
    return struct.pack("<BQ", 0x0C, len(content)) + content


@pytest.mark.parametrize("damage", ["unchecked copy", "another run's copy"])
def test_a_channel_copy_that_contradicts_the_chunks_never_relabels_intact_channels(reference: Path, tmp_path: Path,
                                                                                     damage: str) -> None:
    """One of the two copies of the channels (outside the chunks, no CRC of their own) with vehicles 2 and 3
    swapped: with its "crc32" key renamed (an unchecked copy) or with a CRC that checks (a copy spliced from
    another run). The first chunk's own channel records win: recovery gives back every vehicle as it was, and
    says it refused the copy."""
    import json as json_module

    from mcap.reader import make_reader as reader_of

    from orchestrator.trace import channel_copy

    data = reference.read_bytes()
    spans = _channel_copy_spans(data)
    assert len(spans) == channel_copy.COPIES
    with open(reference, "rb") as stream:
        copy = next(dict(m.metadata) for m in reader_of(stream).iter_metadata() if m.name == channel_copy.NAME)
    swapped = copy["channels"].replace("/platoon/vehicle2", "/platoon/vehicleX").replace(
        "/platoon/vehicle3", "/platoon/vehicle2").replace("/platoon/vehicleX", "/platoon/vehicle3")
    assert swapped != copy["channels"]
    if damage == "unchecked copy":
        forged = {"schemas": copy["schemas"], "channels": swapped, "crc33": copy["crc32"]}
    else:
        forged = {"schemas": copy["schemas"], "channels": swapped,
                  "crc32": str(__import__("zlib").crc32(f"{copy['schemas']}\0{swapped}".encode()))}
    start, end = spans[0]
    damaged = tmp_path / "forged.mcap"
    damaged.write_bytes(data[:start] + _copy_record(forged) + data[end:])
    assert json_module.loads(forged["channels"])  # the forged copy decodes: only the chunks can contradict it

    result = platoon("trace", "recover", damaged, "--out", tmp_path / "fixed.mcap", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    original, fixed = load(reference), load(tmp_path / "fixed.mcap")
    for name in ("vehicle2", "vehicle3"):
        for key in ("t", "x", "y", "gap"):
            assert np.array_equal(fixed.component(name)[key], original.component(name)[key]), (name, key)
    assert fixed.metadata["platoon.recovery"]["refused_channel_copies"] == "1"
    assert "1 copy of the channel list refused" in result.stdout
