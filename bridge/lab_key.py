"""The lab key: a secret the runs and the robot sides share, so that a robot side knows its runs.

Every claim request and wheel command carries a MAC (HMAC-SHA256, cut to 16 bytes) over the robot's
command key and the whole command (claim id, sequence number, deadline, speeds), made with the lab
key. A robot side obeys only commands whose MAC it can check with its own key: whoever can reach its
endpoint but does not hold the key cannot claim the robot, and a copied command cannot be re-aimed at
another robot, another claim or another number (docs/hil.md, "Who can start the robot").

Where the key is (``key_path``): the file a config (``[hil] lab_key``) or a command line (``--lab-key``)
names; else ``$PLATOON_LAB_KEY``; else the user's own ``~/.config/platoon/lab.key`` (``$XDG_CONFIG_HOME``),
which the first program that needs it makes (32 random bytes, mode 0600, in a folder of mode 0700). So
a run and an emulator started by one user on one machine share it with no step at all, and another
user of the machine cannot read it. Two machines get the same file (``platoon hil-certs`` writes one
beside the lab's configs; or copy the default one).

A key file is refused unless it is a regular file (not a link), owned by this user, readable by no one
else, and holds exactly one key: a key others can read is not a secret.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import tempfile
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path

from .protocol import MAC_SIZE  # 128 bits of HMAC-SHA256: beyond guessing at any rate a network carries

KEY_BYTES = 32
KEY_ENV = "PLATOON_LAB_KEY"
HEADER = "platoon-cosim lab key"


class LabKeyError(ValueError):
    """A lab key file that cannot be used; the text names the file and what to do."""


@dataclass(frozen=True)
class LabKey:
    """The shared secret and where it came from (for messages; the secret itself is never printed)."""

    secret: bytes
    path: Path

    def mac(self, key_expr: str, body: bytes) -> bytes:
        """The MAC of ``body`` sent on ``key_expr`` (the key is inside, so a command for one robot is no
        command for another)."""
        message = key_expr.encode() + b"\0" + body
        return hmac.new(self.secret, message, hashlib.sha256).digest()[:MAC_SIZE]

    def verify(self, key_expr: str, body: bytes, mac: bytes) -> bool:
        return hmac.compare_digest(self.mac(key_expr, body), mac)


def default_key_path() -> Path:
    """``$PLATOON_LAB_KEY``, else the user's own ``$XDG_CONFIG_HOME/platoon/lab.key`` (``~/.config``)."""
    named = os.environ.get(KEY_ENV)
    if named:
        return Path(named).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "platoon" / "lab.key"


def key_text(secret: bytes) -> str:
    """A key file's whole text: a header line and the key in hex (easy to copy, and to tell from other files)."""
    return f"# {HEADER}: keep it secret; every run and robot side of the lab holds the same\n{secret.hex()}\n"


def new_secret() -> bytes:
    return secrets.token_bytes(KEY_BYTES)


def _parse(path: Path, text: str) -> bytes:
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    try:
        if len(lines) == 1 and len(lines[0]) == 2 * KEY_BYTES:
            return bytes.fromhex(lines[0])
    except ValueError:
        pass
    raise LabKeyError(f"lab key {path}: not a lab key file (expected one line of {2 * KEY_BYTES} hex digits, as "
                      "`platoon hil-certs` or the first run writes it)")


def read_private(path: Path, what: str, error: type[ValueError] = LabKeyError, missing: str = "", folder: str = "",
                 limit: int = 4096) -> bytes:
    """The bytes of a secret file the user named (a lab key, a CA's private key): a regular file, not a link,
    this user's, readable by no one else; whoever else can read it can drive the robots (or sign anyone into
    the lab). The one check of such a file: every refusal is one ``error`` naming ``what``, the file and what to
    do (``missing``, ``folder``: the hints for a file that is not there, and for a folder named instead)."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        raise error(f"{what} {path}: no such file{missing}") from None
    except OSError as failure:
        raise error(f"{what} {path}: cannot open it ({failure.strerror or failure}; a link is refused)") from None
    if stat.S_ISDIR(os.fstat(descriptor).st_mode):  # before fdopen, which refuses a folder with a traceback
        os.close(descriptor)
        raise error(f"{what} {path}: a folder, not a key file{folder}")
    with os.fdopen(descriptor, "rb") as stream:
        info = os.fstat(stream.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise error(f"{what} {path}: not a regular file")
        if info.st_uid != os.geteuid():
            raise error(f"{what} {path}: owned by user {info.st_uid}, not by this user ({os.geteuid()}): "
                        "whoever owns it can use it as theirs; use one of your own")
        if info.st_mode & 0o077:
            raise error(f"{what} {path}: mode {stat.S_IMODE(info.st_mode):04o}, others can read it: it must be a "
                        f"file only you can read (mode 0600); `chmod 600 {path}` once you know no one else copied "
                        "it (else make a new one)")
        return stream.read(limit)


def read_key(path: Path) -> LabKey:
    """The key in ``path``, checked (``read_private``)."""
    data = read_private(path, "lab key", missing=" (`platoon hil-certs DIR ...` writes DIR/lab.key; copy it to "
                        "every run host and robot side)", folder=f" (the lab's DIR? name the file in it: {path / 'lab.key'})")
    try:
        return LabKey(_parse(path, data.decode("ascii")), path)
    except UnicodeDecodeError:
        raise LabKeyError(f"lab key {path}: not a lab key file (not text)") from None


def _make_default(path: Path) -> None:
    """Create the default key file if it is missing: written aside (0600), synced, then linked into place,
    which fails if another program made it meanwhile (then that one is used). Never replaces a file."""
    folder = path.parent
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    descriptor, aside = tempfile.mkstemp(prefix=".lab.key.", dir=folder)  # mode 0600 from its creation
    try:
        with os.fdopen(descriptor, "w") as stream:
            stream.write(key_text(new_secret()))
            stream.flush()
            os.fsync(stream.fileno())
        with suppress(FileExistsError):
            os.link(aside, path)
    finally:
        with suppress(OSError):
            os.unlink(aside)


def load_lab_key(named: str | os.PathLike | None = None) -> LabKey:
    """The lab key a program uses: the file ``named`` (it must exist), else the default (made if missing)."""
    if named:
        return read_key(Path(named).expanduser())
    path = default_key_path()
    if not os.path.lexists(path):
        try:
            _make_default(path)
        except OSError as error:
            raise LabKeyError(f"lab key {path}: cannot create it ({error.strerror or error}); name one with "
                              f"--lab-key or {KEY_ENV}") from None
    return read_key(path)
