"""A secure lab: a certificate authority, one certificate per host, and each host's Zenoh config.

``platoon hil-certs`` (its command: orchestrator/cli/hil_certs.py) writes, for a lab described by its hosts and their
roles, everything mutual TLS and Zenoh's access control need (docs/hil.md, "A secure lab"):

* ``ca.pem`` and ``ca.key``: the lab's own certificate authority (an EC P-256 key, self-signed). The
  key signs host certificates; keep it off the lab's machines. Run the command again with ``--ca`` naming
  it to add hosts: the certificates already handed out stay valid;
* ``lab.key``: the lab key (``bridge.lab_key``) every run and robot side holds;
* ``<host>.json5``: that host's Zenoh config, the only file the host needs: peer mode, scouting off,
  TLS with mutual authentication (the CA, the host's certificate and private key inline, base64), and
  an access control list that denies by default and allows, on the lab's key prefix:

  - everyone in the lab: declaring subscribers, liveliness subscribers and queries;
  - a robot side (emulator, ``m3pi-serial``, motion capture) of robots R: to receive wheel commands
    and claim tokens (``<prefix>/m3pi/<r>/cmd/wheels``, ``.../host/*``) only from the run hosts that
    own r, and to send its poses, status and token (``.../pose``, ``.../status``, ``.../alive``)
    only to them;
  - a run host owning robots R: the mirror image: observations of r only from r's robot sides,
    commands and claims only to them.

  So a lab member without the role (another run host, a compromised student laptop with a valid
  certificate) can neither put on robot r's keys nor read its commands, claim or poses.

A host's certificate names it (common name = the host's name: Zenoh's ACL matches on it) and the
addresses peers reach it at (DNS names or IPs; ``localhost``, 127.0.0.1 and ::1 always), which TLS
checks when connecting. The certificates are made with the ``cryptography`` package. This module
makes the files' contents; orchestrator/support/lab_files.py writes them (the output rule, keys 0600 from
their creation on, the lab's folder its owner's alone), reading a secret file back through
``bridge.lab_key.read_private``, the one check of a key file named by the user.
"""

from __future__ import annotations

import base64
import datetime
import ipaddress
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from .protocol import DEFAULT_PREFIX, check_prefix

HOST_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.-]{0,62}$")
DNS_LABEL = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?$")
MAX_ROBOT = 2**31 - 1  # the largest robot id a config takes (vehicles.K.robot)
MAX_DAYS = 3650  # validity of a certificate at most: ten years
LAB_KEY_FILE = "lab.key"  # the lab key (bridge.lab_key) every run and robot side of the lab holds
ALWAYS = ("localhost", "127.0.0.1", "::1")  # every certificate names these: tests and one-machine labs
CA_FILE, CA_KEY_FILE = "ca.pem", "ca.key"
# what every lab member may do on the lab's keys (puts and tokens are per role and robot)
DECLARATIONS = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query", "reply",
                "declare_queryable"]
OBSERVATIONS = ("pose", "status", "alive")  # a robot side's keys (under <prefix>/m3pi/<id>/)


class LabError(ValueError):
    """A lab description that cannot work; the text names the host or option."""


@dataclass
class Lab:
    """The hosts of a lab: who runs which robots, who stands for which robots."""

    run_hosts: dict[str, set[int]] = field(default_factory=dict)  # host -> robots it may drive
    robot_sides: dict[str, set[int]] = field(default_factory=dict)  # host -> robots it serves
    addresses: dict[str, list[str]] = field(default_factory=dict)  # host -> DNS names / IPs peers use
    prefix: str = DEFAULT_PREFIX

    def hosts(self) -> list[str]:
        return list(dict.fromkeys([*self.run_hosts, *self.robot_sides]))

    def check(self) -> None:
        problems = check_prefix(self.prefix)
        hosts = self.hosts()
        if not self.run_hosts or not self.robot_sides:
            problems.append("a lab needs at least one --run-host and one --robot-side")
        problems += [f"host name {name!r}: letters, digits, '.' and '-' only" for name in hosts
                     if not HOST_NAME.match(name) or check_address(name)]
        problems += [f"--address {name}={address}: {check_address(address)}" for name, addresses in self.addresses.items()
                     for address in addresses if check_address(address)]
        problems += [f"--address {name}=...: no host {name!r} in the lab" for name in self.addresses
                     if name not in hosts]
        driven = set().union(*self.run_hosts.values()) if self.run_hosts else set()
        served = set().union(*self.robot_sides.values()) if self.robot_sides else set()
        problems += [f"robot {robot} is driven by a run host but served by no --robot-side"
                     for robot in sorted(driven - served)]
        if problems:
            raise LabError("; ".join(problems))


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _san(addresses: list[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for address in dict.fromkeys(addresses):
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(address)))
        except ValueError:
            names.append(x509.DNSName(address))
    return x509.SubjectAlternativeName(names)


