"""The real parts a lab puts between a run and its robots: the Zenoh router zenohd 1.10.2 (rmw_zenohd is one)
and zenoh-plugin-ros2dds 1.10.2 (the DDS bridge of a DDS-based ROS 2 graph, loaded by zenohd), built once per
machine into a cache outside the repository by tools/build-zenoh-cache.sh (docs/hil.md, "A real router and DDS
bridge"). Slow tests: each drives a 10 s run through them; they skip, saying how to build, without the cache,
except where ``PLATOON_REQUIRE_ROUTER=1`` (CI, ``.ci/run``, which builds the cache first): there a missing part
fails. A run that fell behind its pacing skips the tracking bound only, after the checks that need no pacing
(the exit status, the robot's command count, its final stop).

Everything stays on this machine: the router listens on 127.0.0.1 with multicast scouting off, and DDS is
confined to loopback without multicast (``tests.dds_robot.LOOPBACK_ONLY``) in a DDS domain of its own.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import pytest

from bridge.session import SessionError, open_session, zenoh_config
from tests.conftest import free_port
from tests.dds_robot import LOOPBACK_ONLY
from tests.test_hil import all_fmu_reference, ran, tracked, wait_for
from tests.test_ros2 import ROS3, Emulator, _env, _run, endpoint, stop_process

VERSION = "1.10.2"
CACHE = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "platoon-cosim" / f"zenoh-{VERSION}"
ZENOHD = CACHE / "bin" / "zenohd"
PLUGIN = CACHE / "lib" / "libzenoh_plugin_ros2dds.so"
BUILD = ("tools/build-zenoh-cache.sh (cargo, cmake and libclang; 33 min of CPU, most of an hour or more of wall time on 2 "
         "cores)")

pytestmark = pytest.mark.slow


def _needs(*paths: Path) -> None:
    missing = [str(path) for path in paths if not path.exists()]
    if missing:
        _unavailable(f"{', '.join(missing)} not built: run {BUILD}")


def _track(attempt: Callable[[int], Path], reference: Path) -> str | None:
    """``tests.test_hil.tracked``, but a skip for pacing (every try fell behind) is returned, not raised: the
    caller asserts what needs no pacing first, then skips with it (``_skip_if_behind``)."""
    try:
        tracked(attempt, reference)
    except pytest.skip.Exception as skipped:
        return str(skipped)
    return None


def _skip_if_behind(behind: str | None) -> None:
    if behind is not None:
        pytest.skip(f"{behind} (the checks that need no pacing passed)")


def _final_stop(log: str) -> bool:
    """The DDS robot's last Twist was a stop (tests/dds_robot.py prints it when it ends)."""
    return "dds robot: last command 0.0 0.0" in log


class Router:
    """``zenohd`` on tcp/127.0.0.1:``port``, multicast scouting off, optionally with the ros2dds plugin for
    DDS ``domain``; its log in ``folder``. Ready once a client session reaches it (an event, not a wait)."""

    def __init__(self, folder: Path, domain: int | None = None) -> None:
        self.port = free_port()
        config: dict = {"mode": "router", "listen": {"endpoints": [endpoint(self.port)]},
                        "scouting": {"multicast": {"enabled": False}}}
        if domain is not None:
            config["plugins_loading"] = {"enabled": True, "search_dirs": [str(PLUGIN.parent)]}
            config["plugins"] = {"ros2dds": {"domain": domain}}
        path = folder / "zenohd.json5"
        path.write_text(json.dumps(config))
        self.log = folder / "zenohd.log"
        env = {**os.environ, "CYCLONEDDS_URI": LOOPBACK_ONLY, "ROS_DISTRO": "jazzy",
               "RUST_LOG": "warn,zenoh_plugin_ros2dds=info"}
        with open(self.log, "w") as stream:
            self.process = subprocess.Popen([str(ZENOHD), "-c", str(path)], env=env, stdout=stream,
                                            stderr=subprocess.STDOUT)
        wait_for(self._answers, lambda: f"zenohd answers on {endpoint(self.port)}: {self.log.read_text()[-2000:]}",
                 self.process, seconds=30)

    def _answers(self) -> bool:
        try:
            with open_session(zenoh_config(connect=[endpoint(self.port)], mode="client", connect_wait=0.5), "probe"):
                return True
        except SessionError:
            return False

    def stop(self) -> str:
        return stop_process(self.process, self.log)


