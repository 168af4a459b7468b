"""The kept verdict on a run's FMUs (orchestrator/components/fmu_checks.py) and the kept installed versions
(orchestrator/support/versions.py): given again only while nothing they were computed from changed.

Each test has a cache folder of its own (``XDG_CACHE_HOME``) and FMUs copied from the shared build into a
folder of its own, so what it damages or rebuilds is its own.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import sys
import time
from pathlib import Path

import pytest

from fmus.builders import FMU_NAMES, NATIVE_FMI2
from orchestrator.components import fmu_checks
from orchestrator.components.kinds import ensure_fmus, native_buildable
from orchestrator.support.versions import INSTALLED, installed_versions

pytestmark = pytest.mark.skipif(not native_buildable(), reason="no C compiler: the native FMUs cannot be built")


@pytest.fixture
def own_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache"


@pytest.fixture
def fmus_here(native_fmu_dir: Path, tmp_path: Path) -> Path:
    """A folder of pythonfmu FMUs' place (``ensure_fmus``'s argument) whose native/ holds copies of the current FMUs."""
    folder = tmp_path / "fmus"
    (folder / "native").mkdir(parents=True)
    for name in FMU_NAMES:
        shutil.copy(native_fmu_dir / f"{name}.fmu", folder / "native" / f"{name}.fmu")
    return folder


def test_a_second_run_takes_the_kept_verdict_with_the_builders_guids(own_cache: Path, fmus_here: Path) -> None:
    native = fmus_here / "native"
    assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is None  # nothing kept yet
    paths = ensure_fmus(fmus_here, "native", FMU_NAMES)
    assert paths == {name: native / f"{name}.fmu" for name in FMU_NAMES}
    known = fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES)
    assert known is not None and [fmu.name for fmu in known] == list(FMU_NAMES)
    assert [fmu.guid for fmu in known] == [NATIVE_FMI2.expected_guid(name) for name in FMU_NAMES]
    assert not any(fmu.rebuilt for fmu in known)
    assert ensure_fmus(fmus_here, "native", FMU_NAMES) == paths


def test_an_fmu_damaged_in_place_is_checked_again_and_rebuilt(own_cache: Path, fmus_here: Path) -> None:
    native = fmus_here / "native"
    ensure_fmus(fmus_here, "native", FMU_NAMES)
    vehicle = native / "Vehicle.fmu"
    whole = vehicle.read_bytes()
    stamp = os.stat(vehicle)
    damaged = bytearray(whole)
    damaged[len(damaged) // 2] ^= 0xFF  # same size; the modification time put back as it was: only the change time tells
    vehicle.write_bytes(bytes(damaged))
    os.utime(vehicle, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    assert not NATIVE_FMI2.is_complete(vehicle, "Vehicle", NATIVE_FMI2.expected_guid("Vehicle"))
    assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is None
    ensure_fmus(fmus_here, "native", FMU_NAMES)  # checked, found damaged, rebuilt
    assert NATIVE_FMI2.is_complete(vehicle, "Vehicle", NATIVE_FMI2.expected_guid("Vehicle"))
    assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is not None


def test_an_fmu_replaced_by_another_file_is_checked_again(own_cache: Path, fmus_here: Path) -> None:
    native = fmus_here / "native"
    ensure_fmus(fmus_here, "native", FMU_NAMES)
    target = native / "VirtualTarget.fmu"
    shutil.copy(native / "Vehicle.fmu", target)  # a whole FMU, of the wrong model
    assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is None
    ensure_fmus(fmus_here, "native", FMU_NAMES)
    assert NATIVE_FMI2.is_complete(target, "VirtualTarget", NATIVE_FMI2.expected_guid("VirtualTarget"))


def test_a_source_of_the_guid_touched_is_checked_again(own_cache: Path, fmus_here: Path) -> None:
    native = fmus_here / "native"
    ensure_fmus(fmus_here, "native", FMU_NAMES)
    source = NATIVE_FMI2.digest_files("Vehicle")[0]  # a C source: its stamp changes, its contents do not
    stamp = os.stat(source)
    try:
        os.utime(source, ns=(stamp.st_atime_ns, stamp.st_mtime_ns + 1_000_000))
        assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is None
        ensure_fmus(fmus_here, "native", FMU_NAMES)  # the same GUID: found current, nothing rebuilt, kept again
        assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is not None
    finally:
        os.utime(source, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))


def test_a_module_added_to_a_bundled_folder_is_checked_again(own_cache: Path, fmus_here: Path,
                                                             monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The folders' own times are stamped: a module added changes every GUID without changing any file listed."""
    from fmus.builders import pythonfmu

    native = fmus_here / "native"
    ensure_fmus(fmus_here, "native", FMU_NAMES)
    folder = tmp_path / "model"
    folder.mkdir()
    monkeypatch.setattr(pythonfmu, "BUNDLED_FOLDERS", (*pythonfmu.BUNDLED_FOLDERS, folder))
    ensure_fmus(fmus_here, "native", FMU_NAMES)  # kept with the extra folder's time
    assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is not None
    time.sleep(0.01)
    (folder / "added.py").write_text("")
    assert fmu_checks.known_current(NATIVE_FMI2, native, FMU_NAMES) is None


def test_installed_versions_are_importlib_metadatas_and_follow_sys_path(own_cache: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    expected = {name: importlib.metadata.version(name) for name in INSTALLED}
    assert installed_versions(INSTALLED) == expected  # asked, then kept
    kept = list((own_cache / "platoon-cosim" / "versions").iterdir())
    assert len(kept) == 1
    entry = json.loads(kept[0].read_text())
    entry["versions"] = {name: "0.0.0-kept" for name in INSTALLED}  # what the cache says is what comes back ...
    kept[0].write_text(json.dumps(entry))
    assert installed_versions(INSTALLED) == entry["versions"]
    # ... until a folder of sys.path changes (a distribution installed or removed there)
    folder = tmp_path / "site"
    folder.mkdir()
    monkeypatch.setattr(sys, "path", [*sys.path, str(folder)])
    assert installed_versions(INSTALLED) == expected  # another sys.path: asked, kept in an entry of its own
    (entry_file,) = set((own_cache / "platoon-cosim" / "versions").iterdir()) - set(kept)
    entry = json.loads(entry_file.read_text())
    entry["versions"] = {name: "0.0.0-kept" for name in INSTALLED}
    entry_file.write_text(json.dumps(entry))
    assert installed_versions(INSTALLED) == entry["versions"]
    time.sleep(0.01)
    (folder / "other-1.0.dist-info").mkdir()
    assert installed_versions(INSTALLED) == expected
