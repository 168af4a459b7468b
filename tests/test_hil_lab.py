"""A secure lab: ``platoon hil-certs``, mutual TLS and Zenoh's access control, on 127.0.0.1 with real processes.

The lab of these tests: run host ``laptop`` drives robot 3, run host ``desk`` robot 5, and ``xbee-pc``
is the robot side of both (the emulator). ``desk`` is the insider: a valid certificate of the lab,
but not robot 3's role. The outsiders have no certificate of the lab at all.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import pytest
import zenoh
from cryptography import x509

from bridge.lab import Lab, make_ca, make_host_certificate, pem, zenoh_lab_config
from orchestrator.support.lab_files import write_lab
from bridge.session import SessionError, open_session, zenoh_config
from tests.conftest import free_port
from orchestrator.trace import load
from tests.test_hil import (KEYS, LIVE3, PATIENT, PLATOON, REPO, _env, all_fmu_reference, finish, ran, tracked,
                            start_run, stranger_commands, wait_for_running)

LAB = Lab(run_hosts={"laptop": {3}, "desk": {5}}, robot_sides={"xbee-pc": {3, 5}},
          addresses={"xbee-pc": ["192.168.1.20", "xbee-pc.lab"]})


def test_hil_certs_writes_a_ca_and_host_configs_that_zenoh_takes_and_keeps_the_ca_when_hosts_are_added(
        tmp_path: Path) -> None:
    folder = tmp_path / "lab"
    made = subprocess.run([str(PLATOON), "hil-certs", str(folder), "--run-host", "laptop=3", "--robot-side",
                           "xbee-pc=3", "--address", "xbee-pc=192.168.1.20"], cwd=REPO, env=_env(),
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    assert "new lab CA" in made.stdout and "keep it off the lab's machines" in made.stdout
    ca = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    for host in ("laptop", "xbee-pc"):
        path = folder / f"{host}.json5"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600  # it holds the host's private key
        zenoh_config(connect=["tls/127.0.0.1:7447"], config_file=str(path))  # Zenoh parses it
    assert stat.S_IMODE((folder / "ca.key").stat().st_mode) == 0o600
    assert stat.S_IMODE((folder / "lab.key").stat().st_mode) == 0o600 and stat.S_IMODE(folder.stat().st_mode) == 0o700
    lab_key = (folder / "lab.key").read_bytes()
    unasked = subprocess.run([str(PLATOON), "hil-certs", str(folder), "--run-host", "laptop=3", "--robot-side",
                              "xbee-pc=3"], cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert unasked.returncode == 2 and "a CA is already there" in unasked.stderr, unasked.stderr  # never used unasked
    added = subprocess.run([str(PLATOON), "hil-certs", str(folder), "--run-host", "laptop=3", "--run-host", "desk=5",
                            "--robot-side", "xbee-pc=3,5", "--ca", str(folder / "ca.pem")], cwd=REPO, env=_env(),
                           capture_output=True, text=True, timeout=60)
    assert added.returncode == 0 and f"lab CA {folder / 'ca.pem'}" in added.stdout, added.stderr
    assert (folder / "lab.key").read_bytes() == lab_key  # the hosts already set up keep theirs
    assert (folder / "ca.pem").read_bytes() == ca.public_bytes(__import__("cryptography").hazmat.primitives
                                                               .serialization.Encoding.PEM)
    bad = subprocess.run([str(PLATOON), "hil-certs", str(folder), "--run-host", "laptop", "--robot-side", "x=3"],
                         cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--run-host 'laptop': expected HOST=ROBOT[,ROBOT...]" in bad.stderr


def test_host_certificates_chain_to_the_lab_ca_and_name_the_host_and_its_addresses() -> None:
    ca_key, ca = make_ca(30)
    _, certificate = make_host_certificate(ca_key, ca, "xbee-pc", ["192.168.1.20", "xbee-pc.lab"], 30)
    certificate.verify_directly_issued_by(ca)
    assert certificate.subject.rfc4514_string() == "CN=xbee-pc"
    names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {str(ip) for ip in names.get_values_for_type(x509.IPAddress)} == {"192.168.1.20", "127.0.0.1", "::1"}
    assert set(names.get_values_for_type(x509.DNSName)) == {"xbee-pc", "xbee-pc.lab", "localhost"}


def test_the_acl_lets_only_robot_3s_run_host_command_it_and_only_its_robot_side_report_it() -> None:
    acl = zenoh_lab_config(LAB, "xbee-pc", b"ca", b"cert", b"key")["access_control"]
    assert acl["default_permission"] == "deny"
    subjects = {subject["id"]: subject["cert_common_names"] for subject in acl["subjects"]}
    rules = {rule["id"]: rule for rule in acl["rules"]}
    assert subjects["commands in 3"] == ["laptop"] and subjects["commands in 5"] == ["desk"]
    assert rules["commands in 3"]["key_exprs"] == ["platoon/m3pi/3/cmd/wheels", "platoon/m3pi/3/host/*"]
    assert rules["commands in 3"]["flows"] == ["ingress"]
    laptop = zenoh_lab_config(LAB, "laptop", b"ca", b"cert", b"key")["access_control"]
    assert {subject["id"]: subject["cert_common_names"] for subject in laptop["subjects"]}["observations in 3"] \
        == ["xbee-pc"]
    assert not any(rule["id"].endswith(" 5") for rule in laptop["rules"])  # laptop has no business with robot 5


@pytest.mark.parametrize("endpoint, allowed", [
    ("tcp/192.168.1.20:7447", False), ("udp/10.0.0.7:7447", False), ("tcp/[::]:0", False), ("tcp/0.0.0.0:7447", False),
    ("tcp/lab-pc.local:7447", False), ("tcp/127.0.0.1:7447", True), ("tcp/localhost:7447", True),
    ("tcp/[::1]:7447", True), ("tls/192.168.1.20:7447", True), ("quic/192.168.1.20:7447", True),
])
def test_an_endpoint_off_this_machine_without_tls_is_refused_naming_the_recipe(endpoint: str, allowed: bool) -> None:
    if allowed and endpoint.startswith(("tls/", "quic/")):  # allowed, once a zenoh_config gives the certificates
        with pytest.raises(SessionError, match=f"endpoint {endpoint} is TLS but no zenoh_config gives its certificates"):
            zenoh_config(connect=[endpoint])
    elif allowed:
        zenoh_config(connect=[endpoint])
    else:
        with pytest.raises(SessionError, match=f"endpoint {endpoint.replace('[', '.').replace(']', '.')} leaves this "
                                               "machine without TLS.*platoon hil-certs.*allow_insecure = true"):
            zenoh_config(listen=[endpoint])
        zenoh_config(connect=[endpoint], allow_insecure=True)


def test_a_run_refuses_an_insecure_endpoint_unless_the_config_allows_it(tmp_path: Path) -> None:
    refused = start_run(free_port(), tmp_path / "refused.mcap", 1.0, 'vehicles.3.connect=["tcp/192.0.2.1:7447"]')
    code, _, err = finish(refused, timeout=60)
    assert code == 1 and "endpoint tcp/192.0.2.1:7447 leaves this machine without TLS" in err, err
    allowed = start_run(free_port(), tmp_path / "allowed.mcap", 1.0, 'vehicles.3.connect=["tcp/192.0.2.1:7447"]',
                        "hil.allow_insecure=true", "hil.connect_timeout=0.5")  # TEST-NET: nobody answers
    code, _, err = finish(allowed, timeout=60)
    assert code == 1 and "did not appear within 0.5 s" in err, err


def test_a_tls_endpoint_needs_a_zenoh_config_and_a_tls_robot_that_does_not_appear_names_the_certificates(
        tmp_path: Path) -> None:
    """A tls/ endpoint without certificates cannot work: refused before connecting (not a 10 s wait asking
    whether the emulator runs). With the lab's certificates and nobody (or a robot side that refuses them)
    at the other end, the failure names TLS and the certificates as the likely cause."""
    tls = f"tls/127.0.0.1:{free_port()}"
    started = time.monotonic()
    code, _, err = finish(start_run(free_port(), tmp_path / "bare.mcap", 1.0, f'vehicles.3.connect=["{tls}"]'), 60)
    assert code == 1 and f"endpoint {tls} is TLS but no zenoh_config gives its certificates" in err, err
    assert "platoon hil-certs" in err and time.monotonic() - started < 10.0  # refused, not waited for
    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    code, _, err = finish(start_run(free_port(), tmp_path / "absent.mcap", 1.0, f'vehicles.3.connect=["{tls}"]',
                                    f'vehicles.3.zenoh_config="{folder / "laptop.json5"}"', "hil.connect_timeout=1"), 60)
    assert code == 1 and "did not appear within 1 s" in err, err
    assert "over TLS the likely cause is the certificates" in err, err


def _peers(session) -> list:
    return list(session.info.peers_zid())


def _without_certificates(tls: str):
    """A session config that connects to ``tls`` with no certificate at all (``zenoh_config`` refuses to build
    one: this is an outsider's own config)."""
    config = zenoh_config(connect=["tcp/127.0.0.1:" + tls.rsplit(":", 1)[1]])
    config.insert_json5("connect/endpoints", json.dumps([tls]))
    return config


def _outsiders(folder: Path, tls: str) -> list[tuple[str, object]]:
    """Sessions that try to reach the robot side: plain, TLS without a certificate, and a certificate named
    like the lab's run host but from another CA."""
    foreign_key, foreign_ca = make_ca(1, "not the lab")
    key, certificate = make_host_certificate(foreign_key, foreign_ca, "laptop", [], 1)
    impostor = folder / "impostor.json5"
    impostor.write_text(json.dumps(zenoh_lab_config(LAB, "laptop", pem(foreign_ca), pem(certificate), pem(key))))
    port = tls.rsplit(":", 1)[1]
    return [("plain tcp", zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])),
            ("tls without a certificate", _without_certificates(tls)),
            ("a certificate of another CA", zenoh_config(connect=[tls], config_file=str(impostor)))]


