"""Every command that writes follows the one output rule (orchestrator/support/output.py).

For each writer (run, layout, figure, export-ssp, trace recover, report --plots, export --csv,
sweep-plot), with the real command in a subprocess on real files: it never replaces one of its inputs
(a hard link or a symlink to it, with or without --overwrite), never a FIFO or a device (a character
device made with mknod in a temporary folder), replaces a file that is not what it writes only with
--overwrite; and on a full disk (a real small tmpfs, in a private mount namespace) it ends with one line
naming the target, the old target untouched and no half file left.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest

from tests.test_hostile_traces import CLI, PAPER, REPO, one_line_error, platoon, reference  # noqa: F401 (a fixture)
from tests.test_hostile_traces import env as cli_env

SHORT = ("--set", "simulation.stop_time=2.0")


@dataclass(frozen=True)
class Writer:
    """A command that writes one file: ``argv(inputs, target)``; ``file`` is the target's name (its suffix matters)."""

    name: str
    argv: Callable[["Inputs", Path], tuple]
    file: str = "out.bin"
    target_in: str = ""  # the target is this file inside the folder given to the command (--plots, --csv)
    progress: str = ""  # the start of the line a long command says at once, before its work (and a failure's line)


@dataclass(frozen=True)
class Inputs:
    config: Path
    trace: Path
    sweep: Path


def _folder_option(option: str) -> Callable[[Inputs, Path], tuple]:
    return lambda inputs, target: ("report" if option == "--plots" else "export", inputs.trace, option, target.parent)


WRITERS = [
    Writer("run", lambda i, t: ("run", i.config, *SHORT, "--out", t, "-q")),
    Writer("layout", lambda i, t: ("layout", i.trace, "--out", t)),
    Writer("figure", lambda i, t: ("figure", i.trace, i.trace, "--out", t), file="out.png", progress="figure: drawing "),
    Writer("export-ssp", lambda i, t: ("export-ssp", i.config, "--out", t)),
    Writer("trace recover", lambda i, t: ("trace", "recover", i.trace, "--out", t)),
    Writer("report --plots", _folder_option("--plots"), target_in="xy.png"),
    Writer("export --csv", _folder_option("--csv"), target_in="vehicle1.csv"),
    Writer("sweep-plot", lambda i, t: ("sweep-plot", i.sweep, "--out", t), file="map.png"),
]


@pytest.fixture
def inputs(reference: Path, tmp_path: Path) -> Inputs:  # noqa: F811 (the fixture imported above)
    (tmp_path / "build").symlink_to(REPO / "build", target_is_directory=True)
    config = tmp_path / "victim.toml"
    shutil.copy(PAPER, config)
    trace = tmp_path / "victim.mcap"
    shutil.copy(reference, trace)
    sweep = tmp_path / "sweep"  # a sweep folder as `platoon sweep` leaves it, one run recorded
    (sweep / "results").mkdir(parents=True)
    (sweep / "results.csv").write_text("id,status\nabc,completed\n")
    (sweep / "results" / "abc.json").write_text(json.dumps({"id": "abc", "status": "completed", "values": {},
                                                             "metrics": {}, "config": {}}))
    return Inputs(config, trace, sweep)


