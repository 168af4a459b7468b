"""A user's script that runs an exported SSP package with a live robot in it, and ends the ordinary way
(no ``os._exit``): ``python live_fmu_host.py PACKAGE {libcosim,fmpy} {free,keep}``.

``libcosim``: libcosimpy steps the package's DefaultExperiment; ``free`` then deletes the execution
(libcosim terminates and frees every instance), ``keep`` leaves it to the interpreter's teardown.
``fmpy``: ``orchestrator.interop.fmpy_ssp.simulate_ssp`` (the runner docs/fmus.md gives FMPy users), which
terminates and frees every instance at its end (``free``); ``keep`` makes it leave them all alive, as a
script of its own that never frees would.

Prints ``threads NAME...`` (the interpreter's threads) after the run and again after the free, ``freed``
once the instances are freed, ``end`` when the script is done, and ``joined`` from an ``atexit`` handler:
the interpreter's shutdown calls those only once it has joined every non-daemon thread (where a live FMU
that held its threads kept it waiting). tests/test_live_fmu.py measures from ``end`` to both.
"""

from __future__ import annotations

import atexit
import sys
import threading
import zipfile
from xml.etree import ElementTree

SSD = "{http://ssp-standard.org/SSP1/SystemStructureDescription}"


def threads() -> None:
    print("threads", *sorted(thread.name for thread in threading.enumerate()), flush=True)


def stop_time(package: str) -> float:
    with zipfile.ZipFile(package) as archive:
        return float(ElementTree.fromstring(archive.read("SystemStructure.ssd")).find(f"{SSD}DefaultExperiment")
                     .get("stopTime"))


def run_libcosim(package: str, free: bool) -> bool:
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level

    log_output_level(CosimLogLevel.WARNING)
    global execution  # a user's script keeps it in a global: collected only in the interpreter's teardown
    execution = CosimExecution.from_ssp_file(package)
    ok = execution.simulate_until(round(stop_time(package) * 1e9))
    threads()
    if free:
        del execution
        print("freed", flush=True)
        threads()
    return ok


def run_fmpy(package: str, free: bool) -> bool:
    import fmpy.ssp.simulation

    from orchestrator.interop.fmpy_ssp import simulate_ssp

    if not free:
        fmpy.ssp.simulation.free_fmu = lambda component: None  # neither fmi2Terminate nor fmi2FreeInstance
    result = simulate_ssp(package, stop_time=stop_time(package), step_size=0.01)
    threads()
    if free:
        print("freed", flush=True)
    return len(result) > 0


if __name__ == "__main__":
    atexit.register(print, "joined", flush=True)  # the first registered: called last, after the FMUs' own
    package, host, mode = sys.argv[1:4]
    completed = (run_libcosim if host == "libcosim" else run_fmpy)(package, mode == "free")
    print("steps", "completed" if completed else "failed", flush=True)
    print("end", flush=True)
