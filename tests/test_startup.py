"""What `platoon run` loads before its first step (docs/performance.md "Whole runs").

Start-up was ~0.5 s against libcosim's ~0.25 s; part of it were libraries a run never needed. These
tests keep them out: a run imports no plotting, sweep or analysis code, and the 3D scene's colours of
a large platoon are matplotlib's viridis without importing matplotlib.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.trace.foxglove import PALETTE, vehicle_colors

REPO = Path(__file__).resolve().parents[1]

# What a run must not import (module names, or package prefixes ending in "."): plotting, dataframes,
# the Dask cluster, the sweep runner, the analysis, the figure code, the trace reader (a run
# accumulates its summary while stepping; it reads its trace only when the run ended early), and FMPy
# (the native engine steps the FMUs itself; their cached model description needs no FMPy)
NOT_FOR_A_RUN = ("matplotlib.", "PIL.", "dask.", "distributed.", "pandas.", "scipy.", "zenoh.", "fmpy.", "lxml.",
                 "orchestrator.analysis.linear", "orchestrator.analysis.plots", "orchestrator.analysis.figure", "orchestrator.sweep.runner",
                 "orchestrator.sweep.executors", "orchestrator.trace.reader", "mcap.reader", "rich.progress",
                 "rich.table")

_PROBE = """
import gc, json, sys
full = []
gc.callbacks.append(lambda phase, info: full.append(1) if phase == "stop" and info["generation"] == 2 else None)
from orchestrator.cli.launch import plain_report_options, plain_run_options
sys.argv = ["platoon", *sys.argv[1:]]
options = plain_run_options(sys.argv[1:])  # what the console script does (launch.main), without its os._exit
try:
    if options is None and (report := plain_report_options(sys.argv[1:])) is not None:
        from orchestrator.cli.reporting import report_command

        report_command(**report)
    elif options is None:
        from orchestrator.cli.app import app

        app()
    else:
        from orchestrator.support.startup import loading_a_run

        with loading_a_run():
            from orchestrator.cli.running import run_command

        run_command(options)
    code = 0
except SystemExit as done:
    code = done.code
names = sorted(sys.modules)
import os
threads = len(os.listdir("/proc/self/task"))  # the run's own: inline trace writer, no pool of any kind
print("MODULES " + json.dumps({"code": code, "modules": names, "threads": threads,
                               "blas": os.environ.get("OPENBLAS_NUM_THREADS"), "full_collections": len(full)}))