def target_of(writer: Writer, folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return folder / (writer.target_in or writer.file)


def snapshot(path: Path) -> tuple:
    info = os.lstat(path)
    return (stat.S_IFMT(info.st_mode), info.st_ino, path.read_bytes() if stat.S_ISREG(info.st_mode) else None)


def make_device(path: Path) -> None:
    """A character device with /dev/null's numbers in a temporary folder (as root), else skip saying why."""
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError as error:
        pytest.skip(f"cannot make a device node here (needs root): {error}")


@pytest.mark.parametrize("writer", WRITERS, ids=lambda w: w.name)
def test_a_writer_never_replaces_its_input_a_fifo_or_a_device(writer: Writer, inputs: Inputs, tmp_path: Path) -> None:
    own_input = {"run": inputs.config, "export-ssp": inputs.config, "sweep-plot": inputs.sweep / "results.csv"}.get(
        writer.name, inputs.trace)
    before = own_input.read_bytes()
    for n, link in enumerate((os.link, os.symlink)):
        for extra in ((), ("--overwrite",)):
            target = target_of(writer, tmp_path / f"alias-{n}-{len(extra)}")
            link(own_input, target)
            result = platoon(*writer.argv(inputs, target), *extra, cwd=tmp_path)
            assert result.returncode == 2, (link, extra, result.stdout, result.stderr)
            one_line_error(result, "is the same file as", own_input.name, "which this command reads")
            assert own_input.read_bytes() == before
    for name, make, kind in (("fifo", os.mkfifo, "a FIFO"), ("device", make_device, "a character device")):
        for extra in ((), ("--overwrite",)):
            target = target_of(writer, tmp_path / f"{name}-{len(extra)}")
            make(target)
            was = snapshot(target)
            result = platoon(*writer.argv(inputs, target), *extra, cwd=tmp_path)
            assert result.returncode == 2, (name, extra, result.stdout, result.stderr)
            one_line_error(result, str(target.name), f"is {kind}, not a regular file")
            assert snapshot(target) == was and sorted(p.name for p in target.parent.iterdir()) == [target.name]


@pytest.mark.parametrize("writer", [w for w in WRITERS if w.name != "sweep-plot"], ids=lambda w: w.name)
def test_a_writer_replaces_a_foreign_file_only_with_overwrite(writer: Writer, inputs: Inputs, tmp_path: Path) -> None:
    target = target_of(writer, tmp_path / "foreign")
    target.write_text("someone's notes\n")
    refused = platoon(*writer.argv(inputs, target), cwd=tmp_path)
    assert refused.returncode == 2, refused.stderr
    one_line_error(refused, target.name, "exists and is not", "pass --overwrite")
    assert target.read_text() == "someone's notes\n"
    replaced = platoon(*writer.argv(inputs, target), "--overwrite", cwd=tmp_path)
    assert replaced.returncode == 0, replaced.stderr
    assert target.read_bytes() != b"someone's notes\n" and target.stat().st_size > 100
    again = platoon(*writer.argv(inputs, target), cwd=tmp_path)  # what the command wrote: replaced untold
    assert again.returncode == 0, again.stderr
    assert not [p.name for p in target.parent.iterdir() if p.name.startswith(".") or p.suffix in (".tmp", ".partial")]


# --- a full disk: a real small tmpfs in a private mount namespace ------------------------------------------

SMALL_DISK = ('#!/bin/sh\nsize=$1; shift\nmount -t tmpfs -o size="$size" tmpfs small || exit 99\n'
              'cp -a seed/. small/\n"$@"; code=$?\nmkdir -p left && cp -a small/. left/\nexit $code\n')


def on_small_disk(folder: Path, size: str) -> tuple[str, ...]:
    """A command prefix: ``folder/small`` a tmpfs of ``size`` holding a copy of ``folder/seed``, its content
    copied to ``folder/left`` after the command. Skips, saying why, where a tmpfs cannot be mounted."""
    script = folder / "on-small-disk.sh"
    script.write_text(SMALL_DISK)
    script.chmod(0o755)
    (folder / "small").mkdir(exist_ok=True)
    (folder / "seed").mkdir(exist_ok=True)
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size={size} tmpfs {folder / 'small'}"],
                           capture_output=True, text=True) if shutil.which("unshare") else None
    if probe is None or probe.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs in a private namespace here: {probe.stderr.strip() if probe else 'no unshare'}")
    return ("unshare", "-rm", str(script), size)


@pytest.mark.parametrize("writer", [w for w in WRITERS if w.name != "sweep-plot"], ids=lambda w: w.name)
def test_a_full_disk_leaves_the_old_target_and_no_half_file(writer: Writer, inputs: Inputs, tmp_path: Path) -> None:
    folder = tmp_path / "disk"
    folder.mkdir()
    prefix = on_small_disk(folder, "8k")  # two pages: the old file fits, the new one does not
    seed = target_of(writer, folder / "seed" / "out")
    seed.write_text("old\n")
    target = Path("small/out") / seed.name
    result = platoon(*writer.argv(inputs, target), "--overwrite", cwd=folder, prefix=prefix)
    assert result.returncode in (1, 2), (result.stdout, result.stderr)
    lines = result.stderr.splitlines()  # a figure says it reads before it draws (seconds): then one error line
    if writer.progress:
        assert lines and lines[0].startswith(writer.progress), result.stderr
        lines = lines[1:]
    line = one_line_error((result.returncode, result.stdout, "\n".join(lines)), "No space left on device")
    assert "small/out" in line, line
    left = sorted(str(p.relative_to(folder / "left")) for p in (folder / "left").rglob("*") if p.is_file())
    if writer.name == "run":  # a run's unfinished trace stays in its aside file, for `platoon trace recover`
        left = [name for name in left if name != f"out/{seed.name}.partial"]
    assert left == [f"out/{seed.name}"] and (folder / "left" / "out" / seed.name).read_text() == "old\n"


