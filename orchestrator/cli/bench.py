"""`platoon bench ...`: the benchmarks' command line (options, progress, tables, the JSON result). The
measurements themselves live beside the package, in the repository's benchmarks/ folder (not installed:
benchmarks/__init__.py says why), which knows nothing of the CLI; ``suite`` finds them in a checkout."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer


if TYPE_CHECKING:  # rich's table is imported where used: `platoon run -q` needs none
    pass

from orchestrator.cli.common import (SET_METAVAR, err, fail,
                                     out, output_rule)

# The engines the per-FMU-step suites know (benchmarks/engines.py describes them), listed here so that the
# help can name them without the benchmarks at hand.
BENCH_ENGINES = ("native", "native-buffer", "native-traced", "native-offload", "python", "fmpy-bare", "libcosim",
                 "libcosim-0threads", "libcosim-0threads-lastvalue", "slaves")
DEFAULT_OUT_DIR = Path("runs") / "bench"  # as benchmarks/common.py writes by default
NO_BENCHMARKS = ("the benchmarks are not part of the installed package: they live in the repository's benchmarks/ "
                 "folder; run `platoon bench` in a checkout (git clone, then pip install -e . there; "
                 "docs/performance.md)")


def checkout_with_benchmarks() -> Path | None:
    """The checkout whose benchmarks/ `platoon bench` runs: the one this package is installed from in place
    (pip install -e .), else the current folder if it holds them; None for an installed wheel elsewhere."""
    import orchestrator

    for root in (Path(orchestrator.__file__).resolve().parent.parent, Path.cwd()):
        if (root / "benchmarks" / "__init__.py").is_file():
            return root
    return None


def suite(name: str):
    """The module ``benchmarks.<name>`` of the checkout; exit 2 with ``NO_BENCHMARKS`` where there is none."""
    from importlib import import_module

    root = checkout_with_benchmarks()
    if root is None:
        fail(2, f"platoon bench: {NO_BENCHMARKS}")
    if str(root) not in sys.path:
        sys.path.append(str(root))
    return import_module(f"benchmarks.{name}")


bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: what steps and whole runs cost against FMPy and libcosim, memory per vehicle, HIL latency (JSON under runs/bench/; not pass/fail tests; docs/performance.md).")


ROUNDS_HELP = "interleaved repetitions (each variant once per round, order rotated); medians over rounds"


OutDir = Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")]


Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the tables and the result file")]


Engines = Annotated[str, typer.Option(metavar="ENGINE,...", help=f"comma-separated, of: {', '.join(BENCH_ENGINES)}")]


Counts = Annotated[str, typer.Option("--n", metavar="N,...", help="comma-separated vehicle counts")]


Steps = Annotated[int, typer.Option(min=1, help="communication steps of 0.01 s per measurement")]


Rounds = Annotated[int, typer.Option(min=1, help=ROUNDS_HELP)]


def _csv(option: str, text: str, choices: tuple[str, ...]) -> list[str]:
    """A comma-separated list of names out of ``choices``; anything else is a usage error (exit 2)."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in choices]
    if not names or unknown:
        fail(2, f"{option} {text!r}: expected a comma-separated list of {', '.join(choices)}")
    return list(dict.fromkeys(names))


def _integers(option: str, text: str, least: int, what: str, example: str) -> list[int]:
    """A comma-separated list of whole numbers, each at least ``least``, in the order given without repeats;
    exit 2 naming the option otherwise."""
    try:
        values = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        values = []
    if not values or min(values) < least:
        fail(2, f"{option} {text!r}: expected comma-separated {what} of at least {least}, e.g. {example}")
    return list(dict.fromkeys(values))


def _counts(text: str) -> list[int]:
    """``--n``: comma-separated vehicle counts, each at least 1."""
    return _integers("--n", text, 1, "vehicle counts", "4,16,64,256")


class _BenchProgress:
    """One line per measurement; on a terminal also a bar (stderr) counting the measurements done."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.bar: Progress | None = None
        self.task = None
        if not quiet and err.is_terminal:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("[bold]measuring"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                                TimeElapsedColumn(), TimeRemainingColumn(), console=err, transient=True)

    def __enter__(self) -> "_BenchProgress":
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def __call__(self, done: int, total: int, line: str) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            if self.task is None:
                self.task = self.bar.add_task("measuring", total=total)
            self.bar.update(self.task, completed=done, total=total)
        err.print(line, highlight=False, soft_wrap=True)


class _Terminated(KeyboardInterrupt):
    """SIGTERM during a suite: raised where the suite is, so that its children are ended and its scratch
    folders removed on the way out (``subprocess.run`` kills its child on any exception), as on Ctrl-C."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise _Terminated()


