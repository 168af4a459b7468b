"""``platoon export-ssp``: a config's whole platoon as an SSP 1.0 package for other tools (docs/fmus.md,
"Run the whole platoon in another tool"). Registered by ``register``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer


def export_ssp(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, e.g. configs/paper/platoon.toml")],
    out: Annotated[Optional[Path], typer.Option("--out", help="the package to write (default: <config name>.ssp here)")] = None,
    overrides: Annotated[list[str], typer.Option("--set", metavar="KEY=VALUE", help="override a key, as for platoon run")] = [],
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing --out that is not an SSP package (never an input, a FIFO, a device or a folder)")] = False,
    force: Annotated[bool, typer.Option("--force", hidden=True, help="deprecated alias of --overwrite")] = False,
    fmu_kind: Annotated[Optional[str], typer.Option("--fmus", metavar="<native|python>", help="native (C FMUs: no Python needed where the package runs; default where a C compiler can build them) or python (pythonfmu); overrides simulation.fmus")] = None,
    worker_threads: Annotated[int, typer.Option("--worker-threads", min=0, help="libcosim's numWorkerThreads; 0 steps every FMU on the calling thread (pythonfmu FMUs share one Python interpreter, so more threads only add synchronization)")] = 0,
) -> None:
    """Write the platoon of CONFIG as an SSP 1.0 package: FMUs, parameters, Fig. 2 wiring, step."""
    from fmus.builders import DEFAULT_OUT

    from orchestrator.cli.common import fail, load_config, err, out as console, output_rule
    from orchestrator.support.output import check_target
    from orchestrator.interop.ssp import SspError, export_ssp as write_package, SSP, ssp_notes

    from orchestrator.cli.common import check_choice
    from orchestrator.cli.plain import run_inputs
    from orchestrator.components.kinds import FMU_KINDS, FmuKindError

    check_choice("--fmus", fmu_kind, FMU_KINDS)
    if fmu_kind is not None:
        overrides = [*overrides, f"simulation.fmus={json.dumps(fmu_kind)}"]
    parsed, _ = load_config(config, overrides)
    target = out if out is not None else Path(f"{parsed.name}.ssp")
    if force:  # kept so old scripts work (docs/fmus.md); it means exactly --overwrite
        err.print("note: --force is deprecated; it means --overwrite", highlight=False, soft_wrap=True, markup=False)
    overwrite = overwrite or force
    with output_rule():  # the output rule (support/output.py), checked before any FMU is built
        check_target(target, overwrite, run_inputs(config, parsed), kind=SSP)  # the FMUs it packs too
    try:
        with output_rule():
            written = write_package(parsed, target, DEFAULT_OUT, force=overwrite, worker_threads=worker_threads)
    except (SspError, FmuKindError) as error:
        fail(2, f"config {config}: {error}")
    for note in ssp_notes(parsed):
        err.print(f"note: {note}", highlight=False, soft_wrap=True, markup=False)
    live = ", ".join(f"vehicle{k}" for k in parsed.live_vehicles())
    remote = ", ".join(f"vehicle{k}" for k in parsed.remote_vehicles())
    console.print(f"{written}: {parsed.platoon.count + 1 + len(parsed.linked())} components, step {parsed.simulation.step:g} s, stop "
                  f"{parsed.simulation.stop_time:g} s" + (f"; live robot: {live} (LiveVehicle.fmu)" if live else "")
                  + (f"; remote: {remote} (RemoteVehicle.fmu: start their platoon serve first)" if remote else ""),
                  highlight=False, soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    """Add ``export-ssp`` to ``platoon``."""
    app.command("export-ssp")(export_ssp)
