"""A sweep folder under the output rule: what reads it never replaces any of its files, and what keeps its
books stops in one line when the disk is full.

1. ``platoon sweep-plot DIR --out X`` and ``platoon stability-map DIR --out X`` read every kind of file of
   the sweep folder (results.csv, results/<id>.json, traces/<id>.mcap; a resumed sweep its lock and
   results.parquet too): X is refused when it is one of them, by name, hard link or symlink, with and
   without --overwrite (exit 2, one line), and the file is left as it was. The folder is a real one that
   ``platoon sweep`` made.
2. ``platoon sweep --allow-full-disk`` on a real tmpfs (a private mount namespace, ``unshare -rm``) filled
   to a little free space: whichever of its files the disk fills at (the lock, the table rebuilt at the
   start, a result file, the parquet table at the end; SQLite's "database or disk is full" included), the
   sweep ends with exit 1 and one line naming that file, no traceback; every result it committed reads.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.test_hostile_traces import PAPER, REPO, one_line_error, platoon

KINDS = {  # a file of each kind the readers read, as a path relative to the sweep folder (the first run's)
    "table": lambda folder: "results.csv",
    "parquet": lambda folder: "results.parquet",
    "lock": lambda folder: ".lock",
    "result": lambda folder: f"results/{_first_id(folder)}.json",
    "trace": lambda folder: f"traces/{_first_id(folder)}.mcap",
}
COMMANDS = ("sweep-plot", "stability-map")


def _first_id(folder: Path) -> str:
    return sorted(path.stem for path in (folder / "results").glob("*.json"))[0]


@pytest.fixture(scope="module")
def sweep_folder(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> Path:
    """A real sweep folder: two runs of a string-stability sweep (its keys are what stability-map maps)."""
    work = tmp_path_factory.mktemp("sweep")
    (work / "sweep.toml").write_text(f'base = "{REPO / "configs" / "study" / "string_stability.toml"}"\n'
                                     '[set]\n"simulation.stop_time" = 1.0\n[grid]\n"links.delay" = [0.0, 0.1]\n')
    done = platoon("sweep", work / "sweep.toml", "--out", work / "out", "-q", "--workers", "1", cwd=REPO)
    assert done.returncode == 0, done.stderr
    return work / "out"


def _files(folder: Path) -> dict[str, bytes]:
    return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("command", COMMANDS)
def test_a_map_never_replaces_a_file_of_the_sweep_folder_it_reads(command: str, kind: str, sweep_folder: Path,
                                                                   tmp_path: Path) -> None:
    inside = sweep_folder / KINDS[kind](sweep_folder)
    assert inside.is_file(), inside  # the sweep made one of this kind
    before = _files(sweep_folder)
    hard, soft = tmp_path / "hard.png", tmp_path / "soft.png"
    os.link(inside, hard)
    soft.symlink_to(inside)
    for target in (inside, hard, soft):
        for extra in ((), ("--overwrite",)):
            result = platoon(command, sweep_folder, "--out", target, *extra, cwd=tmp_path)
            assert result.returncode == 2, (target, extra, result.stdout, result.stderr)
            line = one_line_error(result, f"--out {target}", "which this command reads", "choose another path")
            assert inside.name in line, line  # the file it is (by name, or the one the link shares)
            assert _files(sweep_folder) == before
    assert hard.read_bytes() == inside.read_bytes() and soft.resolve() == inside.resolve()


@pytest.mark.parametrize("command", COMMANDS)
def test_a_map_refuses_a_new_name_among_the_sweeps_own_files(command: str, sweep_folder: Path, tmp_path: Path) -> None:
    """results/ and traces/ are the sweep's: a map drawn into them would be taken for a run's file."""
    before = _files(sweep_folder)
    for name in ("results/map.png", "traces/next.mcap"):
        result = platoon(command, sweep_folder, "--out", sweep_folder / name, "--overwrite", cwd=tmp_path)
        assert result.returncode == 2, (name, result.stdout, result.stderr)
        one_line_error(result, f"is {name} of the sweep folder", "which this command reads")
        assert _files(sweep_folder) == before


def test_sweep_plot_still_writes_beside_the_folders_files(sweep_folder: Path, tmp_path: Path) -> None:
    """The refusal is for the sweep's files only: the default map (DIR/map.png) is written, and again."""
    for _ in range(2):
        result = platoon("sweep-plot", sweep_folder, "--x", "links.delay", "--y", "platoon.count", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
    assert (sweep_folder / "map.png").read_bytes().startswith(b"\x89PNG")
    (sweep_folder / "map.png").unlink()


def _hardlink(source: Path, link: Path) -> None:
    os.link(source, link)


def _symlink(source: Path, link: Path) -> None:
    link.symlink_to(source)


@pytest.mark.parametrize("input_, place, make", [
    ("sweep file", "results.csv", None),  # the sweep file itself named DIR/results.csv
    ("sweep file", ".lock", _hardlink),  # the lock's pid would replace its text
    ("base config", "results/abc.json", _symlink),
    ("base config", "traces/abc.mcap", _hardlink),
], ids=["sweep file by name", "sweep file as the lock", "base as a result", "base as a trace"])
def test_a_sweep_never_writes_over_its_sweep_file_or_base(input_: str, place: str, make, tmp_path: Path) -> None:
    """The sweep reads its sweep file and base config, and writes its tables, lock, results and traces in
    --out: a folder where one of those is an input (by name, hard link or symlink) is refused (exit 2, one
    line) before anything is written, the input left as it was."""
    out = tmp_path / "out"
    (out / "results").mkdir(parents=True)
    (out / "traces").mkdir()
    base = tmp_path / "base.toml"
    base.write_text(PAPER.read_text())
    text = f'base = "{base}"\n[grid]\n"platoon.k_v" = [0.5, 0.6]\n'
    sweep = out / place if make is None else tmp_path / "sweep.toml"
    sweep.write_text(text)
    victim = sweep if input_ == "sweep file" else base
    if make is not None:
        make(victim, out / place)
    before = victim.read_bytes()
    result = platoon("sweep", sweep, "--out", out, "-q", cwd=tmp_path)
    assert result.returncode == 2, (result.stdout, result.stderr)
    one_line_error(result, f"--out {out}: its {place} would be", str(victim if make is None or input_ == "base config"
                                                                     else sweep), "which this command reads")
    assert victim.read_bytes() == before and not (out / "results.parquet").exists()


# --- a full disk under the sweep's bookkeeping ------------------------------------------------------------

FILLED = ('#!/bin/sh\nfree=$1; shift\nmount -t tmpfs -o size=1m tmpfs small || exit 99\ncp -a seed/. small/\n'
          'dd if=/dev/zero of=small/filler bs=1k count=2000 2>/dev/null\n'  # fails when full: the disk is full
          '[ "$free" -gt 0 ] && truncate -s -"$free"k small/filler\n'
          '"$@"; code=$?\nmkdir -p left && cp -a small/. left/\nexit $code\n')


def _filled_disk(folder: Path) -> tuple[str, ...]:
    """A command prefix: ``folder/small`` a 1 MB tmpfs holding a copy of ``folder/seed`` and a filler file
    leaving the free space given as the prefix's last word (kB); its content copied to ``folder/left``
    after the command. Skips, saying why, where a tmpfs cannot be mounted."""
    script = folder / "filled.sh"
    script.write_text(FILLED)
    script.chmod(0o755)
    (folder / "small").mkdir()
    (folder / "seed").mkdir()
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", f"mount -t tmpfs -o size=1m tmpfs {folder / 'small'}"],
                           capture_output=True, text=True) if shutil.which("unshare") else None
    if probe is None or probe.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs in a private namespace here: {probe.stderr.strip() if probe else 'no unshare'}")
    return ("unshare", "-rm", str(script))