def run_bench(name: str, measure, render, out_dir: Path, quiet: bool) -> None:
    """Run one suite with progress, print its tables, write its JSON; bad options exit 2, failures 1, SIGINT
    and SIGTERM 130 and 143 once its children ended and its scratch files are gone."""
    import signal

    common = suite("common")
    BenchError, BenchUsageError, write_result = common.BenchError, common.BenchUsageError, common.write_result
    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        with _BenchProgress(quiet) as progress:
            result = measure(progress)
    except BenchUsageError as error:
        fail(2, str(error))
    except BenchError as error:
        fail(1, f"bench {name}: {error}")
    except KeyboardInterrupt as stop:
        signal_name, code = ("SIGTERM", 143) if isinstance(stop, _Terminated) else ("SIGINT (Ctrl-C)", 130)
        fail(code, f"bench {name}: stopped by {signal_name}; its child processes ended, its scratch files removed, no "
                   "result written")
    finally:
        signal.signal(signal.SIGTERM, previous)
    result["command"] = " ".join(["platoon", *sys.argv[1:]])
    out.print(render(result), highlight=False, soft_wrap=True)
    with output_rule():  # a folder it cannot write: one line
        written = write_result(out_dir, name, result)
    out.print(f"results: {written}", highlight=False, soft_wrap=True)


def _per_fmu_step(suite_name: str, engines: str, n: str, steps: int, rounds: int, out_dir: Path, quiet: bool,
                  **options) -> None:
    """The two suites of FMU-step costs (``steps``, ``coupling``): same options, same checks."""
    measured = suite(suite_name)
    chosen, counts = _csv("--engines", engines, BENCH_ENGINES), _counts(n)
    run_bench(suite_name, lambda progress: measured.run(chosen, counts, steps, rounds, progress=progress, **options),
           measured.markdown, out_dir, quiet)


def bench_steps(engines: Engines = "native,python,fmpy-bare,libcosim,libcosim-0threads,libcosim-0threads-lastvalue,slaves",
                n: Counts = "4,16,64,256", steps: Steps = 1000, rounds: Rounds = 5,
                out_dir: OutDir = Path("runs/bench"), quiet: Quiet = False,
                fmus: Annotated[Optional[str], typer.Option("--fmus", metavar="KIND,...", help="comma-separated FMU kinds: python, native (default: both where a C compiler builds the native ones)")] = None) -> None:
    """Microseconds per FMU-step of our engines, the bare FMPy loop, libcosim and the floor, by N, for the
    pythonfmu FMUs and the native ones."""
    from orchestrator.components.kinds import FMU_KINDS

    kinds = None if fmus is None else _csv("--fmus", fmus, FMU_KINDS)
    _per_fmu_step("steps", engines, n, steps, rounds, out_dir, quiet, fmu_kinds=kinds)


def bench_coupling(engines: Engines = "native,slaves", n: Counts = "4,16,64", steps: Steps = 1000, rounds: Rounds = 5,
                   out_dir: OutDir = Path("runs/bench"), quiet: Quiet = False) -> None:
    """Cost per FMU-step with coupling "hold" against "extrapolate" (same rounds, same engines)."""
    _per_fmu_step("coupling", engines, n, steps, rounds, out_dir, quiet)


