"""The lab's files written as secrets (``platoon hil-certs``; bridge/lab.py makes their contents).

These files are the lab's secrets, so writing them is stricter than the output rule alone
(orchestrator/support/output.py, which every file here follows: aside, synced, renamed):

* DIR is the user's own folder, writable by no one else (made 0700 if missing): another user who made
  ``/tmp/lab`` first could read the keys or swap in a CA of their own;
* no file is written through a symlink, nor onto anything but a regular file;
* private keys (``ca.key``, ``lab.key``, each ``HOST.json5``) are 0600 from their creation on; ``ca.pem``
  too until it is in place, then readable as the umask allows but never writable by others;
* ``--ca`` must name a CA that is valid now (an expired one signs certificates every handshake refuses),
  and into a DIR of another lab (another CA, another lab key) it writes nothing: it would replace DIR's
  CA while its ``ca.key`` stays;
* a CA found in DIR is never used unasked: ``--ca`` names the one to sign with (its key beside it),
  else DIR must hold none. So a CA someone slipped into DIR never signs a host;
* everything is checked before anything is written; a failure (full disk) names the file, leaves the
  files already there as they were, and removes what this run made of a new lab.
"""

from __future__ import annotations

import os
import stat
from contextlib import suppress
from pathlib import Path

WHAT = "hil-certs"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_private_folder(folder: Path) -> None:
    """``folder`` must be a folder (not a link) of this user, writable by no one else; missing is fine."""
    from bridge.lab import LabError

    try:
        info = os.lstat(folder)
    except FileNotFoundError:
        return
    except OSError as error:
        raise LabError(f"{folder}: cannot use it ({error.strerror or error})") from None
    if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
        raise LabError(f"{folder}: not a folder (a link or a file); give a folder of your own")
    if info.st_uid != os.geteuid():
        raise LabError(f"{folder}: owned by user {info.st_uid}, not by you: its owner could read the lab's keys "
                       "or swap its CA; use a folder of your own (e.g. ~/lab)")
    if info.st_mode & 0o002 or (info.st_mode & 0o020 and not own_group(info.st_gid)):
        raise LabError(f"{folder}: mode {stat.S_IMODE(info.st_mode):04o}, others may write in it (and swap its CA); "
                       f"`chmod go-w {folder}` or use a folder of your own")


def own_group(gid: int) -> bool:
    """Whether group ``gid`` is this user's private group (named after them, no other member): with umask
    002, as some systems set it, folders are group-writable, and that group is the user alone."""
    import grp
    import pwd

    try:
        group, user = grp.getgrgid(gid), pwd.getpwuid(os.geteuid())
    except KeyError:
        return False
    return gid == user.pw_gid and group.gr_name == user.pw_name and not group.gr_mem


def check_new_file(path: Path) -> None:
    """A file about to be written: absent or a regular file, never a link (replaced, never written through)."""
    from bridge.lab import LabError

    try:
        info = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(info.st_mode):
        raise LabError(f"{path}: is a symbolic link; refusing to write a key through or onto it (remove it)")
    if not stat.S_ISREG(info.st_mode):
        raise LabError(f"{path}: is not a regular file (a folder, FIFO or device); refusing to replace it")


def read_regular(path: Path) -> bytes:
    """A public file of a lab (a CA certificate) found in DIR, never read through a link: a regular file. (A key
    file goes through ``bridge.lab_key.read_private``, which also checks that only its owner can read it.)"""
    from bridge.lab import LabError

    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as error:
        raise LabError(f"{path}: cannot read it ({error.strerror or error}; a link is refused)") from None
    with os.fdopen(descriptor, "rb") as stream:
        if not stat.S_ISREG(os.fstat(stream.fileno()).st_mode):
            raise LabError(f"{path}: not a regular file")
        return stream.read(1 << 20)


def check_ca_current(certificate, where: str) -> None:
    """A lab CA that expired (or is not valid yet) signs certificates every handshake refuses: refused."""
    import datetime

    from bridge.lab import LabError

    now = datetime.datetime.now(datetime.timezone.utc)
    ends, starts = certificate.not_valid_after_utc, certificate.not_valid_before_utc
    if ends <= now:
        raise LabError(f"{where}: the lab CA expired on {ends:%Y-%m-%d %H:%M} UTC ({(now - ends).days} days ago): every "
                       "TLS handshake refuses a certificate it signs; make a new lab (`platoon hil-certs NEWDIR ...`) "
                       "and give every host its new files")
    if starts > now:
        raise LabError(f"{where}: the lab CA is valid only from {starts:%Y-%m-%d %H:%M} UTC (is this machine's clock "
                       "right?)")