@pytest.mark.parametrize("size", ["100k", "700k", "1200k", "2000k", "4m"])  # full at the 1st, 2nd, 3rd, 5th file; none
def test_export_on_a_disk_that_fills_at_any_file_leaves_only_whole_files(size: str, inputs: Inputs, tmp_path: Path) -> None:
    """The disk fills at a different file (and offset) for each size: every file left is whole, old or new."""
    folder = tmp_path / "disk"
    folder.mkdir()
    prefix = on_small_disk(folder, size)
    complete = tmp_path / "complete"
    assert platoon("export", inputs.trace, "--csv", complete, cwd=tmp_path).returncode == 0
    (folder / "seed" / "csv").mkdir()
    for path in complete.iterdir():
        (folder / "seed" / "csv" / path.name).write_text("t,old\n0.0,1.0\n")
    result = platoon("export", inputs.trace, "--csv", "small/csv", cwd=folder, prefix=prefix)
    if result.returncode != 0:
        one_line_error(result, "--csv small/csv/", "No space left on device", "nothing was replaced")
    left = {p.name: p.read_bytes() for p in (folder / "left" / "csv").iterdir()}
    assert sorted(left) == sorted(p.name for p in complete.iterdir())  # no temporary file, none missing
    for name, data in left.items():
        assert data in (b"t,old\n0.0,1.0\n", (complete / name).read_bytes()), name


def test_a_write_that_fails_at_any_point_leaves_the_old_target_and_nothing_else(tmp_path: Path) -> None:
    """ENOSPC simulated at every write of a many-write output (where no tmpfs can be mounted this is the check)."""
    import errno

    from orchestrator.support.output import OutputError, replacing

    target = tmp_path / "table.csv"
    target.write_text("old\n")
    for failing in range(5):
        with pytest.raises(OutputError, match=r"^--out .*table\.csv: cannot write it: No space left on device"):
            with replacing(target) as aside, open(aside, "w") as stream:
                for row in range(5):
                    if row == failing:
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    stream.write(f"row {row}\n")
        assert target.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["table.csv"]
    with replacing(target) as aside:
        aside.write_text("new\n")
    assert target.read_text() == "new\n" and [p.name for p in tmp_path.iterdir()] == ["table.csv"]


# --- platoon build --out: the FMUs have names of their own in the folder it is given --------------------

def test_build_never_replaces_a_source_a_fifo_or_a_device(tmp_path: Path) -> None:
    """`platoon build --out DIR` replaces DIR/Vehicle.fmu whatever it holds (a damaged FMU is rebuilt), but
    never when it is one of the sources it reads (hard link or symlink), a FIFO (it used to hang reading it
    as a zip) or a device: exit 2, one line, nothing changed."""
    source = REPO / "fmus" / "slaves" / "Vehicle.py"
    before = source.read_bytes()
    for n, link in enumerate((os.link, os.symlink)):
        out = tmp_path / f"alias-{n}"
        out.mkdir()
        try:
            link(source, out / "Vehicle.fmu")
        except OSError as error:  # a hard link across filesystems (the temporary folder elsewhere)
            pytest.skip(f"cannot link the source into the temporary folder: {error}")
        result = platoon("build", "--out", out, cwd=tmp_path)
        assert result.returncode == 2, (result.stdout, result.stderr)
        one_line_error(result, "build --out", "Vehicle.fmu", "is the same file as", "Vehicle.py", "which this command reads")
        assert source.read_bytes() == before
    for name, make, kind in (("fifo", os.mkfifo, "a FIFO"), ("device", make_device, "a character device")):
        out = tmp_path / name
        out.mkdir()
        make(out / "Vehicle.fmu")
        was = snapshot(out / "Vehicle.fmu")
        result = platoon("build", "--out", out, cwd=tmp_path, timeout=120)
        assert result.returncode == 2, (name, result.stdout, result.stderr)
        one_line_error(result, "Vehicle.fmu", f"is {kind}, not a regular file")
        assert snapshot(out / "Vehicle.fmu") == was and [p.name for p in out.iterdir()] == ["Vehicle.fmu"]


