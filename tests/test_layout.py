"""The architecture's import rules, as the README's Layout section states them.

* bridge/ depends on the science (fmus.model) and on the orchestrator's interface only: never on the
  master, the trace or FMPy, so the robot side can change without touching the co-simulation.
* orchestrator/trace/ is one package without an import circle inside it.
* no module imports another module's private (underscored) name: what two modules share is public.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def imported_modules(path: Path, package: str) -> set[str]:
    """Absolute names of the modules a file imports (relative imports resolved against ``package``)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
    return names


def bridge_import_violations(root: Path) -> list[str]:
    """What a file of ``root``/bridge (its subpackages too: bridge/ros2/) imports that the bridge may not:
    of the project only fmus.model, fmus.component and fmus.realtime (the wall-clock pacing and the paced threads'
    real-time priority, which the emulated robot shares with the live vehicle: scheduling, nothing of FMI), and
    nothing of FMPy, pythonfmu or the MCAP library."""
    found = []
    for path in sorted((root / "bridge").rglob("*.py")):
        package = ".".join(path.relative_to(root).parent.parts)  # relative imports resolve against it
        for name in sorted(imported_modules(path, package)):
            top = name.split(".")[0]
            if (top in ("fmus", "orchestrator") and not name.startswith(("fmus.model", "fmus.component", "fmus.realtime"))) or \
                    top in ("fmpy", "pythonfmu", "mcap"):
                found.append(f"{path.relative_to(root)} imports {name}")
    return found


def test_bridge_imports_only_the_model_and_the_component_interface() -> None:
    assert (REPO / "bridge" / "ros2" / "link.py").is_file()  # the walk must reach the subpackages
    assert bridge_import_violations(REPO) == []


def test_the_bridge_import_rule_sees_into_subpackages(tmp_path: Path) -> None:
    """A bad import in bridge/ros2/ is found, as in bridge/; relative imports inside the bridge are fine."""
    ros2 = tmp_path / "bridge" / "ros2"
    ros2.mkdir(parents=True)
    (ros2 / "__init__.py").write_text("")
    (ros2 / "fine.py").write_text("from fmus.model.dynamics import M3piDynamics\nfrom ..protocol import Pose\n")
    (ros2 / "bad.py").write_text("import mcap\nfrom orchestrator.trace import load\n")
    assert bridge_import_violations(tmp_path) == [
        "bridge/ros2/bad.py imports mcap", "bridge/ros2/bad.py imports orchestrator.trace",
        "bridge/ros2/bad.py imports orchestrator.trace.load"]


def test_the_trace_package_has_no_import_circle() -> None:
    folder = REPO / "orchestrator" / "trace"
    modules = {path.stem for path in folder.glob("*.py") if path.stem != "__init__"}
    graph = {
        module: {name.split(".")[2] for name in imported_modules(folder / f"{module}.py", "orchestrator.trace")
                 if name.startswith("orchestrator.trace.") and name.split(".")[2] in modules}
        for module in modules
    }
    done: set[str] = set()

    def visit(module: str, path: tuple[str, ...]) -> None:
        assert module not in path, "import circle: " + " -> ".join((*path, module))
        if module in done:
            return
        for imported in graph[module]:
            visit(imported, (*path, module))
        done.add(module)

    for module in sorted(graph):
        visit(module, ())
    assert graph["format"] == set(), "format is the bottom of the package"


def test_every_fmu_carries_the_project_modules_its_slave_imports() -> None:
    """An FMU runs on the code in its resources (a host need not have this project installed): every
    project module its slave imports, directly or through other project modules, is bundled."""
    from fmus.builders import ALL_FMUS, bundled_sources

    def module_file(name: str) -> Path | None:
        for candidate in (REPO / Path(*name.split(".")).with_suffix(".py"), REPO / Path(*name.split(".")) / "__init__.py"):
            if candidate.is_file():
                return candidate
        return None

    for fmu in ALL_FMUS:
        bundled = {path.resolve() for path in bundled_sources(fmu)}
        pending, seen = [REPO / "fmus" / "slaves" / f"{fmu}.py"], set()
        while pending:
            path = pending.pop()
            if path in seen:
                continue
            seen.add(path)
            assert path.resolve() in bundled, f"{fmu}.fmu does not carry {path.relative_to(REPO)}"
            package = ".".join(path.relative_to(REPO).with_suffix("").parts[:-1])
            for name in imported_modules(path, package):
                if name.split(".")[0] in ("fmus", "bridge", "orchestrator"):
                    parts = name.split(".")
                    pending += [found for found in (module_file(".".join(parts[:k])) for k in range(1, len(parts) + 1))
                                if found is not None]