def bench_scenarios(
    configs: Annotated[list[Path], typer.Option("--config", metavar="CONFIG", help="scenario TOML (repeatable; default configs/paper/*.toml)")] = [],
    engines: Annotated[str, typer.Option(metavar="ENGINE,...", help="comma-separated: native, python")] = "native,python",
    variants: Annotated[str, typer.Option(metavar="VARIANT,...", help="comma-separated: cli-traced (platoon run --out X -q), traced, untraced")] = "cli-traced,traced,untraced",
    rounds: Rounds = 3,
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key in every scenario")] = [],
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Whole-run wall times of the paper's scenarios, start-up included, traced and untraced."""
    measured = suite("scenarios")

    chosen = _csv("--engines", engines, measured.ENGINES)
    kinds = _csv("--variants", variants, measured.VARIANTS)
    run_bench("scenarios", lambda progress: measured.run(configs or None, chosen, kinds, rounds, overrides, progress=progress),
           measured.markdown, out_dir, quiet)


def bench_wholerun(
    n: Counts = "16",
    steps: Annotated[str, typer.Option(metavar="STEPS[,...]", help="communication steps of 0.01 s per run: one count, or one per --n (e.g. --n 16,64 --steps 10000,2000)")] = "10000",
    variants: Annotated[str, typer.Option(metavar="VARIANT,...", help="comma-separated: platoon (default run, traced, table), platoon-q (-q --trace-every 100), platoon-start (10 steps), libcosim (no observer), libcosim-outputs (time series of every output), libcosim-last-value, libcosim-file (CSV of every variable, every step); before, before-q, before-start: the same with --before's script; start-up (10 steps): platoon-first (-q -v: when the first step began), python (python -c pass), libcosim-start; platoon-hour (configs/bench/platoon100-1h.toml with its trace, once per round)")] = "platoon,platoon-q,platoon-start,libcosim,libcosim-file,platoon-hour",
    rounds: Rounds = 5,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
    fmus: Annotated[str, typer.Option("--fmus", metavar="<python|native>", help="the FMUs every variant steps: python (pythonfmu, the system the floors were set on) or native (the C twins)")] = "python",
    before: Annotated[Optional[Path], typer.Option("--before", metavar="PLATOON", help="another build's platoon script, for the before* variants (a change against what it replaces, in one sitting)")] = None,
    hour_config: Annotated[Path, typer.Option("--hour-config", metavar="CONFIG", help="the config platoon-hour runs")] = Path("configs/bench/platoon100-1h.toml"),
) -> None:
    """Whole `platoon run` processes against libcosim running the same system from an SSP (0 threads)."""
    measured = suite("wholerun")
    from orchestrator.components.kinds import FMU_KINDS

    if fmus not in FMU_KINDS:
        fail(2, f"--fmus {fmus!r}: expected one of {', '.join(FMU_KINDS)}")
    kinds, counts = _csv("--variants", variants, measured.VARIANTS), _counts(n)
    try:
        per_n = [int(part) for part in steps.split(",")]
    except ValueError:
        per_n = []
    if not per_n or min(per_n) < 1 or len(per_n) not in (1, len(counts)):
        fail(2, f"--steps {steps!r}: expected one step count of at least 1, or one per --n value, e.g. 10000,2000")
    if before is not None and not before.is_file():
        fail(2, f"--before {before}: no such file")
    if "platoon-hour" in kinds and not hour_config.is_file():
        fail(2, f"--hour-config {hour_config}: no such file")
    run_bench("wholerun", lambda progress: measured.run(counts, per_n if len(per_n) > 1 else per_n[0], rounds, kinds,
                                                  progress=progress, fmus=fmus, before=before, hour=hour_config),
           measured.markdown, out_dir, quiet)


def bench_instances(
    engines: Annotated[str, typer.Option(metavar="ENGINE,...", help="comma-separated: native, fmpy")] = "native,fmpy",
    n: Counts = "4,16,64,256",
    wirings: Annotated[str, typer.Option(metavar="WIRING,...", help="comma-separated: instances (unconnected), platoon (wired, settle sweeps)")] = "instances,platoon",
    rounds: Rounds = 3,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Instantiation time and RSS per vehicle instance (slope over N), native engine and FMPy."""
    measured = suite("instances")

    chosen, counts = _csv("--engines", engines, measured.ENGINES), _counts(n)
    kinds = _csv("--wirings", wirings, measured.WIRINGS)
    run_bench("instances", lambda progress: measured.run(chosen, counts, rounds, kinds, progress=progress), measured.markdown,
           out_dir, quiet)


def bench_profile(
    n: Counts = "4,16,64",
    steps: Annotated[int, typer.Option(min=1, help="steps per sample (capped to 20 s simulated in all)")] = 1000,
    rounds: Rounds = 3,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Where the native engine's time goes: native loop against the floor in one process, perf split."""
    measured = suite("profile")

    counts = _counts(n)
    run_bench("profile", lambda progress: measured.run(counts, steps, rounds, progress=progress), measured.markdown, out_dir, quiet)


def bench_flatness(
    n: Counts = "4,16,64,256",
    steps: Annotated[int, typer.Option(min=1, help="steps per sample")] = 150,
    rounds: Annotated[int, typer.Option(min=1, help="interleaved samples per process")] = 5,
    repeats: Annotated[int, typer.Option(min=1, help="processes per N and experiment")] = 3,
    callgrind: Annotated[bool, typer.Option("--callgrind", help="also count instructions and simulated cache misses (valgrind; slow)")] = False,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Why the cost per FMU-step grows with N: stepping order, idle instances, object sizes, cache misses."""
    measured = suite("flatness")

    counts = _counts(n)
    run_bench("flatness", lambda progress: measured.run_suite(counts, steps, rounds, repeats, callgrind, progress=progress),
           measured.suite_markdown, out_dir, quiet)


CORE_BUILD_HELP = "LABEL=PATH of a built orchestrator/execution/native/_core .so (copy it aside before rebuilding _core.c)"


def bench_callgrind(
    n: Counts = "4,16,64,256",
    engines: Annotated[str, typer.Option(metavar="ENGINE,...", help="comma-separated: native, python, fmpy-bare")] = "native",
    fmu_steps: Annotated[int, typer.Option(min=1, help="FMU-steps per measurement (steps = this / (N + 1))")] = 2500,
    ll: Annotated[str, typer.Option("--ll", metavar="CACHE,...", help="comma-separated last-level caches to simulate: l2 (this machine's "
                                               "512 KiB L2), detected (valgrind's choice, the L3)")] = "l2",
    cores: Annotated[list[str], typer.Option("--core", metavar="LABEL=PATH", help=f"{CORE_BUILD_HELP}; repeatable (native engine; default: the installed core)")] = [],
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Instructions and cache misses per FMU-step of an engine's stepping (valgrind), the master's own apart."""
    measured = suite("flatness")

    counts, chosen = _counts(n), _csv("--engines", engines, measured.CALLGRIND_ENGINES)
    levels = [measured.LAST_LEVELS[name] for name in _csv("--ll", ll, tuple(measured.LAST_LEVELS))]
    run_bench("callgrind", lambda progress: measured.callgrind_series(counts, fmu_steps, levels, measured.core_builds(cores) or None,
                                                                progress=progress, engines=chosen),
           measured.callgrind_markdown, out_dir, quiet)


def bench_cores(
    builds: Annotated[list[str], typer.Argument(metavar="LABEL=PATH", help=f"{CORE_BUILD_HELP}; at least two", show_default=False)],
    n: Counts = "4,16,64,256",
    steps: Steps = 1000,
    rounds: Rounds = 5,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """The native engine with two or more builds of _core.c: µs per FMU-step, interleaved in fresh interpreters."""
    measured = suite("flatness")

    counts = _counts(n)
    run_bench("cores", lambda progress: measured.compare_cores(measured.core_builds(builds), counts, steps, rounds, progress=progress),
           measured.cores_markdown, out_dir, quiet)



def bench_hil(
    seconds: Annotated[float, typer.Option(min=0.5, help="seconds per live run (the ping-pong takes half)")] = 10.0,
    rounds: Annotated[int, typer.Option(min=1, help="repetitions of every measurement (order rotated); medians")] = 1,
    out_dir: Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")] = DEFAULT_OUT_DIR,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the tables and the result file")] = False,
) -> None:
    """Hardware in the loop on loopback: Zenoh round trip (bare and in live runs) and step jitter at 100 and 200 Hz."""
    measured = suite("hil")

    run_bench("hil", lambda progress: measured.run(seconds, rounds, progress), measured.render, out_dir, quiet)


def bench_sweep(
    workers: Annotated[str, typer.Option(metavar="N,...", help="comma-separated local worker counts")] = "1,2",
    runs: Annotated[int, typer.Option(min=1, help="runs in the sweep")] = 8,
    stop_time: Annotated[float, typer.Option(min=0.1, help="simulated seconds per run")] = 100.0,
    rounds: Annotated[int, typer.Option(min=1, help="interleaved repetitions; medians")] = 3,
    dask: Annotated[bool, typer.Option("--dask/--no-dask", help="also on a Dask LocalCluster")] = True,
    out_dir: Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")] = DEFAULT_OUT_DIR,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the table and the result file")] = False,
) -> None:
    """Speed-up of a sweep with more local workers (and on Dask): wall time of real platoon sweep runs."""
    measured = suite("sweep")

    counts = sorted(_integers("--workers", workers, 1, "worker counts", "1,2"))
    run_bench("sweep", lambda progress: measured.run(counts, runs, stop_time, rounds, dask, progress), measured.render, out_dir, quiet)