"""


def probe(*args: str, cwd: Path, env: dict[str, str] | None = None, drop: tuple[str, ...] = ()) -> dict:
    """A `platoon` command run in a fresh interpreter: {code, modules it loaded, threads at its end, blas}."""
    environment = {key: value for key, value in os.environ.items() if key not in drop}
    environment.update({"PYTHONPATH": str(REPO), "NO_COLOR": "1", "TERM": "dumb", **(env or {})})
    result = subprocess.run([sys.executable, "-c", _PROBE, *args], cwd=cwd, env=environment, capture_output=True,
                            text=True, timeout=120)
    line = next((line for line in result.stdout.splitlines() if line.startswith("MODULES ")), None)
    assert line is not None, result.stdout + result.stderr
    found = json.loads(line[len("MODULES "):])
    assert found["code"] in (0, None), result.stdout + result.stderr
    return found


def imported_by(*args: str, cwd: Path) -> list[str]:
    """The modules a `platoon` command loaded, in a fresh interpreter."""
    return probe(*args, cwd=cwd)["modules"]


def unwanted(modules: list[str]) -> list[str]:
    return [name for name in modules
            if any(name == banned or name.startswith(banned) or name + "." == banned for banned in NOT_FOR_A_RUN)]


def test_a_quiet_run_of_a_large_platoon_imports_nothing_it_does_not_need(tmp_path: Path, fmu_dir: Path) -> None:
    # 12 vehicles: more than the 10-colour palette, so the scene's colours come from viridis
    modules = imported_by("run", str(REPO / "configs" / "paper" / "platoon.toml"), "--set", "platoon.count=12",
                          "--set", "simulation.stop_time=0.2", "-q", "--trace-every", "10",
                          "--out", str(tmp_path / "t.mcap"), cwd=REPO)
    assert "orchestrator.execution.run" in modules and "orchestrator.execution.native" in modules  # it did run
    assert unwanted(modules) == []
    # numpy was a quarter of start-up: the native engine's blocks reach the trace worker as bytes
    # (orchestrator/support/rows.py); what computes on rows imports it: the summary table, a live view; the
    # watch that says when a run leaves the model, which every run has, checks a short run's rows that are
    # plainly inside in plain Python (orchestrator/observers/validity.py)
    assert "orchestrator.observers.validity" in modules
    assert "numpy" not in modules


def quiet_run(tmp_path: Path) -> list[str]:
    return ["run", str(REPO / "configs" / "paper" / "platoon.toml"), "--set", "simulation.stop_time=0.2", "-q",
            "--trace-every", "10", "--out", str(tmp_path / "t.mcap")]


def table_run(tmp_path: Path) -> list[str]:
    return [argument for argument in quiet_run(tmp_path) if argument != "-q"]


def test_a_run_starts_no_blas_threads(tmp_path: Path, fmu_dir: Path) -> None:
    """numpy's OpenBLAS would start a thread per core at import; a run does no linear algebra (a run
    that prints its table imports numpy for the running summary)."""
    found = probe(*table_run(tmp_path), cwd=REPO, drop=("OPENBLAS_NUM_THREADS",))
    assert "numpy" in found["modules"]
    assert found["blas"] == "1" and found["threads"] == 1, found


def test_a_run_makes_no_full_garbage_collection(tmp_path: Path, fmu_dir: Path) -> None:
    """Start-up objects live as long as the process: loading them must not cost full collections
    (orchestrator/support/startup.py, loading_a_run)."""
    assert probe(*quiet_run(tmp_path), cwd=REPO)["full_collections"] == 0


def test_a_users_blas_setting_is_kept(tmp_path: Path, fmu_dir: Path) -> None:
    """A run that prints its table imports numpy (the running summary): with the user's BLAS threads."""
    found = probe(*table_run(tmp_path), cwd=REPO, env={"OPENBLAS_NUM_THREADS": "2"})
    assert "numpy" in found["modules"]
    assert found["blas"] == "2" and found["threads"] == 2, found


def test_a_plain_run_loads_neither_typer_nor_rich(tmp_path: Path, fmu_dir: Path) -> None:
    """`platoon run -q` parses its command line without typer and prints its lines without rich
    (orchestrator/cli/launch.py): ~0.1 s of start-up (docs/performance.md, "Start-up")."""
    modules = imported_by(*quiet_run(tmp_path), cwd=REPO)
    assert "orchestrator.execution.run" in modules  # it did run
    assert [name for name in modules if name.split(".")[0] in ("typer", "rich", "click")] == []
    assert "orchestrator.cli.app" not in modules


def test_a_run_and_a_report_of_a_config_seen_before_load_no_pydantic(tmp_path: Path, fmu_dir: Path) -> None:
    """pydantic and the config models were half of a short run's start-up: a config validated before comes back
    from the cache of validated configs (orchestrator/scenario/config_records.py; tests/test_config_cache.py holds
    it to the models). The first run and report validate, and load pydantic; the second ones do not."""
    cache = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    runs = [probe(*quiet_run(tmp_path), "--overwrite", cwd=REPO, env=cache)["modules"] for _ in range(2)]
    assert "pydantic" in runs[0] and "orchestrator.execution.run" in runs[1]
    assert [name for name in runs[1] if name.split(".")[0] in ("pydantic", "pydantic_core")] == []
    assert "orchestrator.scenario.config" not in runs[1]
    reports = [probe("report", str(tmp_path / "t.mcap"), cwd=REPO, env=cache)["modules"] for _ in range(2)]
    assert "pydantic" in reports[0] and "orchestrator.analysis.metrics" in reports[1]
    assert [name for name in reports[1] if name.split(".")[0] in ("pydantic", "pydantic_core")] == []