K_V = (0.5, 0.6, 0.7, 0.8, 0.9)


def _grid(points: int = len(K_V)) -> str:
    return f'"platoon.k_v" = [{", ".join(map(str, K_V[:points]))}]\n'


GRID = _grid()
# rejected points (a negative step) with 3 kB names: no trace, and a row that fills a page every rows or two
REJECTED = '"simulation.step" = [-1.0]\n"name" = [%s]\n' % ", ".join(f'"{chr(97 + i)* 3000}"' for i in range(20))
# free kB on the disk, the runs of the sweep done before (of its points), the points, and the file the disk
# fills at, measured: a 1 s run's trace is ~140 kB, a result file takes a 4 kB page, the parquet table 12 kB
FULL_AT = {
    "lock": (0, 0, GRID, ".lock: cannot write the sweep's pid"),
    "table rebuild": (4, 3, GRID, "results.csv: cannot rebuild it"),  # SQLite's scratch table
    "result file": (40, 3, GRID, "results/"),
    "row": (38, 0, REJECTED, "results.csv: cannot append run"),
    "end": (16, 5, GRID, "results.parquet: cannot write it"),
}


@pytest.mark.parametrize("case", FULL_AT, ids=FULL_AT)
def test_a_sweep_on_a_full_disk_stops_in_one_line_naming_the_file(case: str, tmp_path: Path, fmu_dir: Path) -> None:
    free, done, points, named = FULL_AT[case]
    prefix = _filled_disk(tmp_path)
    (tmp_path / "build").symlink_to(REPO / "build", target_is_directory=True)
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'base = "{PAPER}"\n[set]\n"simulation.stop_time" = 1.0\n[grid]\n{points}')
    if done:  # a sweep of the first points before, its folder (and lock) as it left it
        before = tmp_path / "before.toml"
        before.write_text(sweep.read_text().replace(GRID, _grid(done)))
        assert platoon("sweep", before, "--out", "seed/out", "-q", cwd=tmp_path).returncode == 0
    result = platoon("sweep", sweep, "--out", "small/out", "-q", "--allow-full-disk", "--workers", "1",
                     cwd=tmp_path, prefix=(*prefix, str(free)), timeout=300)
    assert result.returncode == 1, (result.stdout, result.stderr)
    line = one_line_error(result, "sweep stopped: sweep file small/out/" + named, "run the same command to resume")
    full = "database or disk is full" if case == "table rebuild" else "No space left on device"
    assert full in line, line
    left = tmp_path / "left" / "out"
    if case == "lock":  # refused before any run: what it made is gone again
        assert not left.exists(), sorted(left.rglob("*"))
        return
    results = [json.loads(path.read_text()) for path in (left / "results").glob("*.json")]
    assert len(results) >= done, results  # what was committed before stays, and whole
    for record in results:  # every committed run whole: its result reads, its trace is there
        assert record["status"] in ("completed", "invalid"), record
        if record["status"] == "completed":
            assert (left / record["trace"]).stat().st_size > 1000
