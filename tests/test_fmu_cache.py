"""The per-user cache of extracted FMUs (orchestrator/components/cache.py): reused, checked, shared, bounded.

Every test has a cache folder of its own (``root``) and the real FMUs of build/fmus; processes that
hold an entry, race to make one or die while making one are real subprocesses.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from fmus.builders import ALL_FMUS, PYTHONFMU
from fmus.platforms import fmi_platform
from orchestrator.components import cache as fmu_cache
from orchestrator.components.fmu import UnpackedFmu
from orchestrator.support.scratch import PREFIX

REPO = Path(__file__).resolve().parents[1]
BINARY = "binaries/{}/Vehicle{}".format(*fmi_platform())


@pytest.fixture
def root(tmp_path: Path) -> Path:
    return tmp_path / "cache"


@pytest.fixture
def vehicle(fmu_dir: Path) -> Path:
    return fmu_dir / "Vehicle.fmu"


def entries(root: Path) -> list[Path]:
    return sorted(root.glob(f"{fmu_cache.ENTRY_PREFIX}*"))


def leftovers(root: Path) -> list[Path]:
    return sorted(path for path in root.iterdir() if not path.name.startswith(fmu_cache.ENTRY_PREFIX))


def zipped(fmu: Path, name: str) -> bytes:
    with zipfile.ZipFile(fmu) as archive:
        return archive.read(name)


def start_holder(fmu: Path, root: Path, before: str = "") -> subprocess.Popen[str]:
    """A process that holds ``fmu``'s entry and sleeps; prints the folder (or None) once it holds it.
    ``before``: Python run first (e.g. to slow extraction down)."""
    code = (f"import sys, time\n{before}\nfrom pathlib import Path\nfrom orchestrator.components import cache as fmu_cache\n"
            f"held = fmu_cache.hold(Path({str(fmu)!r}), Path({str(root)!r}))\n"
            "print(held.directory if held else None, flush=True)\ntime.sleep(600)\n")
    return subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})


def kill(process: subprocess.Popen[str]) -> None:
    process.send_signal(signal.SIGKILL)
    process.wait()


def test_the_second_use_finds_the_first_extraction(vehicle: Path, root: Path) -> None:
    first = fmu_cache.hold(vehicle, root)
    assert first is not None
    binary = os.stat(first.directory / BINARY)
    first.release()
    second = fmu_cache.hold(vehicle, root)
    assert second is not None and second.directory == first.directory
    assert os.stat(second.directory / BINARY).st_ino == binary.st_ino  # not extracted again
    assert (second.directory / BINARY).read_bytes() == zipped(vehicle, BINARY)
    second.release()
    assert len(entries(root)) == 1 and leftovers(root) == []


def test_an_fmu_in_use_is_shared_by_a_second_run(vehicle: Path, root: Path) -> None:
    holder = start_holder(vehicle, root)
    try:
        theirs = Path(holder.stdout.readline().strip())
        ours = fmu_cache.hold(vehicle, root)
        assert ours is not None and ours.directory == theirs
        ours.release()
    finally:
        kill(holder)
    assert len(entries(root)) == 1 and leftovers(root) == []


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [
    _flip,
    lambda path: path.write_bytes(path.read_bytes()[:-1]),
    lambda path: path.write_bytes(path.read_bytes() + b"\0"),
    Path.unlink,
], ids=["byte flipped", "truncated", "grown", "deleted"])
def test_a_damaged_cached_file_is_found_and_extracted_again(vehicle: Path, root: Path, damage) -> None:
    held = fmu_cache.hold(vehicle, root)
    held.release()
    damage(held.directory / BINARY)
    again = fmu_cache.hold(vehicle, root)
    assert again is not None
    assert (again.directory / BINARY).read_bytes() == zipped(vehicle, BINARY)
    again.release()
    assert len(entries(root)) == 1 and leftovers(root) == []


def test_a_damaged_entry_another_run_holds_is_left_to_it(vehicle: Path, root: Path, monkeypatch) -> None:
    monkeypatch.setenv(fmu_cache.CACHE_ENV, str(root))
    holder = start_holder(vehicle, root)
    try:
        theirs = Path(holder.stdout.readline().strip())
        _flip(theirs / BINARY)
        assert fmu_cache.hold(vehicle, root) is None
        private = UnpackedFmu.open_cached(vehicle)  # this run extracts privately instead
        assert private._held is None and (private.directory / BINARY).read_bytes() == zipped(vehicle, BINARY)
        private.cleanup()
        assert theirs.is_dir()  # never replaced under a run that uses it
    finally:
        kill(holder)
    repaired = fmu_cache.hold(vehicle, root)  # the holder is gone: the entry is replaced now
    assert repaired is not None and (repaired.directory / BINARY).read_bytes() == zipped(vehicle, BINARY)
    repaired.release()
    assert len(entries(root)) == 1 and leftovers(root) == []


def test_runs_starting_together_make_one_entry(vehicle: Path, root: Path) -> None:
    holders = [start_holder(vehicle, root) for _ in range(4)]
    try:
        folders = {holder.stdout.readline().strip() for holder in holders}
    finally:
        for holder in holders:
            kill(holder)
    assert folders == {str(entries(root)[0] / fmu_cache.FILES)}
    assert len(entries(root)) == 1 and leftovers(root) == []


def test_a_run_killed_while_extracting_leaves_nothing_that_breaks_the_next(vehicle: Path, root: Path) -> None:
    slow = ("import fmpy\n_extract = fmpy.extract\n"
            "def extract(*a, **k):\n    _extract(*a, **k); print('extracted', flush=True); time.sleep(600)\n"
            "fmpy.extract = extract")
    victim = start_holder(vehicle, root, before=slow)
    try:
        assert victim.stdout.readline().strip() == "extracted"
    finally:
        kill(victim)
    assert entries(root) == [] and [p.name[:len(PREFIX)] for p in leftovers(root)] == [PREFIX]  # its half-made entry
    held = fmu_cache.hold(vehicle, root)
    assert held is not None and (held.directory / BINARY).read_bytes() == zipped(vehicle, BINARY)
    held.release()
    assert len(entries(root)) == 1 and leftovers(root) == []  # swept when the entry was made


def _distinct_copies(fmu: Path, folder: Path, count: int) -> list[Path]:
    """Copies of ``fmu`` with different bytes (a zip comment each): different cache entries."""
    folder.mkdir()
    copies = []
    for index in range(count):
        copy = folder / f"Vehicle{index}.fmu"
        shutil.copy(fmu, copy)
        with zipfile.ZipFile(copy, "a") as archive:
            archive.comment = f"copy {index}".encode()
        copies.append(copy)
    return copies


def test_the_cache_is_bounded_but_keeps_entries_in_use(vehicle: Path, root: Path, tmp_path: Path) -> None:
    copies = _distinct_copies(vehicle, tmp_path / "copies", fmu_cache.KEEP + 3)
    holder = start_holder(copies[0], root)  # the oldest entry, in use all along
    try:
        in_use = Path(holder.stdout.readline().strip())
        for copy in copies[1:]:
            fmu_cache.hold(copy, root).release()
        assert in_use.is_dir()
        assert len(entries(root)) == fmu_cache.KEEP + 1  # the newest KEEP, and the one in use
    finally:
        kill(holder)
    fmu_cache.hold(copies[-1], root).release()  # no new entry: nothing is evicted
    assert len(entries(root)) == fmu_cache.KEEP + 1
    fmu_cache.hold(copies[1], root).release()  # evicted earlier: made again, and the old in-use one goes now
    assert len(entries(root)) == fmu_cache.KEEP and not in_use.exists()
    assert leftovers(root) == []


def test_an_unusable_cache_means_a_private_extraction(vehicle: Path, tmp_path: Path, monkeypatch) -> None:
    blocked = tmp_path / "a file"
    blocked.write_text("not a folder")
    assert fmu_cache.hold(vehicle, blocked / "cache") is None
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)  # others could put their own binary there
    assert fmu_cache.hold(vehicle, shared) is None and list(shared.iterdir()) == []
    monkeypatch.setenv(fmu_cache.CACHE_ENV, "off")
    private = UnpackedFmu.open_cached(vehicle)
    assert private._held is None and (private.directory / BINARY).is_file()
    private.cleanup()
    assert not private.directory.exists()


def test_a_run_from_the_cache_records_what_a_private_one_does(tmp_path: Path, fmu_dir: Path, monkeypatch) -> None:
    from orchestrator.scenario.config import config_from_mapping
    from orchestrator.execution.run import run_scenario
    from orchestrator.trace import load

    from mcap.reader import make_reader

    def declared(path: Path) -> tuple[list, list]:
        """The file's schemas and channels (names, encodings, data, metadata: the outputs' descriptions)."""
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        return (sorted((s.name, s.encoding, s.data) for s in summary.schemas.values()),
                sorted((c.topic, c.message_encoding, sorted(c.metadata.items())) for c in summary.channels.values()))

    config = config_from_mapping({"name": "cached", "platoon": {"count": 3}, "simulation": {"stop_time": 1.0}})
    traces, files = {}, []
    for mode in ("off", str(tmp_path / "cache"), str(tmp_path / "cache")):  # private, cache made, cache used
        monkeypatch.setenv(fmu_cache.CACHE_ENV, mode)
        out = tmp_path / f"{len(traces)}.mcap"
        assert run_scenario(config, "", out, fmu_dir=fmu_dir).status == "completed"
        traces[len(traces)] = load(out)
        files.append(out)
    assert len(entries(tmp_path / "cache")) == 2  # Vehicle and VirtualTarget
    assert declared(files[0]) == declared(files[1]) == declared(files[2])
    first = traces[0]
    assert first.metadata["platoon.fmus"] == traces[1].metadata["platoon.fmus"] == traces[2].metadata["platoon.fmus"]
    for other in (traces[1], traces[2]):
        assert first.channels.keys() == other.channels.keys() and first.errors.keys() == other.errors.keys()
        for name, columns in first.channels.items():
            assert columns.keys() == other.channels[name].keys()
            assert all((columns[key] == other.channels[name][key]).all() for key in columns)
        assert all((first.errors[key] == other.errors[key]).all() for key in first.errors)


def test_making_an_entry_sweeps_what_killed_private_runs_left(vehicle: Path, root: Path, tmp_path: Path,
                                                             monkeypatch) -> None:
    """Runs that find their FMUs cached make no temp folders, so the sweep of dead runs' temp folders
    (orchestrator/support/scratch.py) also happens when an entry is made."""
    import tempfile

    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", None)
    dead = temp / f"{PREFIX}fmu-Vehicle-killed"
    dead.mkdir()
    (dead / ".owner.lock").touch()  # its owner's lock died with it
    fmu_cache.hold(vehicle, root).release()
    assert not dead.exists()


@pytest.mark.parametrize("name", ALL_FMUS)
def test_the_cached_description_is_fmpys(fmu_dir: Path, root: Path, name: str) -> None:
    """A run from the cache reads the model description without FMPy: every field it reads must be
    what FMPy reads from the FMU."""
    from fmpy import read_model_description

    fmu = next(built.path for built in PYTHONFMU.build(fmu_dir, names=ALL_FMUS) if built.name == name)
    held = fmu_cache.hold(fmu, root)
    expected, got = read_model_description(str(fmu)), held.description
    held.release()
    assert got.guid == expected.guid and got.coSimulation.modelIdentifier == expected.coSimulation.modelIdentifier
    assert len(got.modelVariables) == len(expected.modelVariables) > 0
    for ours, fmpys in zip(got.modelVariables, expected.modelVariables):
        for field in fmu_cache._VARIABLE_FIELDS:
            assert getattr(ours, field) == getattr(fmpys, field), (ours.name, field)


def test_a_damaged_cached_description_is_made_again(vehicle: Path, root: Path) -> None:
    held = fmu_cache.hold(vehicle, root)
    held.release()
    stored = held.directory.parent / fmu_cache.DESCRIPTION
    stored.write_text(stored.read_text().replace('"output"', '"input"', 1))  # still valid JSON
    again = fmu_cache.hold(vehicle, root)
    assert again is not None and again.description == held.description
    again.release()
    assert len(entries(root)) == 1 and leftovers(root) == []
