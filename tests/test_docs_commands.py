"""Every command in README.md and docs/*.md runs, so a doc cannot drift from the tool again.

Each fenced ``sh``/``shell``/``bash``/``console`` block is run as one bash script (its variables and
background jobs, ``&`` and ``kill %1``, as a user pasting it would have them), in a copy of this
working tree (the commands write runs/, traces, plots), with this tree's code (PYTHONPATH), the
venv's ``platoon`` and ``python`` on PATH and ``.venv`` linked to the venv. Every command's exit status
is checked (0 unless the table says otherwise) and nothing may print a traceback, nor a ``warning:``
the docs do not announce. ``/tmp/`` in a command becomes the test's own temporary folder, which is
also the block's ``TMPDIR`` (two test runs at once must not share ``/tmp/Vehicle`` or ``/tmp/release``).
Each block runs within a budget: ``BUDGET``, or its ``SLOW`` entry's, derived from a cold run measured
on 2 cores; a block that cross-compiles has Zig's cache warmed first, off its clock.

Commands that need hardware, the network beyond 127.0.0.1, or much more than ~30 s are run in a
shortened but real form, each for the reason ``SPECIAL`` gives: the same command with a shorter
``stop_time``, or ``--help`` of exactly that subcommand plus a parse of its options (``Parse``). A
``SPECIAL`` entry whose command is no longer in the docs fails the test, so the table cannot go stale.
The README's first block (install, run; tests) is special: the run part of its install line is run as
written, pip is not.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import fixed_ports, shared_build

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SHELLS = ("sh", "shell", "bash", "console")
VENV_BIN = Path(sys.executable).parent
SHORT = " --set simulation.stop_time=2"  # a live run paced to the wall clock: 2 s instead of 10 or 60


@dataclass(frozen=True)
class Shorten:
    """Run ``command`` instead (a real, shorter form of the documented one), for ``why``."""
    command: str
    why: str


@dataclass(frozen=True)
class Parse:
    """Not run: ``platoon SUBCOMMAND --help`` runs, and the documented arguments parse, for ``why``."""
    why: str


@dataclass(frozen=True)
class Skip:
    """Not run at all, for ``why`` (what it needs is no part of this tool)."""
    why: str


@dataclass(frozen=True)
class Expect:
    """Run as written; it exits ``status`` with ``text`` in its output, as the doc around it says."""
    status: int
    text: str
    why: str


INSTALL = ("python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/platoon run configs/paper/platoon.toml "
           "--out runs/platoon.mcap && .venv/bin/platoon report runs/platoon.mcap --plots runs/platoon-plots")
REALTIME_PHASE = ".venv/bin/python -m pytest -q -m 'realtime and not slow' -n 0"  # the real-time tests, alone
TEST_LINE = ".venv/bin/pip install -e '.[test]' && .venv/bin/python -m pytest -q && " + REALTIME_PHASE  # README's 2nd
SLOW_PHASES = (".venv/bin/python -m pytest -q -m 'slow and not realtime' --dist loadfile",
               ".venv/bin/python -m pytest -q -m 'slow and realtime' -n 0")  # CI's, after the two (.ci/run)
LIVE3_EMULATOR_4 = (".venv/bin/platoon m3pi-emulator --config configs/hil/m3pi_live3.toml --set vehicles.4.endpoint=zenoh "
                    "--set 'vehicles.4.connect=[\"tcp/127.0.0.1:7447\"]' &")
LIVE3_RUN_4 = (".venv/bin/platoon run configs/hil/m3pi_live3.toml --set vehicles.4.endpoint=zenoh "
               "--set 'vehicles.4.connect=[\"tcp/127.0.0.1:7447\"]'")
ROS2_LAB_RUN = (".venv/bin/platoon run configs/hil/ros2_live3.toml --set 'vehicles.3.connect=[\"tcp/192.168.1.20:7447\"]' "
                "--set vehicles.3.ros2.command_topic=/diff_drive_controller/cmd_vel --set vehicles.3.ros2.command_type=TwistStamped "
                "--set hil.allow_insecure=true")
ROS2_DDS_LAB_RUN = (".venv/bin/platoon run configs/hil/ros2_live3.toml --set 'vehicles.3.connect=[\"tcp/192.168.1.20:7447\"]' "
                    "--set vehicles.3.ros2.convention=bridge_dds "
                    "--set hil.allow_insecure=true")
ROS2_DDS_EMULATED_RUN = (".venv/bin/platoon run configs/hil/ros2_live3.toml --set vehicles.3.ros2.convention=bridge_dds "
                         "--set simulation.stop_time=10")
ROS2_PUBLISH_RUN = (".venv/bin/platoon run configs/paper/m3pi.toml --set ros2.publish=true "
                    "--set 'ros2.connect=[\"tcp/192.168.1.20:7447\"]' "
                    "--set hil.allow_insecure=true")
LAB_RUN = (".venv/bin/platoon run configs/hil/m3pi_live3.toml --set simulation.stop_time=10 --set "
           "'vehicles.3.connect=[\"tls/127.0.0.1:7450\"]' --set 'vehicles.3.zenoh_config=\"/tmp/lab/laptop.json5\"'")
CALIBRATION_RUN = ".venv/bin/platoon run configs/hil/calibrate.toml -q --out /tmp/calibrate.mcap"
REAL_ROBOT_RUN = ".venv/bin/platoon run configs/hil/m3pi_live3.toml --set 'vehicles.3.connect=[\"tcp/127.0.0.1:7448\", \"tcp/127.0.0.1:7449\"]'"

ZENOHD = "~/.cache/platoon-cosim/zenoh-1.10.2/bin/zenohd -c configs/hil/zenohd-local.json5"
ROUTER_BLOCKS = (  # docs/hil.md, "A real router and DDS bridge"
    ZENOHD + " &",
    ".venv/bin/platoon m3pi-emulator --config configs/hil/ros2_live3.toml --ros2 rmw_zenoh --set "
    "'vehicles.3.listen=[\"tcp/127.0.0.1:7447\"]' --set 'vehicles.3.connect=[\"tcp/127.0.0.1:7448\"]' &",
    ".venv/bin/platoon run configs/hil/ros2_live3.toml --set simulation.stop_time=10 --out /tmp/ros2-router.mcap",
    "kill %2 %1",
    "export CYCLONEDDS_URI=\"$(.venv/bin/python -c 'from tests.dds_robot import LOOPBACK_ONLY; print(LOOPBACK_ONLY)')\"",
    "RUST_LOG=warn,zenoh_plugin_ros2dds=info " + ZENOHD + " --plugin-search-dir ~/.cache/platoon-cosim/zenoh-1.10.2/lib "
    "-P ros2dds &",
    ".venv/bin/python -m tests.dds_robot configs/hil/ros2_live3.toml 0 &",
    ".venv/bin/platoon run configs/hil/ros2_live3.toml --set vehicles.3.ros2.convention=bridge_dds "
    "--set simulation.stop_time=10 --out /tmp/ros2-dds.mcap",
)

# (doc, command as written, without a trailing comment) -> how it is run instead, and why
SPECIAL: dict[tuple[str, str], Shorten | Parse | Skip | Expect] = {
    ("README.md", INSTALL): Shorten(
        INSTALL.split(" && ", 2)[2],
        "the venv and `pip install -e` are the environment this test runs in (pip would need the network); "
        "the run and report of the install line run as written"),
    ("README.md", TEST_LINE): Shorten(
        REALTIME_PHASE + " --collect-only",
        "the test extra is the environment this test runs in (pip would need the network); the whole suite "
        "takes minutes (and includes this test); collecting the real-time phase imports every test module, as "
        "the first phase does, and selects the second's tests (which phase holds which test: "
        "test_the_real_time_tests_are_a_phase_of_their_own)"),
    ("README.md", SLOW_PHASES[0]): Shorten(
        SLOW_PHASES[0] + " --collect-only",
        "the slow tests take ~10 min (CI runs them); collecting them imports their modules and selects them"),
    ("README.md", SLOW_PHASES[1]): Shorten(
        SLOW_PHASES[1] + " --collect-only", "the long HIL runs, paced to the wall clock (CI runs them)"),
    ("README.md", ".venv/bin/platoon run configs/hil/m3pi_live3.toml"): Shorten(
        ".venv/bin/platoon run configs/hil/m3pi_live3.toml" + SHORT,
        "a live run is paced to the wall clock: 60 s as written"),
    ("README.md", ".venv/bin/platoon run configs/bench/platoon100-1h.toml --trace-every 10"): Shorten(
        ".venv/bin/platoon run configs/bench/platoon100-1h.toml --trace-every 10 --set simulation.stop_time=60",
        "one simulated hour of 100 vehicles takes ~10 s of CPU (a minute on a loaded machine); the first minute of it"),
    ("docs/hil.md", ".venv/bin/platoon run configs/hil/m3pi_live3.toml --set simulation.stop_time=10 --out /tmp/hil-doc.mcap"):
        Shorten(".venv/bin/platoon run configs/hil/m3pi_live3.toml --set simulation.stop_time=10 --out /tmp/hil-doc.mcap" + SHORT,
                "a live run is paced to the wall clock: 10 s as written"),
    ("docs/hil.md", LIVE3_RUN_4): Shorten(LIVE3_RUN_4 + SHORT, "a live run is paced to the wall clock: 60 s as written"),
    ("docs/hil.md", CALIBRATION_RUN): Shorten(
        CALIBRATION_RUN + " --set simulation.stop_time=12",
        "the calibration experiment is paced to the wall clock: 60 s as written; its first 12 s (speed steps: the "
        "limit and the dead-band then come out not identified, as calibrate says)"),
    ("docs/hil.md", LAB_RUN): Shorten(LAB_RUN + SHORT, "a live run is paced to the wall clock: 10 s as written"),
    ("docs/hil.md", ".venv/bin/platoon m3pi-serial --port /dev/ttyUSB0 --id 3 --listen tcp/127.0.0.1:7448 --max-speed 0.8 &"):
        Parse("needs a real m3pi behind an XBee on /dev/ttyUSB0"),
    ("docs/hil.md", ".venv/bin/platoon mocap --system vicon --host 192.168.1.5 --body m3pi_3=3 --listen tcp/127.0.0.1:7449 &"):
        Parse("needs a Vicon system at 192.168.1.5 (tests/test_ros2.py runs platoon mocap with libmotioncapture's mock)"),
    ("docs/remote.md", ".venv/bin/platoon serve Vehicle --name vehicle3 --listen tls/192.168.1.13:7447 --zenoh-config "
                       "lab/robot3-serve.json5"): Parse("needs the robot's computer at 192.168.1.13 and the lab's certificates"),
    ("docs/hil.md", ROS2_LAB_RUN): Parse("needs the lab's ROS 2 machine and its rmw_zenohd at 192.168.1.20"),
    ("docs/hil.md", ROS2_DDS_LAB_RUN): Parse("needs the lab's ROS 2 machine and its zenoh-bridge-ros2dds at 192.168.1.20"),
    ("docs/hil.md", ROS2_PUBLISH_RUN): Parse("needs a ROS 2 graph's router at 192.168.1.20 (tests/test_ros2.py publishes "
                                             "to a local viewer)"),
    ("docs/hil.md", ".venv/bin/platoon run configs/hil/ros2_live3.toml --set simulation.stop_time=10 --out /tmp/ros2-doc.mcap"):
        Shorten(".venv/bin/platoon run configs/hil/ros2_live3.toml --set simulation.stop_time=10 --out /tmp/ros2-doc.mcap" + SHORT,
                "a live run is paced to the wall clock: 10 s as written"),
    ("docs/hil.md", ROS2_DDS_EMULATED_RUN): Shorten(ROS2_DDS_EMULATED_RUN + SHORT,
                                                   "a live run is paced to the wall clock: 10 s as written"),
    ("docs/hil.md", "tools/build-zenoh-cache.sh"): Skip("builds zenohd and the ros2dds plugin with cargo: most of an "
                                                        "hour (docs/hil.md, \"A real router and DDS bridge\")"),
    **{("docs/hil.md", command): Skip("needs zenohd (and its ros2dds plugin) from tools/build-zenoh-cache.sh; "
                                      "tests/test_zenoh_router.py runs the same chains, the DDS block as written (slow)")
       for command in ROUTER_BLOCKS},
    ("docs/hil.md", REAL_ROBOT_RUN): Parse("needs the real robot and motion capture of the two lines above"),
    ("docs/hil.md", ".venv/bin/platoon bench hil"): Shorten(
        ".venv/bin/platoon bench hil --seconds 0.5", "about 40 s as written; the same measurements, 0.5 s each"),
    ("docs/hil.md", ".venv/bin/platoon bench hil --rounds 5"): Parse(
        "five rounds of the benchmark the line above runs (shortened) once: minutes"),
    ("docs/fmus.md", "platoon export-ssp configs/hil/m3pi_live3.toml --set simulation.stop_time=20 --out m3pi_live3.ssp"):
        Shorten("platoon export-ssp configs/hil/m3pi_live3.toml --set simulation.stop_time=20 --out m3pi_live3.ssp" + SHORT,
                "run_live.py then runs the package, paced to the wall clock: 20 s as written"),
    ("docs/model.md", "platoon run configs/paper/platoon.toml $EQ --set simulation.step=0.1 --set simulation.max_substep=0.1 "
                      "--set simulation.stop_time=400 --trace-every 10 --out runs/long.mcap"):
        Expect(1, "failed at t = 208.3 s", "the section's point: with the paper's k_v 100 vehicles break down "
                                           "(its table: fails at t = 208.3 s); the trace keeps what was recorded"),
    ("docs/foxglove.md", "platoon run configs/paper/platoon.toml --out runs/platoon.mcap --live --live-wait"):
        Shorten("platoon run configs/paper/platoon.toml --out runs/platoon.mcap --live --live-port 8799 --live-speed 0"
                + SHORT, "--live-wait waits for a viewer (none here) and the run is paced to the wall clock: the same "
                         "live server, unpaced, 2 s, on a port no test uses; tests/test_foxglove_view.py watches it"),
    ("docs/sweeps.md", "pip install 'platoon-cosim[dask]'"): Skip("needs the network (the extra is checked below)"),
    ("docs/sweeps.md", "dask scheduler &"): Skip("Dask's own command; tests/test_sweep.py runs a real Dask cluster"),
    ("docs/sweeps.md", "dask worker tcp://127.0.0.1:8786 --nworkers 2 --nthreads 1 &"): Skip("as dask scheduler"),
    ("docs/sweeps.md", "platoon sweep configs/sweeps/offset_map.toml --out runs/offset_map --scheduler tcp://127.0.0.1:8786"):
        Parse("needs the Dask cluster of the two lines above"),
}

# Files a block needs beside the tree, made in its copy before it runs (each says why)
def _sweep_cut_short(root: Path) -> None:
    """The sweeps as written take 1.5 min (50 runs of 100 s): in the copy, the same file cut to 8 runs of 5 s."""
    path = root / "configs" / "sweeps" / "offset_map.toml"
    text = (REPO / path.relative_to(root)).read_text()  # the file as shipped (both sweep blocks call this)
    text = text.replace('"simulation.trace_every" = 10', '"simulation.trace_every" = 10\n"simulation.stop_time" = 5.0')
    text = text.replace('"platoon.count" = [1, 2, 4, 6, 8]', '"platoon.count" = [1, 2]')
    text = text.replace('"platoon.d_star" = [12.5, 25.0, 50.0, 75.0, 95.0]', '"platoon.d_star" = [25.0, 75.0]')
    assert text.count("5.0") >= 1 and '[1, 2]' in text and '[25.0, 75.0]' in text, "offset_map.toml changed: update this"
    path.write_text(text)


def _stability_sweep_cut_short(root: Path) -> None:
    """The study as written is 75 runs (a minute or five on 2 cores): in the copy, 4 of them (2 laws x 2 delays,
    no loss), each the full 391 s its gains need."""
    path = root / "configs" / "sweeps" / "string_stability.toml"
    text = (REPO / path.relative_to(root)).read_text()
    cut = (text.replace('"platoon.speed_law" = ["paper", "acc", "cacc"]', '"platoon.speed_law" = ["paper", "cacc"]')
               .replace('"links.delay" = [0.0, 0.1, 0.2, 0.3, 0.4]', '"links.delay" = [0.0, 0.3]')
               .replace('"links.loss" = [0.0, 0.2, 0.4, 0.6, 0.8]', '"links.loss" = [0.0]'))
    assert cut.count("[0.0") == 2 and '["paper", "cacc"]' in cut, "string_stability.toml changed: update this"
    path.write_text(cut)


def _broken_traces(root: Path) -> None:
    """What `platoon trace recover` is for: a killed run's file (a finished trace cut at 60 %: complete
    chunks, no footer, as SIGKILL leaves it) and a damaged one (4 KiB zeroed in the middle)."""
    runs = root / "runs"
    runs.mkdir(exist_ok=True)
    full = runs / "full.mcap"
    made = subprocess.run(["platoon", "run", "configs/paper/platoon.toml", "--set", "simulation.stop_time=20", "-q",
                           "--trace-writer", "inline", "--out", str(full)], cwd=root, env=_env(root),
                          capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr
    data = full.read_bytes()
    (runs / "killed.mcap.partial").write_bytes(data[: len(data) * 6 // 10])
    damaged = bytearray(data)
    middle = int(len(data) * 0.45)
    damaged[middle:middle + 4096] = bytes(4096)
    (runs / "damaged.mcap").write_bytes(bytes(damaged))


SETUP = {("docs/reproduction.md", 54): _sweep_cut_short, ("docs/sweeps.md", 7): _sweep_cut_short,
         ("docs/model.md", 879): _stability_sweep_cut_short,
         ("docs/trace-format.md", 273): _broken_traces}


@dataclass
class Block:
    doc: str  # relative to the repository
    line: int  # of the opening fence
    commands: list[str]  # continuation lines joined (backslash-newline kept), comment lines dropped
    after: str | None  # the next fenced python block of the same doc (a script a command runs by name)


def doc_blocks() -> list[Block]:
    found = []
    fence = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)
    for path in DOCS:
        text = path.read_text()
        matches = list(fence.finditer(text))
        for index, match in enumerate(matches):
            if match.group(1) not in SHELLS:
                continue
            after = next((m.group(2) for m in matches[index + 1:] if m.group(1) == "python"), None)
            commands, pending = [], ""
            for raw in match.group(2).splitlines():
                if not pending and (not raw.strip() or raw.lstrip().startswith("#")):
                    continue
                pending += raw
                if raw.endswith("\\"):
                    pending += "\n"
                    continue
                commands.append(pending)
                pending = ""
            found.append(Block(str(path.relative_to(REPO)), text[:match.start()].count("\n") + 1, commands, after))
    return found


def bare(command: str) -> str:
    """The command without a trailing comment, continuation lines joined by one space (the table's key)."""
    text = re.sub(r"\s*\\\n\s*", " ", command)
    return re.sub(r"\s+#[^'\"]*$", "", text).strip()


BLOCKS = doc_blocks()


def test_the_table_names_only_commands_the_docs_hold() -> None:
    """A stale entry (the doc changed) must be noticed, not silently run nothing."""
    written = {(block.doc, bare(command)) for block in BLOCKS for command in block.commands}
    assert len(BLOCKS) >= 15
    for key in SPECIAL:
        assert key in written, f"SPECIAL names a command no longer in the docs: {key}"
    for doc, line in SETUP:
        assert any(block.doc == doc and block.line == line for block in BLOCKS), f"SETUP: no block at {doc}:{line}"


def _env(root: Path) -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": str(root), "PATH": f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}",
           "COLUMNS": "100", "NO_COLOR": "1", "TERM": "dumb"}
    env.pop("FORCE_COLOR", None)
    env.pop("VIRTUAL_ENV", None)
    return env


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> Path:
    """A copy of this working tree with the built FMUs (no .git, runs or caches) and ``.venv`` linked.
    The native FMUs are built first where a compiler is (docs/fmus.md unzips one): a block must not
    depend on another having run before it in the same copy (the blocks run on parallel workers)."""
    from fmus.builders import NATIVE_FMI2, NATIVE_OUT, NoCompiler

    try:
        with shared_build():
            NATIVE_FMI2.build(REPO / NATIVE_OUT)
    except NoCompiler:
        pass  # the blocks that need them skip, saying so
    root = tmp_path_factory.mktemp("docs") / "repo"
    skip = shutil.ignore_patterns(".git", "runs", "build", "__pycache__", ".venv", "*.mcap", "*.mcap.partial",
                                  ".pytest_cache", "node_modules")
    shutil.copytree(REPO, root, ignore=skip, symlinks=True)
    shutil.copytree(fmu_dir, root / "build" / "fmus")
    (root / ".venv").symlink_to(VENV_BIN.parent)
    return root