def bench_sweep_bookkeeping(
    points: Annotated[str, typer.Option(metavar="N,...", help="comma-separated sweep sizes (points)")] = "100,1000,10000,100000",
    first_run: Annotated[int, typer.Option(min=0, help="also time the first run of a sweep this big (0: no)")] = 1_000_000,
    out_dir: Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")] = DEFAULT_OUT_DIR,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the table and the result file")] = False,
) -> None:
    """A sweep's bookkeeping per run (plan, result file, results.csv row) against its size; and how soon a
    sweep of --first-run points starts its first run."""
    measured = suite("sweep_bookkeeping")

    sizes = sorted(_integers("--points", points, 10, "sweep sizes", "100,1000"))
    run_bench("sweep-bookkeeping", lambda progress: measured.run(sizes, first_run, progress), measured.render, out_dir, quiet)


def bench_readback(
    rounds: Annotated[int, typer.Option(min=1, help="interleaved repetitions; medians")] = 3,
    with_map: Annotated[bool, typer.Option("--map/--no-map", help="also the 75-run study sweep against its "
                                           "stability-map (about a minute a round)")] = False,
    out_dir: Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")] = DEFAULT_OUT_DIR,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the table and the result file")] = False,
) -> None:
    """Each trace reader (load, report, stability, stability-map) against the run that wrote the trace."""
    measured = suite("readback")

    run_bench("readback", lambda progress: measured.run(rounds, with_map, progress), measured.render, out_dir, quiet)