@pytest.mark.realtime
def test_with_tls_and_acl_strangers_cannot_connect_or_drive_and_the_platoon_tracks_as_without(tmp_path: Path) -> None:
    """The emulator as lab host xbee-pc on tls/127.0.0.1, the run as laptop. Outsiders never get a
    session; desk (a valid certificate, not robot 3's run host) connects but its claim token and
    commands never reach the robot side, and it hears none of robot 3's messages. The 10 s live run matches the all-FMU run to 3 mm, as
    over plain TCP (test_hil.py::test_live_robot_tracks_the_all_fmu_run)."""
    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    tls = f"tls/127.0.0.1:{free_port()}"
    log = tmp_path / "emulator.log"
    with open(log, "w") as stream:
        robot = subprocess.Popen([str(PLATOON), "m3pi-emulator", "--config", str(LIVE3), "--set",
                                  f'vehicles.3.connect=["{tls}"]', "--zenoh-config", str(folder / "xbee-pc.json5")],
                                 cwd=REPO, env=_env(), stdout=stream, stderr=subprocess.STDOUT)
    sessions = []
    try:
        deadline = time.monotonic() + 30
        while "configured, pose on" not in log.read_text():
            assert robot.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        desk = open_session(zenoh_config(connect=[tls], config_file=str(folder / "desk.json5")), "desk")
        sessions.append(desk)
        outsiders = [(what, open_session(config, what)) for what, config in _outsiders(folder, tls)]
        sessions += [session for _, session in outsiders]
        deadline = time.monotonic() + 10
        while not _peers(desk):  # the insider gets a session: TLS itself works
            assert time.monotonic() < deadline, "desk, a lab host, could not connect"
            time.sleep(0.05)
        token = desk.liveliness().declare_token(KEYS.host(0x5757_5757_5757_5757))  # noqa: F841 (held)
        overheard: list[str] = []  # robot 3's keys are sent to robot 3's hosts only
        listeners = [desk.declare_subscriber(key, lambda sample: overheard.append(str(sample.key_expr)),  # noqa: F841
                                             allowed_origin=zenoh.Locality.REMOTE)  # not its own puts
                     for key in (KEYS.pose, KEYS.wheels, KEYS.status)]
        for _, session in [("desk", desk), *outsiders]:
            stranger_commands(session, 0x5757_5757_5757_5757)
        trace = tmp_path / "tls.mcap"
        run = start_run(0, trace, 10.0, f'vehicles.3.connect=["{tls}"]',
                        f'vehicles.3.zenoh_config="{folder / "laptop.json5"}"', *PATIENT)
        wait_for_running(log, run)  # the strangers try again while the run drives the robot
        for _, session in [("desk", desk), *outsiders]:
            stranger_commands(session, 0x5757_5757_5757_5757)
        code, out, err = finish(run)
        assert code == 0, err
        assert overheard == []
        assert {what: _peers(session) for what, session in outsiders} == {what: [] for what, _ in outsiders}
        stats = json.loads(load(trace).metadata["platoon.hil"]["vehicle3"])
        assert stats["command.foreign"] == 0 and stats["command.invalid"] == 0 and stats["pose.dropped.foreign"] == 0

        def attempt(index: int) -> Path:  # a run that fell too far behind to test tracking: another, as laptop
            if index == 0:
                return trace
            again = tmp_path / f"tls-{index}.mcap"
            code, _, err = finish(start_run(0, again, 10.0, f'vehicles.3.connect=["{tls}"]',
                                            f'vehicles.3.zenoh_config="{folder / "laptop.json5"}"', *PATIENT))
            ran(code, err)
            return again

        tracked(attempt, all_fmu_reference(LIVE3, tmp_path / "fmu.mcap"))
    finally:
        for session in sessions:
            session.close()
        robot.terminate()
        robot.wait(10)
    emulator_log = log.read_text()
    assert "5757575757575757" not in emulator_log and "refused" not in emulator_log, emulator_log
    assert "commands received" in emulator_log and "foreign=" not in emulator_log, emulator_log