def test_build_on_a_full_disk_leaves_the_old_fmu_and_no_half_file(tmp_path: Path) -> None:
    folder = tmp_path / "disk"
    folder.mkdir()
    prefix = on_small_disk(folder, "8k")  # two pages: the old file fits, a 250 kB FMU does not
    (folder / "seed" / "out").mkdir()
    (folder / "seed" / "out" / "Vehicle.fmu").write_text("old\n")
    result = platoon("build", "--out", "small/out", "--force", cwd=folder, prefix=prefix)
    assert result.returncode == 2, (result.stdout, result.stderr)
    one_line_error(result, "build --out small/out/Vehicle.fmu", "No space left on device", "nothing was replaced")
    left = sorted(str(p.relative_to(folder / "left")) for p in (folder / "left").rglob("*") if p.is_file())
    assert left == ["out/Vehicle.fmu"] and (folder / "left" / "out" / "Vehicle.fmu").read_text() == "old\n"


# --- the FMUs a run builds for itself (build/fmus, before its first step) ---------------------------------

@pytest.mark.parametrize("command", ["run", "sweep"])
def test_a_fifo_where_a_run_builds_its_fmus_is_refused_in_one_line_not_read(command: str, tmp_path: Path) -> None:
    """A run (and a sweep, before its workers start) builds its FMUs into build/fmus/ under the current
    folder when they are missing or stale. A FIFO in an FMU's place used to hang the run (the zip reader
    opened it, waiting for a writer forever): now exit 2, one line naming it, the FIFO left as it was."""
    from tests.test_hostile_traces import start

    fifos = [tmp_path / "build" / "fmus" / "Vehicle.fmu", tmp_path / "build" / "fmus" / "native" / "Vehicle.fmu"]
    for fifo in fifos:  # the pythonfmu and the native one: whichever kind this machine runs
        fifo.parent.mkdir(parents=True, exist_ok=True)
        os.mkfifo(fifo)
    was = [snapshot(fifo) for fifo in fifos]
    if command == "run":
        argv = ("run", PAPER, "--out", tmp_path / "t.mcap")
    else:
        (tmp_path / "sweep.toml").write_text(f'base = "{PAPER}"\n[grid]\n"platoon.k_v" = [0.5, 0.6]\n')
        argv = ("sweep", tmp_path / "sweep.toml", "--out", tmp_path / "out", "-q")
    process = start(*argv, cwd=tmp_path)
    try:
        stdout, stderr = process.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, 9)
        process.communicate()
        raise AssertionError(f"platoon {command} hung on the FIFO at build/fmus") from None
    assert process.returncode == 2, (stdout, stderr)
    line = one_line_error((process.returncode, stdout, stderr), "Vehicle.fmu", "is a FIFO, not a regular file")
    assert "build/fmus/" in line, line  # where it is
    assert [snapshot(fifo) for fifo in fifos] == was
    assert sorted(p.name for p in tmp_path.iterdir()) == ["build", *(["sweep.toml"] if command == "sweep" else [])]