def script_of(block: Block, scratch: Path) -> tuple[str, list[str]]:
    """The block as a bash script (each command's status checked) and the commands only parsed."""
    lines = ["trap 'kill $(jobs -p) 2>/dev/null; wait' EXIT"]  # no emulator outlives its block
    parsed = []
    for command in block.commands:
        how = SPECIAL.get((block.doc, bare(command)))
        if isinstance(how, Skip):
            continue
        if isinstance(how, Parse):
            parsed.append(bare(command))
            continue
        text = how.command if isinstance(how, Shorten) else command
        text = text.replace("/tmp/", f"{scratch}/")
        lines.append(text)
        if not bare(text).endswith("&"):
            expected = how.status if isinstance(how, Expect) else 0
            quoted = shlex.quote(bare(text))
            lines.append(f'status=$?; [ "$status" -eq {expected} ] || {{ echo "doc command exited $status, '
                         f'expected {expected}: "{quoted} >&2; exit 99; }}')
    return "\n".join(lines) + "\n", parsed


def parse_only(command: str, root: Path) -> None:
    """``--help`` of exactly the documented subcommand runs, and its documented arguments parse."""
    import typer

    from orchestrator.cli.app import app

    words = shlex.split(command)
    if words[-1] == "&":
        words = words[:-1]
    assert Path(words[0]).name == "platoon", command
    group, path, rest = typer.main.get_command(app), [], words[1:]
    while rest and rest[0] in getattr(group, "commands", {}):
        group = group.commands[rest[0]]
        path.append(rest.pop(0))
    helped = subprocess.run(["platoon", *path, "--help"], cwd=root, env=_env(root), capture_output=True, text=True,
                            timeout=60)
    assert helped.returncode == 0 and "Traceback" not in helped.stderr, helped.stderr
    context = group.make_context(" ".join(["platoon", *path]), list(rest))  # raises on an unknown option or a bad value
    assert context.params, command
    if isinstance(context.params.get("config"), Path):  # and the config with its --set overrides validates
        from orchestrator.scenario.config import load_config

        load_config(root / context.params["config"], context.params.get("overrides") or [])