def hil_certs(folder: Path, *options: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(PLATOON), "hil-certs", str(folder), "--run-host", "laptop=3", "--robot-side", "xbee-pc=3",
                           *options], cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("options, problem", [
    (("--address", "laptop=héllo.example"), "is neither an IP address nor a DNS name"),
    (("--address", "laptop=bad name"), "is neither an IP address nor a DNS name"),
    (("--address", "laptop=*"), "is neither an IP address nor a DNS name"),
    (("--address", "laptop=*.lab.example"), "is neither an IP address nor a DNS name"),
    (("--days", "4000000"), "--days 4000000: expected 1 to 3650"),
    (("--days", "0"), "--days 0: expected 1 to 3650"),
    (("--run-host", "desk=99999999999999999999"), "robot ids go from 0 to 2147483647"),
])
def test_hil_certs_bad_input_is_one_line_exit_2_and_leaves_nothing(tmp_path: Path, options: tuple, problem: str) -> None:
    made = hil_certs(tmp_path / "lab", *options)
    assert made.returncode == 2 and problem in made.stderr, made.stderr
    assert len(made.stderr.strip().splitlines()) == 1 and "Traceback" not in made.stderr
    assert not (tmp_path / "lab").exists()


def test_hil_certs_never_writes_through_a_link_or_onto_a_fifo_or_folder(tmp_path: Path) -> None:
    folder = tmp_path / "lab"
    folder.mkdir(mode=0o700)
    victim = tmp_path / "victim.txt"
    victim.write_text("mine\n")
    (folder / "laptop.json5").symlink_to(victim)
    linked = hil_certs(folder)
    assert linked.returncode == 2 and "is a symbolic link" in linked.stderr, linked.stderr
    assert victim.read_text() == "mine\n" and sorted(p.name for p in folder.iterdir()) == ["laptop.json5"]
    (folder / "laptop.json5").unlink()
    os.mkfifo(folder / "laptop.json5")
    fifo = hil_certs(folder)  # would hang if it opened the FIFO
    assert fifo.returncode == 2 and "not a regular file" in fifo.stderr, fifo.stderr
    (folder / "laptop.json5").unlink()
    (folder / "laptop.json5").mkdir()
    made = hil_certs(folder)
    assert made.returncode == 2 and "not a regular file" in made.stderr and "Errno" not in made.stderr, made.stderr