@pytest.mark.parametrize("writer_kind", ["inline", "process"])
def test_a_runs_trace_is_synced_then_renamed_then_its_folder_synced(writer_kind: str, tmp_path: Path) -> None:
    """`platoon run` replacing an existing trace: the finalized aside file reaches the disk before the
    rename, and the folder after it (a power cut then leaves the old trace or the whole new one).
    Watched in the process that finalizes the file (the worker's, for "process"): a sitecustomize on
    the path wraps os.fsync and prints each synced path with the folder's listing at that moment."""
    old = tmp_path / "t.mcap"
    done = platoon("run", PAPER, "--set", "simulation.stop_time=0.2", "-q", "--out", old, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    watcher = tmp_path / "sitecustomize.py"
    watcher.write_text(
        "import os, sys\n"
        "_fsync = os.fsync\n"
        "def _watched(fd):\n"
        "    path = os.path.realpath(f'/proc/self/fd/{fd}')\n"
        "    folder = path if os.path.isdir(path) else os.path.dirname(path)\n"
        "    if folder == %r:\n"
        "        print('FSYNC', os.path.basename(path) or '.', sorted(os.listdir(folder)), file=sys.stderr, flush=True)\n"
        "    _fsync(fd)\n"
        "os.fsync = _watched\n" % str(tmp_path))
    env = {**cli_env(), "PYTHONPATH": os.pathsep.join([str(tmp_path), str(REPO)])}
    result = subprocess.run([*CLI, "run", str(PAPER), "--set", "simulation.stop_time=0.2", "-q", "--trace-writer",
                             writer_kind, "--out", str(old)], cwd=tmp_path, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    synced = [line.split(" ", 1)[1] for line in result.stderr.splitlines() if line.startswith("FSYNC ")]
    names = [entry.split(" ", 1)[0] for entry in synced]
    trace = next((i for i, name in enumerate(names) if name.startswith(("t.mcap.", ".t.mcap."))), None)
    assert trace is not None, result.stderr  # the aside file was synced ...
    assert "'t.mcap'" in synced[trace] and f"'{names[trace]}'" in synced[trace], synced  # ... before the rename
    assert tmp_path.name in names[trace + 1:], synced  # then the folder, after the rename
    assert not any(name.startswith(("t.mcap.", ".t.mcap.")) for name in os.listdir(tmp_path))


def test_report_refuses_a_plot_target_before_reading_the_trace(tmp_path: Path) -> None:
    """`platoon report --plots DIR`: a panel's target that may not be replaced (a foreign file, without
    --overwrite) is refused before the trace is read: the error names the target even when the trace
    is not one, and the foreign file is untouched."""
    plots = tmp_path / "plots"
    plots.mkdir()
    foreign = plots / "xy.png"
    foreign.write_text("my notes, not an image\n")
    bogus = tmp_path / "bogus.mcap"
    bogus.write_text("not an MCAP file\n")
    result = platoon("report", bogus, "--plots", plots, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    assert "xy.png" in result.stderr and "not an MCAP" not in result.stderr, result.stderr
    assert foreign.read_text() == "my notes, not an image\n"


# --- what a run reads besides its config: the FMUs in build/fmus and the files the config names ------------

@pytest.mark.parametrize("command", ["run", "export-ssp"])
def test_a_run_never_replaces_an_fmu_it_reads_or_a_file_its_config_names(command: str, tmp_path: Path,
                                                                        fmu_dir: Path) -> None:
    """`platoon run` and `platoon export-ssp` read the FMUs in build/fmus (and build/fmus/native) under the
    current folder: `--out build/fmus/Vehicle.fmu --overwrite` used to replace the FMU with the trace. Now
    each FMU, by name, hard link or symlink, and a Zenoh config the config names, is refused (exit 2)."""
    fmus = tmp_path / "build" / "fmus"
    shutil.copytree(fmu_dir, fmus, ignore=shutil.ignore_patterns("*.tmp"))
    zenoh = tmp_path / "zenoh.json5"
    zenoh.write_text("{}\n")
    config = tmp_path / "live.toml"  # a live vehicle: the run would wait for its robot, but is refused before
    config.write_text((REPO / "configs" / "hil" / "m3pi_live3.toml").read_text()
                      + '\n[vehicles.2]\nendpoint = "zenoh"\nzenoh_config = "zenoh.json5"\n')
    victims = [fmus / "Vehicle.fmu", zenoh] + ([fmus / "native" / "Vehicle.fmu"] if (fmus / "native").is_dir() else [])
    for victim in victims:
        before = victim.read_bytes()
        hard, soft = tmp_path / "hard.bin", tmp_path / "soft.bin"
        os.link(victim, hard)
        soft.symlink_to(victim)
        for target in (victim, hard, soft):
            argv = ("run", config, "-q") if command == "run" else ("export-ssp", config)
            result = platoon(*argv, "--out", target, "--overwrite", cwd=tmp_path, timeout=120)
            assert result.returncode == 2, (victim, target, result.stdout, result.stderr)
            one_line_error(result, "is the same file as", victim.name, "which this command reads")
            assert victim.read_bytes() == before
        hard.unlink()
        soft.unlink()