# --- the house (docs/architecture.md): layers without circles, the CLI on top, short functions ---------

PACKAGES = ("fmus", "orchestrator", "bridge", "benchmarks")  # benchmarks/: beside the package, not installed
LONGEST_FUNCTION = 80  # lines, in orchestrator/, bridge/ and benchmarks/


def project_modules() -> dict[str, Path]:
    """Every module of the packages by dotted name (a package by its ``__init__``)."""
    modules = {}
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


def import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports, deferred imports (inside functions) included; a module
    importing from its own package's ``__init__`` is not an edge (Python runs that ``__init__`` first anyway)."""
    modules = project_modules()

    def owner(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        targets = {owner(name) for name in imported_modules(path, package)}
        graph[module] = {t for t in targets if t and t != module
                         and not (modules[t].name == "__init__.py" and module.startswith(t + "."))}
    return graph


def test_no_import_circle_anywhere_in_the_packages() -> None:
    graph = import_graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: tuple[str, ...]) -> None:
        assert state.get(module) != 1, "import circle: " + " -> ".join((*path[path.index(module):], module))
        if state.get(module) == 2:
            return
        state[module] = 1
        for imported in sorted(graph[module]):
            visit(imported, (*path, module))
        state[module] = 2

    for module in sorted(graph):
        visit(module, ())


def test_only_the_command_line_imports_the_command_line() -> None:
    offenders = [(module, imported) for module, imports in import_graph().items() for imported in imports
                 if imported.startswith("orchestrator.cli") and not module.startswith("orchestrator.cli")
                 and module != "orchestrator.__main__"]
    assert offenders == []


def test_the_fmus_never_import_the_orchestrator() -> None:
    """The science and the component interface are the bottom layer (the LiveVehicle FMU carries them)."""
    offenders = [(module, imported) for module, imports in import_graph().items() if module.startswith("fmus")
                 for imported in imports if imported.startswith("orchestrator")]
    assert offenders == []


def test_no_function_in_the_orchestrator_the_bridge_or_the_benchmarks_is_longer_than_80_lines() -> None:
    long = []
    for package in ("orchestrator", "bridge", "benchmarks"):
        for path in (REPO / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > LONGEST_FUNCTION:
                        long.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name} ({lines} lines)")
    assert long == []


def test_every_engine_is_one_module_behind_the_engine_protocol() -> None:
    """Adding an engine is adding one file to orchestrator/execution/engines (orchestrator/execution/engine.py)."""
    from orchestrator.execution.engine import engine_class, engine_names

    assert set(engine_names()) == {"monolithic", "native", "python"}
    for name in engine_names():
        engine = engine_class(name)
        assert engine.name == name
        for method in ("start", "advance", "close"):
            assert callable(getattr(engine, method)), f"{name} engine has no {method}"


# a module's private names (a leading underscore) are its own: a second module that needs one gets it made
# public where it lives (one implementation, named as shared). Known exceptions, each to be made public:
PRIVATE_IMPORTS_LEFT: set[tuple[str, str]] = set()  # none left


def compiled_modules() -> set[str]:
    """The compiled modules setup.py builds (``Extension("orchestrator.trace._native", ...)``)."""
    import re

    return set(re.findall(r'Extension\(\s*"([\w.]+)"', (REPO / "setup.py").read_text()))


def _source_folder(path: Path, node: ast.ImportFrom) -> Path:
    """The folder of the package an ``ImportFrom`` names (relative imports resolved against ``path``)."""
    if node.level:
        base = path.parent
        for _ in range(node.level - 1):
            base = base.parent
        return base.joinpath(*(node.module.split(".") if node.module else []))
    return REPO.joinpath(*(node.module or "").split("."))


def test_no_module_imports_a_private_name_of_another() -> None:
    """E.g. ``platoon stability-map`` reads a sweep's folder with orchestrator/sweep/results.py's public
    helpers, as ``sweep-plot`` does, not with plot.py's private ones. A private *module* (a compiled
    extension such as ``_core``) may be imported: it is a file of its own."""
    offenders, compiled = [], compiled_modules()
    for package in ("orchestrator", "bridge", "fmus"):
        for path in (REPO / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, ast.ImportFrom):
                    continue
                folder = _source_folder(path, node)
                for alias in node.names:
                    name = alias.name
                    module = ".".join((*folder.relative_to(REPO).parts, name))
                    if not name.startswith("_") or name.startswith("__") or (folder / name).is_dir() or module in compiled:
                        continue
                    where = str(path.relative_to(REPO))
                    if (where, name) not in PRIVATE_IMPORTS_LEFT:
                        offenders.append(f"{where}:{node.lineno} imports {name} from {node.module or '.'}")
    assert offenders == []