def test_hil_certs_refuses_a_folder_others_can_write_and_rewrites_an_open_key_file_0600(tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)  # as /tmp/lab made by another user would let them swap the CA
    made = hil_certs(shared)
    assert made.returncode == 2 and "others may write in it" in made.stderr and list(shared.iterdir()) == []
    from orchestrator.support.lab_files import own_group

    shared.chmod(0o770)  # group-writable: fine only if the group is the user's own private group (umask 002)
    grouped = hil_certs(shared)
    assert grouped.returncode == (0 if own_group(shared.stat().st_gid) else 2), grouped.stderr
    folder = tmp_path / "lab"
    assert hil_certs(folder).returncode == 0
    (folder / "laptop.json5").chmod(0o644)
    again = hil_certs(folder, "--ca", str(folder / "ca.pem"))
    assert again.returncode == 0, again.stderr
    assert stat.S_IMODE((folder / "laptop.json5").stat().st_mode) == 0o600  # a new private key is never left 0644
    (folder / "ca.key").chmod(0o644)
    opened = hil_certs(folder, "--ca", str(folder / "ca.pem"))
    assert opened.returncode == 2 and "only you can read (mode 0600)" in opened.stderr


def test_hil_certs_never_turns_one_lab_into_another_and_refuses_an_expired_ca(tmp_path: Path) -> None:
    """The issue's cases: `--ca OTHER/ca.pem` into an existing lab replaced its CA and lab key while its ca.key
    stayed (exit 0); a CA expired 35 days ago signed certificates every handshake refuses. Both now exit 2
    with one line and write nothing; adding hosts to a lab (its own CA, or OTHER's in a new DIR) still works."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    from bridge.lab import make_ca, pem

    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    assert hil_certs(ours).returncode == 0 and hil_certs(theirs).returncode == 0
    before = {path.name: path.read_bytes() for path in ours.iterdir()}
    mixed = hil_certs(ours, "--ca", str(theirs / "ca.pem"))
    assert mixed.returncode == 2 and len(mixed.stderr.strip().splitlines()) == 1, mixed.stderr
    assert "DIR is another lab (its own CA)" in mixed.stderr and f"--ca {ours / 'ca.pem'}" in mixed.stderr
    assert {path.name: path.read_bytes() for path in ours.iterdir()} == before  # nothing written
    assert hil_certs(ours, "--ca", str(ours / "ca.pem")).returncode == 0
    assert hil_certs(tmp_path / "more", "--ca", str(theirs / "ca.pem")).returncode == 0

    old = tmp_path / "old"
    old.mkdir(mode=0o700)
    key, _ = make_ca(1)
    now = datetime.datetime.now(datetime.timezone.utc)
    name = x509.Name([x509.NameAttribute(x509.NameOID.COMMON_NAME, "expired lab CA")])
    expired = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
               .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(days=400))
               .not_valid_after(now - datetime.timedelta(days=35))
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True).sign(key, hashes.SHA256()))
    (old / "ca.pem").write_bytes(pem(expired))
    (old / "ca.key").write_bytes(pem(key))
    (old / "ca.key").chmod(0o600)
    refused = hil_certs(tmp_path / "new", "--ca", str(old / "ca.pem"))
    assert refused.returncode == 2 and "the lab CA expired on" in refused.stderr and "(35 days ago)" in refused.stderr, \
        refused.stderr
    assert not (tmp_path / "new").exists()


def test_hil_certs_writes_the_ca_certificate_writable_by_no_one_else_whatever_the_umask(tmp_path: Path) -> None:
    made = subprocess.run([str(PLATOON), "hil-certs", str(tmp_path / "lab"), "--run-host", "laptop=3", "--robot-side",
                           "xbee-pc=3"], cwd=REPO,
                          env=_env(), capture_output=True, text=True, timeout=60, preexec_fn=lambda: os.umask(0))
    assert made.returncode == 0, made.stderr
    assert stat.S_IMODE((tmp_path / "lab" / "ca.pem").stat().st_mode) == 0o644  # was 0666
    assert stat.S_IMODE((tmp_path / "lab" / "ca.key").stat().st_mode) == 0o600


def test_hil_certs_on_a_full_disk_names_the_file_and_keeps_the_old_ones(tmp_path: Path) -> None:
    """A 64 KiB tmpfs would need root; RLIMIT_FSIZE makes every write past the limit fail with EFBIG (the child
    ignores SIGXFSZ), the same path through the code as ENOSPC: the error names the file, the old stays whole."""
    import resource
    import signal as signals

    folder = tmp_path / "lab"
    assert hil_certs(folder).returncode == 0
    before = {path.name: path.read_bytes() for path in folder.iterdir()}

    def small_files() -> None:
        signals.signal(signals.SIGXFSZ, signals.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))

    full = subprocess.run([str(PLATOON), "hil-certs", str(folder), "--run-host", "laptop=3", "--robot-side",
                           "xbee-pc=3", "--ca", str(folder / "ca.pem")], cwd=REPO, env=_env(), capture_output=True,
                          text=True, timeout=60, preexec_fn=small_files)
    assert full.returncode == 2 and "cannot write it" in full.stderr and ".json5" in full.stderr, full.stderr
    assert {path.name: path.read_bytes() for path in folder.iterdir()} == before  # no half file, nothing cut
    fresh = tmp_path / "fresh"
    new = subprocess.run([str(PLATOON), "hil-certs", str(fresh), "--run-host", "laptop=3", "--robot-side", "xbee-pc=3"],
                         cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60, preexec_fn=small_files)
    assert new.returncode == 2 and not fresh.exists(), new.stderr  # no lone ca.pem blocking the next try


def _robot_side(folder: Path, listen: str, change: Callable[[dict], None] = lambda config: None):
    """xbee-pc's session (robot 3's robot side) listening on ``listen``, its config changed by ``change``
    (to show what a defence is worth: the same case with that defence off), and the commands it receives."""
    text = (folder / "xbee-pc.json5").read_text()
    config = json.loads(text[text.index("{"):])
    change(config)
    path = folder / "robot-side.json5"
    path.write_text(json.dumps(config))
    session = open_session(zenoh_config(listen=[listen], config_file=str(path)), "robot side")
    received: list[bytes] = []
    held = [session.declare_subscriber(KEYS.wheels, lambda sample: received.append(sample.payload.to_bytes())),
            session.liveliness().declare_token(KEYS.alive)]
    return session, received, held


def _drives(session, received: list[bytes], seconds: float = 3.0) -> bool:
    """Whether ``session``'s commands to robot 3 reach the robot side within ``seconds`` (it puts until they do)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        stranger_commands(session, 0x5757_5757_5757_5757)
        if received:
            return True
        time.sleep(0.05)
    return False