@contextmanager
def _router(folder: Path, domain: int | None = None) -> Iterator[Router]:
    router = Router(folder, domain)
    try:
        yield router
    finally:
        router.stop()


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return all_fmu_reference(ROS3, tmp_path_factory.mktemp("reference") / "fmu.mcap")


@pytest.mark.realtime
def test_a_run_in_client_mode_through_zenohd_tracks_as_against_the_emulator(tmp_path: Path, reference: Path) -> None:
    """zenohd where rmw_zenohd listens; the emulator speaking rmw_zenoh as a robot's nodes do (a peer that
    listens on loopback and connects to the router); the run with the shipped config and its defaults (a ROS 2
    vehicle that only connects joins in client mode). The platoon converges as against the emulator directly
    (tests/test_hil.py: the same capped bound; only a run that fell behind is tried again)."""
    _needs(ZENOHD)
    logs: list[str] = []

    def attempt(index: int) -> Path:
        trace = tmp_path / f"routed-{index}.mcap"
        with _router(tmp_path) as router:  # the emulator listens on its own port and connects to the router
            robot = Emulator(free_port(), tmp_path, "rmw_zenoh", f'vehicles.3.listen=["{endpoint(router.port)}"]')
            try:
                run = _run(trace, 10.0, f'vehicles.3.connect=["{endpoint(router.port)}"]')
                out, err = run.communicate(timeout=120)
            finally:
                logs.append(robot.stop())
            ran(run.returncode, err, logs[-1] + router.log.read_text()[-2000:])
            assert "vehicle3" in out
        return trace

    behind = _track(attempt, reference)
    assert "running -> stopped (stop command)" in logs[-1], logs[-1]
    _skip_if_behind(behind)


def test_behind_zenohd_a_peer_run_gets_no_pose_and_the_hint_names_client_mode(tmp_path: Path) -> None:
    """What a lab met: the robot's nodes as rmw_zenoh makes them (peers listening on loopback, connected to the
    router), the run in peer mode (a zenoh_config saying so): the robot's graph is there, no pose arrives, and
    the failure says a run behind a router must be a client. The same run with the defaults starts."""
    _needs(ZENOHD)
    peer = tmp_path / "peer.json5"
    peer.write_text('{ mode: "peer" }')
    with _router(tmp_path) as router:
        robot = Emulator(free_port(), tmp_path, "rmw_zenoh", f'vehicles.3.listen=["{endpoint(router.port)}"]')
        try:
            runs = [_run(tmp_path / f"{name}.mcap", 1.0, f'vehicles.3.connect=["{endpoint(router.port)}"]',
                         "hil.connect_timeout=3", *sets)
                    for name, sets in (("peer", [f'vehicles.3.zenoh_config="{peer}"']), ("client", []))]
            (_, peer_err), (_, client_err) = [run.communicate(timeout=60) for run in runs]
        finally:
            robot.stop()
    assert runs[0].returncode == 1 and "no valid pose on /vrpn_mocap/m3pi_3/pose" in peer_err, peer_err
    assert "(0 received, 0 dropped" in peer_err and "the run must join in client mode" in peer_err, peer_err
    assert runs[1].returncode == 0, client_err


def _dds_robot(domain: int, folder: Path) -> subprocess.Popen:
    log = folder / "dds-robot.log"
    env = {**_env(), "CYCLONEDDS_URI": LOOPBACK_ONLY}
    stream = open(log, "w")
    process = subprocess.Popen([sys.executable, "-m", "tests.dds_robot", str(ROS3), str(domain)],
                               cwd=Path(__file__).resolve().parents[1], env=env, stdout=stream,
                               stderr=subprocess.STDOUT)
    stream.close()
    process.log = log  # type: ignore[attr-defined]
    wait_for(lambda: "dds robot: ready" in log.read_text(), lambda: f"the DDS robot: {log.read_text()}", process)
    return process