def check_same_lab(folder: Path, ca: Path, certificate) -> None:
    """``--ca`` from another folder into DIR: DIR must hold no CA, or that same one. Another CA there would be
    replaced while its key ``ca.key`` stays (no longer a pair), and DIR's hosts trust a CA that is gone."""
    from cryptography import x509

    from bridge.lab import CA_FILE, CA_KEY_FILE, LabError

    here = folder / CA_FILE
    if not os.path.lexists(here):
        if os.path.lexists(folder / CA_KEY_FILE):
            raise LabError(f"{folder / CA_KEY_FILE}: DIR holds a CA key but no {CA_FILE}; writing --ca {ca}'s certificate "
                           "beside it would pair it with a key that is not its own; use a new DIR")
        return
    try:
        theirs = x509.load_pem_x509_certificate(read_regular(here))
    except ValueError:
        theirs = None
    if theirs is None or theirs.public_key() != certificate.public_key():
        raise LabError(f"{here}: DIR is another lab (its own CA); --ca {ca} would replace its CA and lab key while "
                       f"its {CA_KEY_FILE} stays, and its hosts would trust a CA that is gone: add hosts to DIR's lab with "
                       f"--ca {here}, or to {ca}'s in a new DIR")


def _lab_files(lab, folder: Path, days: int, ca: Path | None) -> tuple[dict[Path, tuple[bytes, bool]], bool]:
    """Every file to write (path -> (bytes, private)) and whether the CA is new; nothing written yet."""
    from bridge.lab import CA_FILE, CA_KEY_FILE, LAB_KEY_FILE, LabError, pem, host_file, load_ca, make_ca
    from bridge.lab_key import key_text, new_secret, read_key, read_private

    files: dict[Path, tuple[bytes, bool]] = {}
    if ca is None:
        for name in (CA_FILE, CA_KEY_FILE):
            if os.path.lexists(folder / name):
                raise LabError(f"{folder / name}: a CA is already there; hil-certs signs only with a CA it makes now or "
                               f"one you name: --ca {folder / CA_FILE} (its key {CA_KEY_FILE} beside it), or a new DIR")
        ca_key, certificate = make_ca(days)
        files[folder / CA_FILE] = (pem(certificate), False)
        files[folder / CA_KEY_FILE] = (pem(ca_key), True)
    else:
        key_path = ca.parent / CA_KEY_FILE
        try:
            ca_bytes = ca.read_bytes()
        except OSError as error:
            raise LabError(f"--ca {ca}: cannot read it ({error.strerror or error})") from None
        ca_key, certificate = load_ca(ca_bytes, read_private(key_path, "CA key", LabError, limit=1 << 20), f"--ca {ca}")
        check_ca_current(certificate, f"--ca {ca}")
        if folder.resolve() != ca.parent.resolve():
            check_same_lab(folder, ca, certificate)
            files[folder / CA_FILE] = (pem(certificate), False)
    old_key = (ca.parent if ca is not None else folder) / LAB_KEY_FILE
    secret = read_key(old_key).secret if ca is not None and os.path.lexists(old_key) else new_secret()
    if ca is not None and folder.resolve() != ca.parent.resolve() and os.path.lexists(folder / LAB_KEY_FILE) \
            and read_key(folder / LAB_KEY_FILE).secret != secret:
        raise LabError(f"{folder / LAB_KEY_FILE}: DIR holds another lab key than {old_key}'s lab: writing that one "
                       "would lock DIR's runs and robot sides out of each other; add the hosts to one lab")
    files[folder / LAB_KEY_FILE] = (key_text(secret).encode(), True)
    for host in lab.hosts():
        files[folder / f"{host}.json5"] = (host_file(lab, host, ca_key, certificate, days), True)
    return files, ca is None


def write_lab(lab, folder: Path, days: int = 365, ca: Path | None = None) -> tuple[list[Path], bool]:
    """Write the lab's files into ``folder`` (module docstring); returns the host configs and whether the CA is new."""
    from bridge.lab import MAX_DAYS, LabError
    from bridge.lab_key import LabKeyError
    from orchestrator.support.output import OutputError, write_bytes

    lab.check()
    if not 1 <= days <= MAX_DAYS:
        raise LabError(f"--days {days}: expected 1 to {MAX_DAYS} (ten years)")
    check_private_folder(folder)
    try:
        files, new_ca = _lab_files(lab, folder, days, ca)
    except LabKeyError as error:
        raise LabError(str(error)) from None
    for path in files:
        check_new_file(path)
    made_folder = not folder.exists()
    try:
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as error:
        raise LabError(f"{folder}: cannot make it ({error.strerror or error})") from None
    check_private_folder(folder)  # again: someone may have made it between the check and mkdir (in /tmp)
    written: list[Path] = []
    try:
        for path, (data, private) in files.items():
            write_bytes(path, data, WHAT, private=True)  # 0600 from its creation on, whatever the umask ...
            written.append(path)
            if not private:  # ... then readable as the umask allows, never writable by others (umask 000: 0644)
                os.chmod(path, 0o644 & ~_umask())
    except OutputError:
        if new_ca:  # a new lab half made is no lab: nothing of it stays (old files were never touched)
            for path in written:
                with suppress(OSError):
                    path.unlink()
            if made_folder:
                with suppress(OSError):
                    folder.rmdir()
        raise
    return [path for path in files if path.suffix == ".json5"], new_ca