def _lab_client(folder: Path, tls: str, host: str | None, change: Callable[[dict], None]) -> Any:
    """A session connecting to ``tls`` with the lab's CA, as ``host`` (its certificate) or none, changed by ``change``."""
    text = (folder / f"{host or 'laptop'}.json5").read_text()
    config = json.loads(text[text.index("{"):])
    change(config)
    path = folder / f"client-{host}.json5"
    path.write_text(json.dumps(config))
    return open_session(zenoh_config(connect=[tls], config_file=str(path)), f"client {host}")


@pytest.mark.parametrize("mtls, acl", [(True, False), (False, True), (False, False)])
def test_an_outsider_who_trusts_the_lab_ca_but_has_no_certificate_is_kept_out_by_mutual_tls_or_the_acl_alone(
        tmp_path: Path, mtls: bool, acl: bool) -> None:
    """The outsider trusts the lab's CA (it verifies the robot side and would connect) but shows no client
    certificate and keeps no access list of its own. Either defence of the robot side alone keeps it out: its
    demand for a client certificate (its access list off), or its access list (which names the lab's
    hosts by their certificates; client certificates not asked for). With both off (a server certificate
    only, which bridge.session refuses to listen off loopback with) the outsider's commands arrive."""
    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    tls = f"tls/127.0.0.1:{free_port()}"

    def robot_side(config: dict) -> None:  # one defence on, the other off
        config["transport"]["link"]["tls"]["enable_mtls"] = mtls
        config["access_control"]["enabled"] = acl

    def outsider(config: dict) -> None:
        tls_config = config["transport"]["link"]["tls"]
        for name in ("connect_certificate_base64", "connect_private_key_base64", "listen_certificate_base64",
                     "listen_private_key_base64"):
            del tls_config[name]
        tls_config["enable_mtls"] = False
        del config["access_control"]

    side, received, _ = _robot_side(folder, tls, robot_side)
    client = _lab_client(folder, tls, None, outsider)
    try:
        assert _drives(client, received) is not (mtls or acl)
    finally:
        client.close()
        side.close()
    if not mtls:
        with pytest.raises(SessionError, match="needs mutual TLS"):
            zenoh_config(listen=[tls.replace("127.0.0.1", "0.0.0.0")], config_file=str(folder / "robot-side.json5"))