@pytest.mark.realtime
def test_a_dds_robot_driven_through_zenohd_and_the_ros2dds_plugin_tracks_as_against_the_emulator(
        tmp_path: Path, reference: Path) -> None:
    """A ROS 2 robot on DDS (CycloneDDS: PoseStamped out on rt/vrpn_mocap/m3pi_3/pose, Twist in on
    rt/m3pi_3/cmd_vel, its node announced on ros_discovery_info) behind zenohd with zenoh-plugin-ros2dds, as
    zenoh-bridge-ros2dds deploys it; the run with the shipped config, convention bridge_dds. It converges
    within the emulator runs' bound, and the robot counted the run's commands."""
    pytest.importorskip("cyclonedds", reason="the DDS-side robot needs the cyclonedds wheel (pip install cyclonedds)")
    _needs(ZENOHD, PLUGIN)
    domain = random.Random().randrange(1, 200)  # a DDS domain of its own: another test run here never meets it
    logs: list[str] = []

    def attempt(index: int) -> Path:
        trace = tmp_path / f"dds-{index}.mcap"
        with _router(tmp_path, domain) as router:
            robot = _dds_robot(domain, tmp_path)
            try:
                run = _run(trace, 10.0, f'vehicles.3.connect=["{endpoint(router.port)}"]',
                           "vehicles.3.ros2.convention=bridge_dds")
                out, err = run.communicate(timeout=120)
            finally:
                robot.terminate()
                robot.wait(10)
                logs.append(robot.log.read_text())  # type: ignore[attr-defined]
            ran(run.returncode, err, logs[-1] + router.log.read_text()[-3000:])
        return trace

    behind = _track(attempt, reference)
    received = int(logs[-1].rsplit("commands received ", 1)[1].split()[0])
    assert received >= 900, logs[-1]  # one Twist per 10 ms step for 10 s, and the stops
    assert _final_stop(logs[-1]), logs[-1]
    _skip_if_behind(behind)


DOCUMENTED_PORT = 7447  # configs/hil/zenohd-local.json5, as docs/hil.md runs it


def test_the_documented_dds_block_runs_as_written(tmp_path: Path) -> None:
    """docs/hil.md, "A real router and DDS bridge": its DDS block as a lab runs it, line by line in one shell
    (tests/test_docs_commands.py's ROUTER_BLOCKS hold the lines to the docs): zenohd with the shipped
    configs/hil/zenohd-local.json5 on 127.0.0.1:7447 and the plugin by ``-P ros2dds`` (ROS domain 0, its
    defaults), the DDS robot, and the 10 s run with the shipped config. The run exits 0, the robot counted
    its commands and the last was a stop, and zenohd's log shows the plugin's routes as the docs quote them."""
    import socket

    from tests.test_docs_commands import ROUTER_BLOCKS

    pytest.importorskip("cyclonedds", reason="the DDS-side robot needs the cyclonedds wheel (pip install cyclonedds)")
    _needs(ZENOHD, PLUGIN)
    with socket.socket() as probe:  # as written, the block needs 7447 free on this machine
        if probe.connect_ex(("127.0.0.1", DOCUMENTED_PORT)) == 0:
            _unavailable(f"127.0.0.1:{DOCUMENTED_PORT} is taken: the documented block cannot run as written")
    export, router, robot, run = ROUTER_BLOCKS[4:8]
    script = "\n".join([export, router, robot, run + '\necho "run exit $?"', "kill %2 %1", "wait"])
    done = subprocess.run(["bash", "-c", script], cwd=Path(__file__).resolve().parents[1], env=_env(),
                          capture_output=True, text=True, timeout=300)
    out = done.stdout + done.stderr
    assert "run exit 0" in out, out[-4000:]
    received = int(out.rsplit("commands received ", 1)[1].split()[0])
    assert received >= 900, out[-4000:]  # one Twist per 10 ms step for 10 s, and the stops
    assert _final_stop(out), out[-4000:]
    for line in ("Discovered ROS Node /m3pi_3_base", "Route Subscriber (Zenoh:m3pi_3/cmd_vel -> ROS:/m3pi_3/cmd_vel)",
                 "Route Publisher (ROS:/vrpn_mocap/m3pi_3/pose -> Zenoh:vrpn_mocap/m3pi_3/pose)"):
        assert line in out, f"{line!r} not in zenohd's log: {out[-4000:]}"


def _unavailable(reason: str) -> None:
    """Skip, or fail where the router tests are required (CI: ``PLATOON_REQUIRE_ROUTER=1``)."""
    if os.environ.get("PLATOON_REQUIRE_ROUTER") == "1":
        pytest.fail(reason)
    pytest.skip(reason)
