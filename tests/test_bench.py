"""``platoon bench`` works end to end: tiny runs write their JSON, bad options exit 2 with one line;
the benchmarks run as ``python -m benchmarks.<name>`` start (``--help``) from any folder.

Functional checks only, on runs a few steps long: what the benchmarks measure is reported by
``platoon bench`` itself (docs/performance.md), never asserted here, since timing on a shared machine
is no pass/fail criterion.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.test_cli import REPO, error_line, platoon

SINGLE = REPO / "configs" / "paper" / "single.toml"
# the benchmarks with a command line of their own (the others are ``platoon bench`` suites)
MODULES = ("coupling_accuracy", "equilibrium_growth", "fmu_step_cost", "paper_scenarios", "trace_encoder",
           "trace_memory", "trace_overhead")


def installed_core() -> str:
    """The built native core, to stand for both sides of an A/B comparison of _core builds."""
    from orchestrator.execution.native import _core

    return _core.__file__


def written(result, folder: Path, suite: str) -> dict:
    """The one JSON file the suite wrote into ``folder``, which the output names."""
    assert result.returncode == 0, result.stderr
    files = sorted(folder.glob(f"{suite}-*.json"))
    assert len(files) == 1, files
    assert f"results: {files[0]}" in result.stdout.replace("\n", "")
    data = json.loads(files[0].read_text())
    assert data["suite"] == suite and data["command"].startswith(f"platoon bench {suite}")
    assert {"versions", "machine"} <= set(data)
    return data


def test_steps_writes_medians_and_ratios(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "steps", "--engines", "native,python,slaves", "--n", "1,2", "--steps", "5",
                     "--rounds", "1", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "steps")
    # both FMU kinds in the same rounds (the slave classes have no native twin)
    assert set(data["medians"]) == {"native", "python", "slaves", "native + native FMUs", "python + native FMUs"}
    assert all(set(by_n) == {"1", "2"} and min(by_n.values()) > 0 for by_n in data["medians"].values())
    assert len(data["samples"]) == 10 and {s["steps"] for s in data["samples"]} == {5}
    assert data["disagreeing"] == {}  # every engine and FMU kind simulated the same system
    assert "native / slaves" in result.stdout and "| (a) native engine, tracing off |" in result.stdout
    assert "native engine: native FMUs / pythonfmu FMUs" in result.stdout


def test_steps_measures_one_fmu_kind_on_request(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "steps", "--engines", "native", "--fmus", "native", "--n", "1", "--steps", "5",
                     "--rounds", "1", "--out-dir", tmp_path, "-q", cwd=REPO)
    data = written(result, tmp_path, "steps")
    assert set(data["medians"]) == {"native + native FMUs"} and data["fmu_kinds"] == ["native"]
    bad = platoon("bench", "steps", "--fmus", "java", "--out-dir", tmp_path, cwd=REPO)
    assert bad.returncode == 2 and "--fmus" in bad.stderr


def test_coupling_measures_both_couplings(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "coupling", "--engines", "native", "--n", "1", "--steps", "5", "--rounds", "1",
                     "--out-dir", tmp_path, "-q", cwd=REPO)
    data = written(result, tmp_path, "coupling")
    assert {s["coupling"] for s in data["samples"]} == {"hold", "extrapolate"}
    assert data["hold_over_extrapolate"]["native"]["1"] > 0
    assert result.stderr == ""  # --quiet: no progress lines


def test_instances_reports_per_vehicle_slope(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "instances", "--engines", "native", "--wirings", "instances", "--n", "1,3",
                     "--rounds", "1", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "instances")
    fit = data["per_vehicle_slope"]["instances"]["native"]
    assert {"ms_per_vehicle", "kib_per_vehicle"} <= set(fit)
    assert [s["instances"] for s in data["samples"]] == [2, 4]


def test_scenarios_times_whole_processes(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "scenarios", "--config", SINGLE, "--set", "simulation.stop_time=0.05",
                     "--engines", "native", "--variants", "cli-traced,untraced", "--rounds", "1",
                     "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "scenarios")
    by_variant = {s["variant"]: s for s in data["samples"]}
    assert set(by_variant) == {"cli-traced", "untraced"}
    assert by_variant["cli-traced"]["trace_bytes"] > 0 and by_variant["untraced"]["trace_bytes"] is None
    assert all(s["steps"] == 5 and s["wall_s"] > s["run_wall_s"] >= 0 for s in data["samples"])  # a 5-step native run prints "in 0.00 s"


def test_wholerun_times_our_runs_and_libcosim_on_the_same_system(tmp_path: Path, fmu_dir: Path) -> None:
    short = tmp_path / "short.toml"  # platoon-hour's run, made short
    short.write_text((REPO / "configs/paper/platoon.toml").read_text().replace("stop_time = 100.0", "stop_time = 0.5"))
    result = platoon("bench", "wholerun", "--n", "2", "--steps", "20", "--rounds", "1", "--out-dir", tmp_path,
                     "--variants", "platoon,platoon-q,platoon-start,libcosim,libcosim-outputs,libcosim-last-value,"
                     "libcosim-file,platoon-hour", "--hour-config", short, cwd=REPO)
    data = written(result, tmp_path, "wholerun")
    assert {s["variant"] for s in data["samples"]} == set(data["variants"]) == {
        "platoon", "platoon-q", "platoon-start", "libcosim", "libcosim-outputs", "libcosim-last-value", "libcosim-file",
        "platoon-hour"}
    assert all(s["wall_s"] > 0 and s["exit"] == 0 for s in data["samples"])
    # the hour's run (here a short config's) is measured once per round, whatever N, and reported on its own
    assert [s["n"] for s in data["samples"] if s["variant"] == "platoon-hour"] == ["platoon-hour"]
    assert data["hour"]["wall_s"] > 0 and "platoon-hour, with its trace" in result.stdout
    assert set(data["ratios"]["2"]) >= {"platoon / libcosim", "platoon / libcosim-file", "platoon-q / libcosim",
                                        "libcosim-last-value / libcosim", "libcosim-file / libcosim"}
    assert "platoon / libcosim" in result.stdout and "(target ≤ 1.50)" in result.stdout


def test_wholerun_measures_another_build_in_the_same_sitting(tmp_path: Path, fmu_dir: Path) -> None:
    """``--before PLATOON``: the before* variants run that script (here: this very build, so both sides agree)."""
    script = Path(sys.executable).parent / "platoon"
    result = platoon("bench", "wholerun", "--fmus", "native", "--variants", "platoon-start,before-start,before-q",
                     "--before", script, "--n", "2", "--steps", "20", "--rounds", "1", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "wholerun")
    assert data["before"] == str(script) and {s["variant"] for s in data["samples"]} == {
        "platoon-start", "before-start", "before-q"}
    assert "platoon-start / before-start" in data["ratios"]["2"]
    missing = platoon("bench", "wholerun", "--variants", "before", "--out-dir", tmp_path, cwd=REPO)
    assert missing.returncode == 2 and "--before" in missing.stderr
    absent = platoon("bench", "wholerun", "--before", tmp_path / "none", "--out-dir", tmp_path, cwd=REPO)
    assert absent.returncode == 2 and "no such file" in absent.stderr


def test_wholerun_times_the_start_up_against_the_interpreter_and_libcosim(tmp_path: Path, fmu_dir: Path) -> None:
    """10-step runs (ours with -v, which says when the first step began), `python -c pass` and libcosim's
    10 steps, in the same rounds: the start-up figure and its ratios."""
    result = platoon("bench", "wholerun", "--fmus", "native", "--variants", "platoon-start,platoon-first,python,libcosim-start",
                     "--n", "2", "--steps", "20", "--rounds", "1", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "wholerun")
    first = next(s for s in data["samples"] if s["variant"] == "platoon-first")
    assert 0 < first["first_step_s"] < first["wall_s"], first  # seconds from the process's start, before its end
    assert data["medians"]["2"]["platoon-first"]["first_step_s"] == first["first_step_s"]
    assert {"platoon-start / python", "platoon-start / libcosim-start", "libcosim-start / python"} <= set(data["ratios"]["2"])
    assert "start-up (10 steps)" in result.stdout and "first step" in result.stdout


def test_wholerun_runs_each_n_for_its_own_step_count(tmp_path: Path, fmu_dir: Path) -> None:
    """``--steps 20,10`` with ``--n 2,3``: each N runs its own count, ours and libcosim's alike (libcosim's
    end time is checked against it); a count per N or one for all, anything else is a usage error."""
    result = platoon("bench", "wholerun", "--fmus", "native", "--variants", "platoon-q,libcosim", "--n", "2,3",
                     "--steps", "20,10", "--rounds", "1", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "wholerun")
    assert data["steps"] == {"2": 20, "3": 10} and "20 steps at N = 2, 10 at N = 3" in result.stdout
    wrong = platoon("bench", "wholerun", "--n", "2,3", "--steps", "20,10,5", "--out-dir", tmp_path, cwd=REPO)
    assert wrong.returncode == 2 and "--steps" in wrong.stderr


def test_wholerun_compares_the_same_fmus_on_both_sides(tmp_path: Path, fmu_dir: Path) -> None:
    """Our run and libcosim's step the same kind of FMU: a native-FMU run against libcosim stepping the
    pythonfmu ones would be no comparison."""
    result = platoon("bench", "wholerun", "--fmus", "native", "--variants", "platoon,libcosim", "--n", "2", "--steps",
                     "20", "--rounds", "1", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "wholerun")
    assert data["fmus"] == "native" and "native FMUs in every variant" in result.stdout
    ssp_side = platoon("bench", "wholerun", "--fmus", "java", "--out-dir", tmp_path, cwd=REPO)
    assert ssp_side.returncode == 2 and "--fmus" in ssp_side.stderr


def test_startup_times_each_command_and_the_sweeps_cost_per_run(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "startup", "--runs", "2", "--stop-time", "0.5", "--rounds", "1", "--out-dir", tmp_path, cwd=REPO,
                     timeout=900)  # 16 whole processes, each seconds on a loaded machine
    data = written(result, tmp_path, "startup")
    medians = data["medians"]
    assert set(medians) == {"--help", "--version", "bad option", "run 10 steps", "README run", "report",
                            "run of a sweep's length", "sweep"}
    assert all(0 < m["first"] <= m["whole"] for m in medians.values())
    assert data["sweep"]["per_run"] == medians["sweep"]["whole"] / 2
    assert "first output s" in result.stdout and "1 worker" in result.stdout and len(data["load_average"]) == 2


def test_flatness_times_both_orders(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "flatness", "--n", "1,5", "--steps", "3", "--rounds", "1", "--repeats", "1",
                     "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "flatness")
    orders = data["orders"]
    assert set(orders["medians"]) == {"phases", "per-component", "idle"}  # idle: 5 of the 6 components at N = 5
    assert set(orders["medians"]["idle"]) == {"5"}
    assert orders["us_by_kind"]["5"]["Vehicle"] > 0


def test_cores_compares_builds(tmp_path: Path, fmu_dir: Path) -> None:
    core = installed_core()
    result = platoon("bench", "cores", f"a={core}", f"b={core}", "--n", "1", "--steps", "5", "--rounds", "1",
                     "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "cores")
    assert set(data["cores"]) == {"a", "b"} and [s["core_label"] for s in data["samples"]] == ["a", "b"]
    assert "| b / a (wall) |" in result.stdout


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="needs valgrind")
def test_callgrind_splits_the_master_from_the_fmus(tmp_path: Path, fmu_dir: Path) -> None:
    result = platoon("bench", "callgrind", "--n", "1", "--fmu-steps", "4", "--out-dir", tmp_path, cwd=REPO)
    data = written(result, tmp_path, "callgrind")
    [run] = data["runs"]
    assert (run["engine"], run["core_label"], run["last_level"]) == ("native", "installed", "524288,8,64")
    assert 0 < run["per_fmu_step"]["Ir_master"] < run["per_fmu_step"]["Ir"]


@pytest.mark.parametrize("args, pieces", [
    (["steps", "--engines", "native,warp"], ["--engines 'native,warp'", "fmpy-bare"]),
    (["steps", "--n", "4,x"], ["--n '4,x'", "vehicle counts"]),
    (["steps", "--n", "0"], ["--n '0'", "at least 1"]),
    (["coupling", "--engines", ""], ["--engines ''"]),
    (["instances", "--engines", "libcosim"], ["--engines 'libcosim'", "native, fmpy"]),
    (["instances", "--wirings", "ring"], ["--wirings 'ring'", "instances, platoon"]),
    (["scenarios", "--variants", "traced,fast"], ["--variants 'traced,fast'", "untraced"]),
    (["wholerun", "--variants", "platoon,libcosim-fast"], ["--variants 'platoon,libcosim-fast'", "libcosim-outputs"]),
    (["scenarios", "--config", "no/such.toml"], ["no/such.toml", "not found"]),
    (["scenarios", "--config", str(SINGLE), "--set", "platoon.count=0"], ["platoon.count"]),
    (["callgrind", "--engines", "libcosim"], ["--engines 'libcosim'", "fmpy-bare"]),
    (["callgrind", "--ll", "l3"], ["--ll 'l3'", "l2, detected"]),
    (["callgrind", "--core", "no-label"], ["LABEL=PATH", "'no-label'"]),
    (["cores", "a=no/such.so", "b=no/such.so"], ["LABEL=PATH", "'a=no/such.so'"]),
    (["cores", f"a={SINGLE}"], ["at least two"]),
])
def test_bad_options_exit_2_with_one_clear_line(args: list[str], pieces: list[str], tmp_path: Path) -> None:
    result = platoon("bench", *args, "--out-dir", tmp_path, cwd=tmp_path)
    assert result.returncode == 2, (result.stdout, result.stderr)
    line = error_line(result)
    for piece in pieces:
        assert piece in line, line
    assert not list(tmp_path.glob("*.json"))


def test_scenarios_without_configs_here_says_where_it_looked(tmp_path: Path) -> None:
    result = platoon("bench", "scenarios", "--out-dir", tmp_path, cwd=tmp_path)
    assert result.returncode == 2
    assert "configs/paper/*.toml" in error_line(result)


def test_callgrind_split_counts_each_fmu_call_once() -> None:
    """The master's own instructions are the total minus pythonfmu's SetReal / Step / GetReal, each
    counted once: not again through the std::function helpers listed under the method's name."""
    from benchmarks.flatness import inside_fmu_from_annotation

    listing = """\
107,816,428 (100.0%)  PROGRAM TOTALS
107,797,054 (99.98%) 3,980 (99.87%)  /work/main/orchestrator/native/_core.c:Core_run [/work/_core.so]
 58,513,147 (54.27%) 2,690 (67.50%)  ???:fmi2DoStep [/tmp/f/binaries/linux64/Vehicle.so]
 58,498,647 (54.26%) 2,684 (67.35%)  ???:PySlaveInstance::Step(double, double) [/tmp/f/binaries/linux64/Vehicle.so]
 58,333,147 (54.10%) 2,680 (67.25%)  ???:std::_Function_handler<void (PyGILState_STATE), PySlaveInstance::Step(double, double)::{lambda(PyGILState_STATE)#1}>::_M_invoke(std::_Any_data const&, PyGILState_STATE&&) [/tmp/f/Vehicle.so]
 31,289,665 (29.02%)   901 (22.61%)  ???:PySlaveInstance::GetReal(unsigned int const*, unsigned long, double*) const [/tmp/f/Vehicle.so]
 17,897,599 (16.60%)     .           ???:PySlaveInstance::SetReal(unsigned int const*, unsigned long, double const*) [/tmp/f/Vehicle.so]
  2,288,401 ( 2.12%)    12 ( 0.30%)  ???:PySlaveInstance::clearLogBuffer() const [/tmp/f/Vehicle.so]
     59,500 ( 0.06%)     4 ( 0.10%)  ???:std::_Function_handler<void (PyGILState_STATE), PySlaveInstance::Step(double, double)::{lambda(PyGILState_STATE)#1}>::_M_manager(std::_Any_data&, std::_Any_data const&, std::_Manager_operation) [/tmp/f/Vehicle.so]
  1,000,000 ( 0.90%)   100 ( 2.51%)  ???:PySlaveInstance::Step(double, double) [/tmp/g/binaries/linux64/VirtualTarget.so]
     .           static inline fmi2Status read_outputs(const Core *self, Instance *inst, double *into) {
31,300,165 (29.03%)  => ???:fmi2GetReal (500x)
"""
    assert inside_fmu_from_annotation(listing, ["Ir", "DLmr"]) == {
        "Ir": 58_498_647 + 31_289_665 + 17_897_599 + 1_000_000, "DLmr": 2_684 + 901 + 0 + 100}
    with pytest.raises(ValueError, match="2 columns, expected 3"):
        inside_fmu_from_annotation(listing, ["Ir", "DLmr", "DLmw"])