@pytest.mark.parametrize("robot_side_acl", [True, False])
def test_a_lab_host_without_robot_3s_role_and_without_its_own_acl_is_stopped_by_the_robot_sides_acl_alone(
        tmp_path: Path, robot_side_acl: bool) -> None:
    """desk (a valid lab certificate, run host of robot 5 only) drops its own access list: its puts on robot 3's
    keys leave it, and only the robot side's list refuses them. With the robot side's list off too, they arrive."""
    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    tls = f"tls/127.0.0.1:{free_port()}"

    def robot_side(config: dict) -> None:
        config["access_control"]["enabled"] = robot_side_acl

    def insider(config: dict) -> None:
        del config["access_control"]

    side, received, _ = _robot_side(folder, tls, robot_side)
    desk = _lab_client(folder, tls, "desk", insider)
    try:
        deadline = time.monotonic() + 10
        while not _peers(desk):  # it does connect: TLS lets a lab host in
            assert time.monotonic() < deadline, "desk, a lab host, could not connect"
            time.sleep(0.05)
        assert _drives(desk, received) is not robot_side_acl
    finally:
        desk.close()
        side.close()


def test_an_exposed_listener_needs_mutual_tls_and_a_deny_by_default_acl_before_the_session_opens(tmp_path: Path) -> None:
    """TLS checked by more than its scheme: the lab's server certificate without client authentication, or
    without access control, on tls/0.0.0.0 is refused before anything listens, one line naming the recipe;
    the lab's own config is taken; loopback and allow_insecure are as before."""
    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    text = (folder / "xbee-pc.json5").read_text()
    lab_config = json.loads(text[text.index("{"):])
    anywhere = f"tls/0.0.0.0:{free_port()}"
    for what, change in (("mutual TLS", lambda c: c["transport"]["link"]["tls"].update(enable_mtls=False)),
                         ("access control", lambda c: c.pop("access_control")),
                         ("access control", lambda c: c["access_control"].update(default_permission="allow")),
                         ("access control that lets only named hosts put",  # a rule open to a subject of interfaces
                          lambda c: c["access_control"]["subjects"].append({"id": "anyone", "interfaces": ["lo"]})
                          or c["access_control"]["policies"].append({"rules": ["commands in 3"],
                                                                      "subjects": ["anyone"]}))):
        config = json.loads(json.dumps(lab_config))
        change(config)
        path = folder / "weak.json5"
        path.write_text(json.dumps(config))
        with pytest.raises(SessionError, match=f"listening on {anywhere}, off this machine, needs .*{what}") as refused:
            zenoh_config(listen=[anywhere], config_file=str(path))
        assert "platoon hil-certs" in str(refused.value) and "\n" not in str(refused.value)
        zenoh_config(listen=[anywhere], config_file=str(path), allow_insecure=True)
        zenoh_config(listen=["tls/127.0.0.1:7450"], config_file=str(path))
    zenoh_config(listen=[anywhere], config_file=str(folder / "xbee-pc.json5"))
    emulator = subprocess.run([str(PLATOON), "m3pi-emulator", "--config", str(LIVE3), "--listen", anywhere,
                               "--zenoh-config", str(path), "--duration", "1"], cwd=REPO, env=_env(),
                              capture_output=True, text=True, timeout=60)
    assert emulator.returncode == 2 and "needs access control" in emulator.stderr, emulator.stderr
    assert len(emulator.stderr.strip().splitlines()) == 1