def test_a_report_of_a_run_that_stored_its_summary_loads_neither_numpy_nor_the_reader(tmp_path: Path,
                                                                                       fmu_dir: Path) -> None:
    """A run that prints its table stores it in the trace (orchestrator/analysis/stored_summary.py): its report
    prints it without numpy, the trace reader or the analysis (tests/test_stored_summary.py: the same text)."""
    cache = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    probe(*table_run(tmp_path), "--overwrite", cwd=REPO, env=cache)
    for _ in range(2):  # the second: its config from the cache of validated configs, without pydantic
        modules = probe("report", str(tmp_path / "t.mcap"), cwd=REPO, env=cache)["modules"]
    unwanted = ("numpy", "orchestrator.trace.reader", "orchestrator.trace.columns", "orchestrator.analysis.metrics",
                "pydantic")
    assert [name for name in modules if name.split(".")[0] in unwanted or name in unwanted] == []


def test_a_second_run_checks_no_fmu_and_reads_no_package_metadata(tmp_path: Path, fmu_dir: Path) -> None:
    """The FMUs' check (GUID digests, archive CRCs) and the installed versions a trace records are kept under the
    cache folder (orchestrator/components/fmu_checks.py, orchestrator/support/versions.py): a second run imports
    no importlib.metadata (email and its parsers). Run from a folder of its own, which the run does not write:
    the versions are kept with the time of every folder of sys.path, the current folder among them."""
    cache = {"XDG_CACHE_HOME": str(tmp_path / "cache")}
    here = tmp_path / "here"
    here.mkdir()
    runs = [probe(*quiet_run(tmp_path), "--overwrite", cwd=here, env=cache)["modules"] for _ in range(2)]
    assert "importlib.metadata" in runs[0] and "orchestrator.execution.run" in runs[1]
    assert "importlib.metadata" not in runs[1]


def test_the_cli_alone_imports_none_of_it(tmp_path: Path) -> None:
    modules = imported_by("--version", cwd=tmp_path)
    assert unwanted(modules) == []


@pytest.mark.parametrize("count", [*range(11, 40), 64, 100, 255, 256, 257, 1000])
def test_large_platoons_get_matplotlibs_viridis(count: int) -> None:
    from matplotlib import colormaps

    scale = colormaps["viridis"]
    expected = [tuple(float(c) for c in scale(i / (count - 1))[:3]) for i in range(count)]
    assert vehicle_colors(count) == expected


def test_small_platoons_keep_the_palette() -> None:
    assert vehicle_colors(len(PALETTE)) == PALETTE and vehicle_colors(3) == PALETTE[:3]


def test_the_fmi_platform_is_fmpys() -> None:
    """fmus.platforms names this machine's binaries folders (FMI 2.0 and 3.0) without importing FMPy;
    FMPy's names rule."""
    import fmpy

    from fmus.platforms import fmi_platform, host_platform

    assert fmi_platform() == (fmpy.platform, fmpy.sharedLibraryExtension)
    assert host_platform().directory(3) == fmpy.platform_tuple


def test_a_run_whose_trace_a_worker_writes_loads_no_mcap_writer(tmp_path: Path, fmu_dir: Path) -> None:
    """With the trace encoded in the worker process, the stepping process imports neither the MCAP
    writer (mcap, zstandard, lz4) nor the Foxglove SDK: they are the worker's (a run's start-up
    counts every import)."""
    modules = imported_by(*quiet_run(tmp_path), "--trace-writer", "process", cwd=REPO)
    assert "orchestrator.trace.worker" in modules  # the worker did write it
    assert [name for name in modules if name.split(".")[0] in ("mcap", "zstandard", "lz4", "foxglove")
            or name == "orchestrator.trace.writer"] == []
    assert (tmp_path / "t.mcap").stat().st_size > 0
