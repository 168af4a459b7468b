"""Run an SSP package in libcosim (libcosimpy), as another tool would:
``python ssp_libcosim.py PACKAGE [--isolate] [--tail K]``.

Steps the package's DefaultExperiment with its fixed step (from the .ssd), then prints one line per
component ``NAME X Y`` (final position), ``end T`` (the time reached), with ``--tail K`` the positions
after each of the last K steps (``sample NAME T X Y``) and, with ``--isolate``, where
the FMUs found our packages (``module NAME PATH``). ``--isolate`` first removes this project's packages
from the host's import machinery (they are then found only in an FMU's resources folder), so the
FMUs must bring their own code. libcosim's log (FMU messages included) goes to standard output.
Exit status 1 when a step fails.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import os
import sys
import zipfile
from xml.etree import ElementTree

OUR_PACKAGES = ("fmus", "bridge", "orchestrator")
NS = {"ssd": "http://ssp-standard.org/SSP1/SystemStructureDescription",
      "ssc": "http://ssp-standard.org/SSP1/SystemStructureCommon",
      "osp": "http://opensimulationplatform.com/SSP/OSPAnnotations"}


class OnlyFromFmuResources(importlib.abc.MetaPathFinder):
    """Finds this project's top-level packages only in an FMU's ``resources`` folder on sys.path (where
    pythonfmu puts it), whichever way the project is installed in this environment."""

    def find_spec(self, fullname, path, target=None):
        if fullname not in OUR_PACKAGES:
            return None
        folders = [entry for entry in sys.path if os.path.basename(os.path.normpath(entry or ".")) == "resources"]
        spec = importlib.machinery.PathFinder.find_spec(fullname, folders)
        if spec is None:
            raise ModuleNotFoundError(f"No module named {fullname!r} (ssp_libcosim.py --isolate: only from an FMU)",
                                      name=fullname)
        return spec


def isolate() -> None:
    """Make ``import fmus`` (bridge, orchestrator) fail in this process unless an FMU provides it."""
    sys.meta_path[:] = [OnlyFromFmuResources()] + [finder for finder in sys.meta_path
                                                   if "editable" not in repr(finder).lower()]
    repository = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sys.path[:] = [entry for entry in sys.path
                   if os.path.abspath(entry or ".") not in (repository, os.path.dirname(os.path.abspath(__file__)))]
    for name in OUR_PACKAGES:
        try:
            __import__(name)
        except ImportError:
            continue
        raise SystemExit(f"--isolate: {name} is still importable from {sys.modules[name].__file__}")


def experiment(package: str) -> tuple[float, float]:
    """(stop time, step) in seconds from the package's .ssd."""
    with zipfile.ZipFile(package) as archive:
        root = ElementTree.fromstring(archive.read("SystemStructure.ssd"))
    default = root.find("ssd:DefaultExperiment", NS)
    algorithm = default.find("ssd:Annotations/ssc:Annotation/osp:Algorithm/osp:FixedStepAlgorithm", NS)
    return float(default.get("stopTime")), float(algorithm.get("baseStepSize"))


def main() -> int:
    package = os.path.abspath(sys.argv[1])
    if "--isolate" in sys.argv[2:]:
        isolate()
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver

    log_output_level(CosimLogLevel.INFO if "--isolate" in sys.argv[2:] else CosimLogLevel.WARNING)
    stop_time, step = experiment(package)
    execution = CosimExecution.from_ssp_file(package)
    last = CosimObserver.create_last_value()
    assert execution.add_observer(last)
    steps = round(stop_time / step)
    tail = int(sys.argv[sys.argv.index("--tail") + 1]) if "--tail" in sys.argv else 0
    positions = {}  # name -> (slave index, [reference of x, reference of y])
    for info in execution.slave_infos():
        references = {v.name.decode(): v.reference for v in execution.slave_variables(info.index)}
        positions[info.name.decode()] = (info.index, [references["x"], references["y"]])
    ok = execution.step(steps - tail)
    samples = []
    for _ in range(tail):
        if not ok:
            break
        ok = execution.step(1)
        now = execution.status().current_time / 1e9
        samples += [(name, now, *last.last_real_values(index, refs)) for name, (index, refs) in positions.items()]
    sys.stdout.flush()
    for name, (index, refs) in positions.items():
        x, y = last.last_real_values(index, refs)
        print(name, repr(x), repr(y))
    for sample in samples:
        print("sample", *map(str, sample))
    print("end", execution.status().current_time / 1e9)
    for name in OUR_PACKAGES:
        if name in sys.modules:
            print("module", name, sys.modules[name].__file__)
    print("steps", "completed" if ok else "failed")
    return 0 if ok else 1


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # no interpreter teardown after pythonfmu FMUs ran (see tests/conftest.py)