NAMESPACE_SCRIPT = '''
import json, subprocess, sys, time
from bridge.protocol import RobotKeys, WheelCommand, decode_pose, encode_wheels
from bridge.session import open_session, zenoh_config
platoon, config, address = sys.argv[1:4]
keys = RobotKeys("platoon", 3)
base = [platoon, "m3pi-emulator", "--config", config, "--set", f'vehicles.3.connect=["tcp/{address}"]']
refused = subprocess.run(base + ["--duration", "1"], capture_output=True, text=True, timeout=60)
robot = subprocess.Popen(base + ["--allow-insecure"], stderr=subprocess.PIPE, text=True)
poses = []
try:
    with open_session(zenoh_config(connect=[f"tcp/{address}"], allow_insecure=True), "stranger") as stranger:
        stranger.declare_subscriber(keys.pose, lambda sample: poses.append(decode_pose(sample.payload.to_bytes())))
        token = stranger.liveliness().declare_token(keys.host(0x5757575757575757))
        publisher = stranger.declare_publisher(keys.wheels)
        deadline = time.monotonic() + 60
        while not (publisher.matching_status.matching and poses):
            assert time.monotonic() < deadline, "the stranger never reached the emulator"
            time.sleep(0.02)
        for seq in range(1, 201):
            now = time.time()
            publisher.put(encode_wheels(WheelCommand(0, now + 1.0, 0.0, 0.0, 0x5757575757575757)))
            publisher.put(encode_wheels(WheelCommand(seq, now + 0.5, 1.0, 1.0, 0x5757575757575757)))
            time.sleep(0.005)
        seen = len(poses)
        while len(poses) < seen + 40:
            time.sleep(0.01)
    run = subprocess.run([platoon, "run", config, "--set", "simulation.stop_time=2", "--set",
                          f'vehicles.3.connect=["tcp/{address}"]', "--set", "hil.allow_insecure=true", "--out",
                          sys.argv[4]], capture_output=True, text=True, timeout=120)
finally:
    robot.terminate()
    log = robot.communicate(timeout=30)[1]
moved = max(((p.x - poses[0].x) ** 2 + (p.y - poses[0].y) ** 2) ** 0.5 for p in poses)
print(json.dumps({"refused": [refused.returncode, refused.stderr], "moved": moved,
                  "claims": sorted({p.claim for p in poses}), "run": [run.returncode, run.stderr], "log": log}))
'''