def _key_usage(ca: bool) -> x509.KeyUsage:
    return x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                         data_encipherment=False, key_agreement=False, key_cert_sign=ca, crl_sign=ca,
                         encipher_only=False, decipher_only=False)


def make_ca(days: int, name: str = "platoon-cosim lab CA") -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    certificate = (x509.CertificateBuilder().subject_name(_name(name)).issuer_name(_name(name))
                   .public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
                   .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
                   .add_extension(_key_usage(ca=True), critical=True)
                   .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
                   .sign(key, hashes.SHA256()))
    return key, certificate


def make_host_certificate(ca_key: ec.EllipticCurvePrivateKey, ca: x509.Certificate, host: str,
                          addresses: list[str], days: int) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate for ``host`` (its common name), valid as TLS server and client, naming ``addresses``."""
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    certificate = (x509.CertificateBuilder().subject_name(_name(host)).issuer_name(ca.subject)
                   .public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .add_extension(_key_usage(ca=False), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                         ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                   .add_extension(_san([host, *addresses, *ALWAYS]), critical=False)
                   .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
                   .sign(ca_key, hashes.SHA256()))
    return key, certificate


def pem(item: Any) -> bytes:
    if isinstance(item, x509.Certificate):
        return item.public_bytes(serialization.Encoding.PEM)
    return item.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                              serialization.NoEncryption())


def access_control(lab: Lab, host: str) -> dict[str, Any]:
    """The ACL of ``host``'s own session (module docstring): deny by default, allow by role, per robot, both
    ways, so that a lab member without the role can neither put on a robot's keys nor read them."""
    keys = f"{lab.prefix}/m3pi"
    rules: list[dict[str, Any]] = [{"id": "lab", "permission": "allow", "flows": ["ingress", "egress"],
                                    "messages": DECLARATIONS, "key_exprs": [f"{lab.prefix}/**"]}]
    subjects: list[dict[str, Any]] = [{"id": "lab", "cert_common_names": lab.hosts()}]
    policies: list[dict[str, Any]] = [{"rules": ["lab"], "subjects": ["lab"]}]

    def allow(rule: str, flow: str, key_exprs: list[str], peers: list[str]) -> None:
        if not peers:
            return
        rules.append({"id": rule, "permission": "allow", "flows": [flow], "messages": ["put", "liveliness_token"],
                      "key_exprs": key_exprs})
        subjects.append({"id": rule, "cert_common_names": peers})
        policies.append({"rules": [rule], "subjects": [rule]})

    for robot in sorted(lab.robot_sides.get(host, ())):  # commands and claims from (and observations to) its owners
        owners = [name for name, robots in lab.run_hosts.items() if robot in robots]
        allow(f"commands in {robot}", "ingress", [f"{keys}/{robot}/cmd/wheels", f"{keys}/{robot}/host/*"], owners)
        allow(f"observations out {robot}", "egress", [f"{keys}/{robot}/{tail}" for tail in OBSERVATIONS], owners)
    for robot in sorted(lab.run_hosts.get(host, ())):  # observations from (and commands to) its robot sides
        sides = [name for name, robots in lab.robot_sides.items() if robot in robots]
        allow(f"observations in {robot}", "ingress", [f"{keys}/{robot}/{tail}" for tail in OBSERVATIONS], sides)
        allow(f"commands out {robot}", "egress", [f"{keys}/{robot}/cmd/wheels", f"{keys}/{robot}/host/*"], sides)
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def zenoh_lab_config(lab: Lab, host: str, ca_pem: bytes, certificate_pem: bytes, key_pem: bytes) -> dict[str, Any]:
    """``host``'s Zenoh config: peer, no scouting, mutual TLS (inline), its ACL; endpoints come from the run."""
    def b64(data: bytes) -> str:
        return base64.b64encode(data).decode("ascii")

    tls = {"root_ca_certificate_base64": b64(ca_pem), "enable_mtls": True, "verify_name_on_connect": True,
           "listen_certificate_base64": b64(certificate_pem), "listen_private_key_base64": b64(key_pem),
           "connect_certificate_base64": b64(certificate_pem), "connect_private_key_base64": b64(key_pem)}
    return {"mode": "peer", "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            "transport": {"link": {"tls": tls}}, "access_control": access_control(lab, host)}


def load_ca(certificate_pem: bytes, key_pem: bytes, where: str) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A lab CA from its files' bytes, checked: a CA certificate and the EC key that goes with it."""
    try:
        key = serialization.load_pem_private_key(key_pem, password=None)
        certificate = x509.load_pem_x509_certificate(certificate_pem)
    except ValueError as error:
        raise LabError(f"{where}: cannot read the lab CA ({error})") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise LabError(f"{where}: the CA key is not an EC private key")
    if key.public_key() != certificate.public_key():
        raise LabError(f"{where}: the CA key does not go with the CA certificate")
    try:
        is_ca = certificate.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    except x509.ExtensionNotFound:
        is_ca = False
    if not is_ca:
        raise LabError(f"{where}: the certificate is not a CA's")
    return key, certificate


def host_file(lab: Lab, host: str, ca_key: ec.EllipticCurvePrivateKey, ca: x509.Certificate, days: int) -> bytes:
    """The whole ``<host>.json5``: a new key and certificate for ``host``, its Zenoh config around them."""
    key, certificate = make_host_certificate(ca_key, ca, host, lab.addresses.get(host, []), days)
    config = zenoh_lab_config(lab, host, pem(ca), pem(certificate), pem(key))
    header = (f"// Zenoh config of lab host {host!r} (platoon hil-certs): mutual TLS and access control.\n"
              "// Holds this host's private key: copy it to that host only. docs/hil.md, \"A secure lab\".\n")
    return (header + json.dumps(config, indent=2) + "\n").encode()


def parse_assignment(text: str, option: str) -> tuple[str, set[int]]:
    """``NAME=3,4`` -> ("NAME", {3, 4}); a ``LabError`` naming ``option`` otherwise."""
    name, _, robots = text.partition("=")
    try:
        ids = {int(part) for part in robots.split(",") if part.strip()}
    except ValueError:
        ids = set()
    if not name or not ids or any(robot < 0 for robot in ids):
        raise LabError(f"{option} {text!r}: expected HOST=ROBOT[,ROBOT...], e.g. laptop=3,4")
    if any(robot > MAX_ROBOT for robot in ids):
        raise LabError(f"{option} {text!r}: robot ids go from 0 to {MAX_ROBOT} (a config's vehicles.K.robot)")
    return name, ids


def check_address(text: str) -> str | None:
    """Why ``text`` cannot go into a certificate as an address peers reach a host at (None: it can): an IP,
    or a DNS name of ASCII letters, digits and '-' in dot-separated labels (no wildcard, no spaces)."""
    try:
        ipaddress.ip_address(text)
        return None
    except ValueError:
        pass
    if not text.isascii() or len(text) > 253 or not all(DNS_LABEL.match(label) for label in text.split(".")):
        return (f"{text!r} is neither an IP address nor a DNS name (labels of ASCII letters, digits and '-', "
                "no wildcard, no spaces; an internationalized name in its xn-- form)")
    return None