# Blocks that listen on a fixed port as documented (the HIL configs' tcp/127.0.0.1:7447, a --live
# server): run one at a time, across parallel workers too (tests/conftest.py: fixed_ports)
FIXED_PORT = re.compile(r"m3pi-emulator|--live\b|configs/hil/|ros2\.publish|platoon serve|bench remote")
@dataclass(frozen=True)
class Slow:
    """A block long by nature, run as written by the slow tests only (pytest -m slow; CI runs them), within
    ``budget`` seconds: a bound derived from a cold run measured on 2 cores, with room for a machine
    that runs other test files (wine, qemu) and a CPU-bound process beside it. ``zig``: it
    cross-compiles, so Zig's cache is warmed first (tests/conftest.py: ``zig_cache``), not on its clock."""
    budget: float
    why: str
    zig: bool = False


# s for any other block: 7x the longest of them, docs/model.md:675 (a string-stability sweep cut short), which
# took 16.5 s here (2026-11-29, 2 cores at load 7-9, this file under -n 2; the rest 12 s or less)
BUDGET = 120.0
SLOW = {"platoon build --all-platforms --out /tmp/release": Slow(
            600.0, "cross-compiles five binaries for four FMUs in two FMI versions with Zig (tests/test_platforms.py "
                   "runs them). Measured 2026-11-29 on 2 cores at load 5-8: 141 s with Zig's cache cold (75 s of CPU, "
                   "most of it MinGW-w64's CRT), 35-37 s warm (16 s of CPU); warming the cache for the five targets "
                   "took 159 s cold, 0.5 s warm. The budget is 4x the cold run: it holds even if the warm-up missed "
                   "something, and a warm build at a quarter of the CPU it had here", zig=True),
        "python -m fmus.builders.zig_cache": Slow(
            BUDGET, "warms Zig's cache as CI does: 159 s on a cold cache (the block above), so run after the "
                    "fixture has warmed it (0.5 s then), with the slow tests that cross-compile", zig=True),
        "platoon export-ssp configs/hil/m3pi_live3.toml --set simulation.stop_time=20 --out m3pi_live3.ssp": Slow(
            BUDGET, "libcosim runs the package paced to the wall clock for 20 s (23 s measured at load 7), the longest "
                    "test of the default run; tests/test_live_fmu.py runs LiveVehicle.fmu in libcosim against the "
                    "emulator there")}