def bench_remote(
    n: Counts = "1,4,16",
    steps: Annotated[int, typer.Option(min=1, help="macro steps per measurement")] = 500,
    rounds: Rounds = 3,
    out_dir: OutDir = DEFAULT_OUT_DIR,
    quiet: Quiet = False,
) -> None:
    """Remote vehicles on loopback: a macro step in lockstep against one by one, local, and the Zenoh round trip."""
    measured = suite("remote")
    run_bench("remote", lambda progress: measured.run(_counts(n), steps, rounds, progress), measured.render, out_dir, quiet)


def bench_startup(
    runs: Annotated[int, typer.Option(min=1, help="runs in the sweep")] = 20,
    stop_time: Annotated[float, typer.Option(min=0.1, help="simulated seconds per run of the sweep")] = 200.0,
    rounds: Rounds = 3,
    sweep: Annotated[bool, typer.Option("--sweep/--no-sweep", help="also the sweep's cost per run against a run's own work")] = True,
    out_dir: OutDir = DEFAULT_OUT_DIR,
    quiet: Quiet = False,
) -> None:
    """Each command's time to first output (--help, --version, a bad option, a 10-step run, the README's run and its
    report), and a sweep's cost per run against the run's own work (one worker)."""
    measured = suite("startup")
    run_bench("startup", lambda progress: measured.run(runs, stop_time, rounds, sweep, progress), measured.render,
              out_dir, quiet)


def register(app: typer.Typer) -> None:
    """``platoon bench`` and its suites."""
    bench_app.command("steps")(bench_steps)
    bench_app.command("coupling")(bench_coupling)
    bench_app.command("scenarios")(bench_scenarios)
    bench_app.command("wholerun")(bench_wholerun)
    bench_app.command("instances")(bench_instances)
    bench_app.command("profile")(bench_profile)
    bench_app.command("flatness")(bench_flatness)
    bench_app.command("callgrind")(bench_callgrind)
    bench_app.command("cores")(bench_cores)
    bench_app.command("hil")(bench_hil)
    bench_app.command("sweep")(bench_sweep)
    bench_app.command("sweep-bookkeeping")(bench_sweep_bookkeeping)
    bench_app.command("readback")(bench_readback)
    bench_app.command("remote")(bench_remote)
    bench_app.command("startup")(bench_startup)
    app.add_typer(bench_app, name="bench")