@pytest.mark.parametrize("module", MODULES)
def test_benchmark_modules_start_from_any_folder(module: str, tmp_path: Path) -> None:
    """Each runs as ``python -m benchmarks.<name>``, its usage naming that command: from the checkout, or from
    any folder with the checkout on PYTHONPATH (as the benchmarks start their own children)."""
    import os

    done = subprocess.run([sys.executable, "-m", f"benchmarks.{module}", "--help"], cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: python -m benchmarks.{module} ")


def test_trace_overhead_times_every_variant(fmu_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from benchmarks import trace_overhead

    monkeypatch.chdir(REPO)  # the paper's config, as a user runs it
    result = trace_overhead.run([1], steps=5, rounds=1, fmu_dir=fmu_dir)
    row = result["results"][1]
    assert [s["variant"] for s in result["samples"]] == list(trace_overhead.VARIANTS)
    assert row["off"]["ratio_to_off"] == 1.0 and row["off"]["trace_mb"] == 0.0
    assert row["inline"]["trace_mb"] > 0 and row["process"]["trace_mb"] > 0
    assert "per FMU-step, median" in trace_overhead.table(result)


def test_trace_memory_samples_rss_and_checks_the_platoon(tmp_path: Path, fmu_dir: Path) -> None:
    target = tmp_path / "memory.json"
    done = subprocess.run([sys.executable, "-m", "benchmarks.trace_memory", "--set", "platoon.count=2",
                           "--set", "simulation.stop_time=3.0", "--sample", "5", "--json", target],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    data = json.loads(target.read_text())
    assert data["suite"] == "trace-memory" and data["status"] == "completed" and data["vehicles"] == 2
    assert data["rss_max_mb"] > 0 and data["samples"]
    assert data["max_deviation_from_equilibrium"]["speed_worst_vehicle"] in {"vehicle1", "vehicle2"}


def test_paper_scenarios_refuses_a_json_target_it_must_not_replace_before_running(tmp_path: Path) -> None:
    """The output rule for ``python -m benchmarks.paper_scenarios --json``: a FIFO (opening it to
    write used to block forever, after minutes of runs) or a file that is not JSON is refused at once, in
    one line naming it, and left as it was."""
    import os
    import stat

    from tests.test_hostile_traces import one_line_error

    fifo, foreign = tmp_path / "results.json", tmp_path / "notes.json"
    os.mkfifo(fifo)
    foreign.write_text("my notes\n")
    for target, kind in ((fifo, "is a FIFO, not a regular file"), (foreign, "exists and is not a JSON file")):
        done = subprocess.run([sys.executable, "-m", "benchmarks.paper_scenarios", "--json", str(target)],
                              cwd=REPO, capture_output=True, text=True, timeout=120)
        assert done.returncode == 1, (done.stdout, done.stderr)
        one_line_error(done, f"--json {target}", kind)
        assert done.stdout == ""  # refused before the first run
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and foreign.read_text() == "my notes\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.json", "results.json"]  # no aside file left


def test_a_hil_helpers_log_is_a_new_file_never_what_is_in_its_place(tmp_path: Path) -> None:
    """``bench hil`` helpers log their stderr to a new file each (mkstemp): a FIFO where the log used to go
    (``echo.stderr``) is neither opened (which would block) nor replaced, and two helpers of one name keep
    two logs."""
    import os
    import stat

    os.mkfifo(tmp_path / "echo.stderr")
    script = ("import sys\nfrom pathlib import Path\nfrom benchmarks.hil import Helper\n"
              "child = [sys.executable, '-c', 'import sys; print(\"ready\", file=sys.stderr, flush=True); sys.stdin.read()']\n"
              "for _ in range(2):\n"
              f"    with Helper(child, 'ready', Path({str(tmp_path)!r}), 'echo') as helper:\n"
              "        print(helper.log.name)\n")
    done = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    logs = done.stdout.split()
    assert len(set(logs)) == 2 and "echo.stderr" not in logs, logs
    assert all((tmp_path / log).read_text() == "ready\n" for log in logs)
    assert stat.S_ISFIFO(os.lstat(tmp_path / "echo.stderr").st_mode)


def test_the_installed_package_holds_no_benchmark() -> None:
    """The wheel's packages are what pyproject's ``packages.find`` picks: the benchmarks are not among them
    (they stay in the checkout, benchmarks/), the package's own folders are."""
    import tomllib

    from setuptools import find_packages

    find = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    installed = find_packages(str(REPO), include=find["include"], exclude=find.get("exclude", ()))
    assert {"orchestrator", "orchestrator.cli", "fmus", "bridge"} <= set(installed)
    assert not [name for name in installed if "bench" in name.split(".")[-1] or name.startswith("benchmarks")]


def test_platoon_bench_outside_a_checkout_says_where_the_benchmarks_are(tmp_path: Path, monkeypatch, capsys) -> None:
    """An installed wheel has no benchmarks/ beside it: ``platoon bench`` says so in one line (exit 2), and
    from a checkout it finds them; the engines its help lists are the benchmarks' own."""
    import orchestrator
    from benchmarks.engines import ENGINES
    from orchestrator.cli import bench

    assert bench.BENCH_ENGINES == ENGINES
    assert bench.checkout_with_benchmarks() == REPO and bench.suite("common").DEFAULT_OUT_DIR == bench.DEFAULT_OUT_DIR
    monkeypatch.setattr(orchestrator, "__file__", str(tmp_path / "site-packages" / "orchestrator" / "__init__.py"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        bench.suite("steps")
    assert exit_.value.code == 2
    message = capsys.readouterr().err.strip()
    assert message.count("\n") == 0 and "benchmarks/" in message and "checkout" in message


def test_bench_readback_stopped_by_sigterm_ends_its_child_and_leaves_no_scratch(tmp_path: Path, fmu_dir: Path) -> None:
    """The issue's case: SIGTERM left `bench readback`'s child running and 31 MB in /tmp. Now: exit 143, one
    line, the child gone, no bench-readback-* folder left (TMPDIR is this test's own). Its first line comes before
    its first measurement (a suite is silent for minutes otherwise)."""
    import os
    import signal
    import time

    psutil = pytest.importorskip("psutil")
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = {**os.environ, "TMPDIR": str(scratch), "COLUMNS": "200"}
    bench = subprocess.Popen([sys.executable, "-c", "from orchestrator.cli import main; main()", "bench", "readback",
                              "--rounds", "1", "--out-dir", str(tmp_path / "out")], cwd=REPO, env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = bench.stderr.readline()
    assert first.startswith("7 measurements in 1 round(s), starting with study run"), first
    deadline = time.monotonic() + 120
    children: list = []
    while not children:  # an event: the suite's first child process (a run writing the study's trace)
        assert bench.poll() is None and time.monotonic() < deadline, bench.communicate()
        children = psutil.Process(bench.pid).children(recursive=True)
        time.sleep(0.05)
    assert list(scratch.glob("bench-readback-*"))  # its scratch folder is there while it works
    bench.send_signal(signal.SIGTERM)
    _, err = bench.communicate(timeout=120)
    assert bench.returncode == 143, err
    assert "Traceback" not in err and "bench readback: stopped by SIGTERM" in err, err
    gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, alive
    assert not list(scratch.glob("bench-readback-*"))