def slow_entries(block: Block) -> list[Slow]:
    return [SLOW[bare(command)] for command in block.commands if bare(command) in SLOW]


# a block that drives a live (emulated) robot, or serves a run live: paced to the wall clock, so it runs in the
# real-time phase, alone (README, "Tests")
PACED = re.compile(r"m3pi-emulator|--live\b")


def block_param(block: Block):
    marks = [pytest.mark.slow] if slow_entries(block) else []
    if any(PACED.search(command) for command in block.commands):
        marks.append(pytest.mark.realtime)
    return pytest.param(block, marks=marks, id=f"{block.doc}:{block.line}")


@pytest.mark.parametrize("block", [block_param(block) for block in BLOCKS])
def test_doc_block_runs(block: Block, tree: Path, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    slow = slow_entries(block)
    budget = max((entry.budget for entry in slow), default=BUDGET)
    if any(entry.zig for entry in slow):
        request.getfixturevalue("zig_cache")  # warmed once per machine, before the block's clock starts
    setup = SETUP.get((block.doc, block.line))
    if setup is not None:
        setup(tree)
    if block.after is not None:
        for name in re.findall(r"python (\w+\.py)", "\n".join(block.commands)):
            (tree / name).write_text(block.after)  # the script the doc gives right after the commands
    if any("unzip" in c or "cc " in c for c in block.commands) and not (shutil.which("cc") and shutil.which("unzip")):
        pytest.skip("needs a C compiler and unzip (docs/fmus.md: a plain C host)")
    script, parsed = script_of(block, tmp_path)
    for command in parsed:
        parse_only(command, tree)
    with fixed_ports() if FIXED_PORT.search("\n".join(block.commands)) else nullcontext():
        # TMPDIR too: what a command makes in the temporary folder (a build's scratch) is the test's own
        env = {**_env(tree), "TMPDIR": str(tmp_path)}
        started = subprocess.Popen(["bash", "-c", script], cwd=tree, env=env, stdout=subprocess.PIPE,
                                   stderr=subprocess.STDOUT, text=True, start_new_session=True)
        try:
            output, _ = started.communicate(timeout=budget)
        except subprocess.TimeoutExpired:
            os.killpg(started.pid, signal.SIGKILL)
            output, _ = started.communicate()
            pytest.fail(f"{block.doc}:{block.line} took more than its budget of {budget:.0f} s (tests/test_docs_commands.py: "
                        f"SLOW, BUDGET):\n{output[-3000:]}")
    assert started.returncode == 0, f"{block.doc}:{block.line}:\n{output[-4000:]}"
    assert "Traceback" not in output, output[-4000:]
    for command in block.commands:
        how = SPECIAL.get((block.doc, bare(command)))
        if isinstance(how, Expect):
            assert how.text in output, output[-4000:]
    unannounced = [line for line in output.splitlines() if line.startswith("warning:")]
    assert not unannounced, f"{block.doc}:{block.line} warns where its doc does not say so: {unannounced}"


def test_the_readme_first_block_is_ci_s_two_commands() -> None:
    """CI (.ci/run) reads the README's first sh block with its own awk and runs line 1, then line 2: the
    first installs only what a run needs (no extra: a newcomer's first run does not wait for the test
    tools), the second adds the test extra and runs the tests."""
    script = (REPO / ".ci" / "run").read_text()
    reading = re.search(r"^commands=\$\((awk .*)\)$", script, re.MULTILINE)
    assert reading and "sed -n 1p" in script and "sed -n 2p" in script, "how .ci/run reads the README changed"
    lines = subprocess.run(["bash", "-c", reading.group(1)], cwd=REPO, capture_output=True, text=True,
                           check=True).stdout.splitlines()
    assert lines == [INSTALL, TEST_LINE]
    assert "pip install -e . &&" in lines[0] and "[" not in lines[0].split("&&")[1]  # no extra on the first install
    assert "pip install -e '.[test]'" in lines[1] and lines[1].endswith(REALTIME_PHASE)
    assert all(f'"{command}"' in script for command in SLOW_PHASES), "CI's slow phases are not the README's"


def test_the_real_time_tests_are_a_phase_of_their_own() -> None:
    """The four phases (pyproject's addopts, the README's real-time phase, CI's two slow ones) split the tests
    by their two markers, each test in exactly one, as pytest itself reads the expressions; the real-time
    phase holds the live robots' tracking tests and not the pacer's unit tests (no pacing in them)."""
    from _pytest.mark.expression import Expression

    addopts = re.search(r"-m '([^']+)'", tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["pytest"]
                        ["ini_options"]["addopts"]).group(1)
    phases = [Expression.compile(expression) for expression in
              (addopts, *(re.search(r"-m '([^']+)'", command).group(1) for command in (REALTIME_PHASE, *SLOW_PHASES)))]
    for marks in ({"slow", "realtime"}, {"slow"}, {"realtime"}, set()):
        chosen = [phase.evaluate(lambda name, *_, marks=marks: name in marks) for phase in phases]
        assert chosen.count(True) == 1, (marks, chosen)
    listed = subprocess.run([sys.executable, "-m", "pytest", "-q", "--collect-only", "-n", "0", "-m", "realtime",
                             "tests/test_hil.py", "tests/test_ros2.py"], cwd=REPO, capture_output=True, text=True)
    assert listed.returncode == 0, listed.stdout[-2000:] + listed.stderr[-2000:]
    assert "tests/test_hil.py::test_live_robot_tracks_the_all_fmu_run" in listed.stdout
    assert "tests/test_hil.py::test_noisy_late_robot_still_converges" in listed.stdout
    assert "tests/test_ros2.py::test_ros2_robot_tracks_the_all_fmu_run[bridge_dds]" in listed.stdout
    assert "test_pacer" not in listed.stdout and "test_pose_stamped" not in listed.stdout


def test_what_the_docs_commands_write_into_the_checkout_is_ignored_by_git() -> None:
    """A newcomer following the docs in the repository's folder gets no untracked packages, traces or FMUs
    in `git status` (docs/fmus.md writes platoon.ssp there); the figures docs/ shows are the exception."""
    written = {match for block in BLOCKS for command in block.commands
               for match in re.findall(r"--out[ =](\S+\.(?:ssp|mcap|fmu))\b", command)}
    written |= {"platoon.ssp", "runs/x.mcap", "build/fmus/Vehicle.fmu"}  # export-ssp's default name, a run's, a build's
    inside = sorted(path for path in written if not path.startswith(("/", "$")))
    assert any(path.endswith(".ssp") for path in inside), inside
    checked = subprocess.run(["git", "check-ignore", "--no-index", "--verbose", "--non-matching", *inside], cwd=REPO,
                             capture_output=True, text=True)
    not_ignored = [line.split("\t")[-1] for line in checked.stdout.splitlines() if line.startswith("::")]
    assert not not_ignored, f"not ignored by .gitignore: {not_ignored}"


def test_the_dask_extra_the_docs_install_exists() -> None:
    """docs/sweeps.md installs ``platoon-cosim[dask]``: the extra must be declared."""
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert "dask" in extras


def test_ctrl_c_exit_status_is_what_the_docs_say(tmp_path: Path) -> None:
    """A real Ctrl-C (SIGINT to the process) and SIGTERM: the exit status docs/config.md and
    docs/trace-format.md both give, 128 + the signal number."""
    config_md = (REPO / "docs" / "config.md").read_text()
    trace_md = (REPO / "docs" / "trace-format.md").read_text()
    config_row = next(line for line in config_md.splitlines() if line.startswith("|") and "SIGINT (Ctrl-C)" in line)
    trace_row = next(line for line in trace_md.splitlines() if line.startswith("| SIGINT (Ctrl-C) or SIGTERM |"))
    for signum in (signal.SIGINT, signal.SIGTERM):
        trace = tmp_path / f"{signum.name}.mcap"
        run = subprocess.Popen(["platoon", "run", str(REPO / "configs/paper/platoon.toml"), "--allow-long", "-q",
                                "--set", "simulation.stop_time=100000", "--out", str(trace)], cwd=tmp_path,
                               env=_env(REPO), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               # SIGINT at its default, as a shell gives it (a suite started in the background
                               # hands it down ignored, and the run keeps what it is given)
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        aside = trace.with_name(trace.name + ".partial")
        deadline = time.monotonic() + 60
        while not (aside.is_file() and aside.stat().st_size > 0) and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        run.send_signal(signum)
        _, stderr = run.communicate(timeout=60)
        assert run.returncode == 128 + signum, stderr
        assert trace.is_file()  # finalized up to the stop
        code = str(run.returncode)
        assert code in config_row.split("|")[1], config_row
        assert f"{code} ({signum.name})" in trace_row, trace_row