@pytest.mark.realtime
def test_on_a_trusted_network_a_stranger_without_the_lab_key_moves_the_robot_0_m(tmp_path: Path) -> None:
    """The trusted-network setup, on a real non-loopback address (10.200.0.1 in a private network namespace,
    ``unshare -rn``): the emulator refuses to listen there without TLS unless allow_insecure; with it, a
    stranger who reads nothing (its own token, claim requests, 1 s of full-speed commands, no lab key) moves
    the robot 0.000 m, and a run with the key then drives it."""
    import shutil

    if shutil.which("unshare") is None or shutil.which("ip") is None:
        pytest.skip("needs unshare and ip (util-linux, iproute2) for a private network namespace")
    probe = subprocess.run(["unshare", "-rn", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"no private network namespace here (unshare -rn: {probe.stderr.strip()})")
    script = tmp_path / "namespace.py"
    script.write_text(NAMESPACE_SCRIPT)
    address = f"10.200.0.1:{free_port()}"
    done = subprocess.run(["unshare", "-rn", "sh", "-c", "ip link set lo up && ip addr add 10.200.0.1/32 dev lo && "
                           f'exec "$0" "$@"', sys.executable, str(script), str(PLATOON), str(LIVE3), address,
                           str(tmp_path / "after.mcap")], cwd=REPO, env=_env(), capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["refused"][0] == 2 and "leaves this machine without TLS" in result["refused"][1], result["refused"]
    assert result["moved"] == 0.0 and result["claims"] == [0], result
    assert "claimed by 5757575757575757" not in result["log"] and "MAC does not check" in result["log"]
    assert result["run"][0] == 0, result["run"][1]


def test_a_plain_tcp_run_to_a_tls_robot_side_says_the_far_side_speaks_tls(tmp_path: Path) -> None:
    """The lab's robot side listens on tls/, the run connects with tcp/ to the same port (a forgotten
    recipe): Zenoh's handshake fails in silence, and the run's failure says that the far side answers in TLS and
    how to connect, not whether the emulator runs. A plain Zenoh listener there is not taken for TLS."""
    from bridge.tls_probe import speaks_tls

    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    port = free_port()
    side, _, _ = _robot_side(folder, f"tls/127.0.0.1:{port}")
    try:
        code, _, err = finish(start_run(free_port(), tmp_path / "plain.mcap", 1.0,
                                        f'vehicles.3.connect=["tcp/127.0.0.1:{port}"]', "hil.connect_timeout=1"), 60)
    finally:
        side.close()
    assert code == 1 and "did not appear within 1 s" in err, err
    assert (f"tcp/127.0.0.1:{port} answers in TLS: the robot side listens with TLS there, so connect with "
            f"tls/127.0.0.1:{port} and the lab's zenoh_config") in err, err
    assert "is `platoon m3pi-emulator`" not in err
    plain = free_port()
    with open_session(zenoh_config(listen=[f"tcp/127.0.0.1:{plain}"]), "plain"):
        assert not speaks_tls("127.0.0.1", plain)
    assert not speaks_tls("127.0.0.1", free_port())  # nobody there


def test_an_acl_typo_that_keeps_the_runs_claim_from_its_robot_side_is_named_as_such(tmp_path: Path) -> None:
    """A typo in the robot side's access-control rule for robot 3's commands ("cmd/wheel" for "cmd/wheels"):
    its TLS session, liveliness token and status reach the run, but the run's claim request never reaches it.
    The run ends at its connect timeout with exit 1 and one line that says the robot side's status never named
    this run's claim and points at an access-control rule, not at the lab key."""
    folder = tmp_path / "lab"
    write_lab(LAB, folder, days=1)
    robot_side = folder / "xbee-pc.json5"
    text = robot_side.read_text()
    assert text.count('"platoon/m3pi/3/cmd/wheels"') == 1
    robot_side.write_text(text.replace('"platoon/m3pi/3/cmd/wheels"', '"platoon/m3pi/3/cmd/wheel"'))
    tls = f"tls/127.0.0.1:{free_port()}"
    log = tmp_path / "emulator.log"
    with open(log, "w") as stream:
        robot = subprocess.Popen([str(PLATOON), "m3pi-emulator", "--config", str(LIVE3), "--set",
                                  f'vehicles.3.connect=["{tls}"]', "--zenoh-config", str(robot_side)],
                                 cwd=REPO, env=_env(), stdout=stream, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "configured, pose on" not in log.read_text():
            assert robot.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        code, out, err = finish(start_run(0, tmp_path / "typo.mcap", 5.0, f'vehicles.3.connect=["{tls}"]',
                                          f'vehicles.3.zenoh_config="{folder / "laptop.json5"}"',
                                          "hil.connect_timeout=3.0"))
    finally:
        robot.terminate()
        robot.wait(10)
    assert code == 1, err
    problem = [line for line in err.splitlines() if "did not grant this run's claim" in line]
    assert len(problem) == 1, err
    assert "its status on platoon/m3pi/3/status never named it" in problem[0], problem[0]
    assert "access-control rule" in problem[0] and "lab key" not in problem[0].split("never named it")[1], problem[0]
    assert "claimed by" not in log.read_text()
