"""Which FMUs a run steps: the native C twins or the pythonfmu originals, and where each kind lives.

Both kinds are the same model with the same variables (fmus/model is the science; the native C files
mirror it and tests hold them to it), so a run, a trace and a summary mean the same with either.
What differs is what the host needs and what a step costs: a native FMU needs nothing but the C
library and costs about a microsecond per step; a pythonfmu FMU runs its model in Python (tens of
microseconds per step) and needs a Python installation on the host. So a run takes the native ones
wherever they can be built (a C compiler is present), and ``--fmus python`` (or ``simulation.fmus``)
picks the pythonfmu ones, e.g. to compare or on a machine without a compiler.

The pythonfmu FMUs live in ``build/fmus/``, the native ones in ``build/fmus/native/`` (the builders'
defaults); a caller passes the first folder and this module finds the second below it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

if TYPE_CHECKING:
    from orchestrator.scenario.scenario import Scenario

FMU_KINDS = ("native", "python")
NATIVE_SUBFOLDER = "native"


class FmuKindError(ValueError):
    """The requested FMU kind cannot be used here (the message says why and what to do)."""


def native_buildable() -> bool:
    """True when this machine can build the native FMUs (a C compiler is on PATH or in $CC)."""
    from fmus.builders import NoCompiler, compiler

    try:
        compiler()
    except NoCompiler:
        return False
    return True


def native_built(fmu_dir: Path) -> bool:
    """True when current native FMUs are in place below ``fmu_dir`` (built here or copied from a machine
    with a compiler): they run without one."""
    from fmus.builders import FMU_NAMES, NATIVE_FMI2

    folder = fmu_folder(fmu_dir, "native")
    return all(NATIVE_FMI2.is_complete(folder / f"{name}.fmu", name, NATIVE_FMI2.expected_guid(name))
               for name in FMU_NAMES)


def resolve_fmu_kind(requested: str | None, fmu_dir: Path | None = None) -> str:
    """The kind a run uses: the one requested (``--fmus`` over ``simulation.fmus``), else native where
    it can be built or is built already (below ``fmu_dir``), else python."""
    if requested is None:
        buildable = native_buildable() or (fmu_dir is not None and native_built(fmu_dir))
        return "native" if buildable else "python"
    if requested not in FMU_KINDS:
        raise FmuKindError(f"unknown FMU kind {requested!r}; expected one of {', '.join(FMU_KINDS)}")
    return requested


def fmu_folder(fmu_dir: Path, kind: str) -> Path:
    """Where FMUs of ``kind`` are built, below the pythonfmu folder ``fmu_dir``."""
    return Path(fmu_dir) / NATIVE_SUBFOLDER if kind == "native" else Path(fmu_dir)


def ensure_fmus(fmu_dir: Path, kind: str, names: Sequence[str],
                announce: Callable[[str, Path], None] | None = None) -> dict[str, Path]:
    """Paths of FMUs ``names`` of ``kind``, built first where missing or out of date (``announce(name,
    folder)`` before each build).

    The build follows the output rule (orchestrator/support/output.py, ``OwnFiles``): a FIFO, device or
    folder in an FMU's place is refused (``OutputError``, one line naming it) before anything reads it,
    a source of the fmus package is never replaced, and an FMU is written aside, synced and renamed.

    ``LiveVehicle`` (a live robot as an FMU) and ``RemoteVehicle`` (a served FMU's client) exist only as
    pythonfmu FMUs: they run the bridge's Python code, so they come from the pythonfmu folder whatever
    ``kind`` says.
    """
    from fmus.builders import LIVE_FMU, PYTHONFMU, REMOTE_FMU

    paths: dict[str, Path] = {}
    native = [name for name in names if name not in (LIVE_FMU, REMOTE_FMU)] if kind == "native" else []
    python = [name for name in names if name not in native]
    if native:
        from fmus.builders import NATIVE_FMI2, NoCompiler

        try:
            built = _current(NATIVE_FMI2, fmu_folder(fmu_dir, "native"), tuple(native), announce)
        except NoCompiler as error:
            raise FmuKindError(f"{error}; run with --fmus python (or simulation.fmus = \"python\")") from None
        paths.update({fmu.name: fmu.path for fmu in built})
    if python:
        built = _current(PYTHONFMU, Path(fmu_dir), tuple(python), announce)
        paths.update({fmu.name: fmu.path for fmu in built})
    return {name: paths[name] for name in names}


def _current(builder, folder: Path, names: tuple[str, ...], announce: Callable[[str, Path], None] | None) -> list:
    """``builder.build(folder, names=names)`` under the output rule, or its verdict of an earlier run when
    nothing it depends on changed since (orchestrator/components/fmu_checks.py)."""
    from fmus.builders.base import source_files

    from orchestrator.components import fmu_checks
    from orchestrator.support.output import OwnFiles

    known = fmu_checks.known_current(builder, folder, names)
    if known is not None:
        return known
    sources = {name: fmu_checks.sources_stamp(builder, name) for name in names}
    before = {name: fmu_checks.identity(Path(folder) / f"{name}.fmu") for name in names}
    built = builder.build(folder, names=names, announce=announce, output=OwnFiles(source_files(), "FMU"))
    fmu_checks.remember(builder, folder, built, sources, before)
    return built


def run_fmu_names(scenario: "Scenario") -> tuple[str, ...]:
    """The FMUs a scenario's run steps: Vehicle and VirtualTarget, and Link when it has links."""
    from fmus.builders import FMU_NAMES, LINK_FMU

    return FMU_NAMES + ((LINK_FMU,) if any(spec.fmu == LINK_FMU for spec in scenario.components) else ())


def prepare_fmus(fmu_dir: Path) -> None:
    """Build every kind a run may pick (pythonfmu always, native where a compiler is present), so that
    parallel runs (a sweep's workers) only check that they are current."""
    from fmus.builders import FMU_NAMES, LINK_FMU

    for kind in FMU_KINDS:
        if kind == "python" or native_buildable():
            ensure_fmus(fmu_dir, kind, FMU_NAMES + (LINK_FMU,))


def fmu_files(fmu_dir: Path) -> list[Path]:
    """Every FMU a run (or an SSP export) may read below ``fmu_dir``, of both kinds, and the fmus package's
    sources it builds them from: the inputs its output must never replace (support/output.py)."""
    from fmus.builders import FMU_NAMES, LINK_FMU, LIVE_FMU, REMOTE_FMU
    from fmus.builders.base import source_files

    names = (*FMU_NAMES, LINK_FMU, LIVE_FMU, REMOTE_FMU)
    return [fmu_folder(fmu_dir, kind) / f"{name}.fmu" for kind in FMU_KINDS for name in names] + list(source_files())


def fmus_in_folder(folder: Path) -> dict[str, Path]:
    """The run's FMUs (Vehicle, VirtualTarget) in ``folder``, built there if stale: native ones when the
    folder is a ``fmu_folder(..., "native")``, pythonfmu ones otherwise. For tools handed one folder
    (the benchmarks' child processes)."""
    from fmus.builders import FMU_NAMES

    folder = Path(folder)
    if folder.name == NATIVE_SUBFOLDER:
        return ensure_fmus(folder.parent, "native", FMU_NAMES)
    return ensure_fmus(folder, "python", FMU_NAMES)
