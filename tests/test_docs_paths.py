"""README.md, docs/ and the configs (their comments) name no path outside the repository, and every
path inside it that they name exists.

A newcomer has a clone of this repository and nothing else: a design note beside the repository
(``../shared/...``), a path on the machine a measurement was taken on (``/work/...``, ``/root/...``)
or in someone's home folder is a dead reference for them. What the docs may name outside the
repository is what exists on any Linux machine (``/tmp``, ``/dev``, ``/usr``, ``/proc``, ``/bin``),
the tool's own cache folder, and topic names, which look like paths but are not files. A path in the
repository that the docs name and the repository no longer has (a file moved, a typo) misleads as much.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md")), *sorted((REPO / "configs").rglob("*.toml"))]

# the first folder of an absolute path every Linux machine has, so an example there works anywhere;
# "platoon" starts the trace's and Zenoh's topic names (/platoon/vehicle1, /platoon/m3pi/3/pose)
ANYWHERE = {"tmp", "dev", "usr", "proc", "bin", "platoon"}
# ROS 2 names of docs/hil.md's "Your lab" and configs/hil/ros2_live3.toml: topics of vrpn_mocap, of a
# differential-drive base and of tf2, nodes, and a zenoh-bridge-ros2dds namespace
ROS_NAMES = {"vrpn_mocap", "m3pi_3", "diff_drive_controller", "tf", "platoon_vehicle3", "m3pi_emulator_3",
             "m3pi_emulator_<id>", "bot3",
             "lab", "a__b", "m3pi3", "m3pi_3_base"}  # a node namespace, a refused name, a misspelling, a DDS node
# the FMU cache the tool itself makes, and Zig's, which `platoon build --all-platforms` fills (docs/fmus.md); the
# lab key the tool itself makes (docs/hil.md); a ROS node's private topic (``~`` is the node's namespace, not a
# home folder: diff_drive_controller's ``~/cmd_vel``)
HOME_ALLOWED = ("~/.cache/platoon-cosim", "~/.cache/zig", "~/.config/platoon/lab.key", "~/cmd_vel")

SEGMENT = r"[A-Za-z0-9_.*<>-]+"  # a file or folder name, wildcards and <placeholders> allowed
# an absolute path: a slash not inside a word, a unit (m/s), a URL (ws://), a relative or home path
# (a/b, ~/x), followed by a name (not /* or />: C and XML)
ABSOLUTE = re.compile(rf"(?<![\w:/.*<>~\-\]}})])/(?=[A-Za-z0-9_.]){SEGMENT}(?:/{SEGMENT})*")
UP = re.compile(rf"(?<![\w./])(?:\.\./)+(?:{SEGMENT}/?)*")  # ../x, ../../x; not .../x (a key's tail)
HOME = re.compile(rf"(?<![\w/])~/(?:{SEGMENT}/?)*")
# a path in the repository: one of its top folders, then names (a glob or a <placeholder> is not checked)
INSIDE = re.compile(r"(?<![\w./-])((?:orchestrator|fmus|bridge|tests|configs|docs|layouts)/[A-Za-z0-9_./*<>-]*[A-Za-z0-9_*>])")


def missing_paths(doc: Path, repo: Path = REPO) -> list[str]:
    """``doc:line: path`` for every repository path ``doc`` names that the repository does not have
    (a file renamed or moved since the doc was written)."""
    found = []
    for number, line in enumerate(doc.read_text().splitlines(), start=1):
        for match in INSIDE.finditer(line):
            path = match.group(1)
            if not any(c in path for c in "*<>") and not (repo / path).exists():
                found.append(f"{doc.relative_to(repo)}:{number}: {path}")
    return found


def outside_paths(doc: Path, repo: Path = REPO) -> list[str]:
    """``doc:line: path (why)`` for every path in ``doc`` that is outside the repository ``repo``."""
    found = []
    for number, line in enumerate(doc.read_text().splitlines(), start=1):
        where = f"{doc.relative_to(repo)}:{number}"
        for match in ABSOLUTE.finditer(line):
            path = match.group()
            if path.split("/")[1] not in ANYWHERE | ROS_NAMES:
                found.append(f"{where}: {path} (an absolute path only one machine has)")
        for match in UP.finditer(line):
            path = match.group()
            resolved = (doc.parent / path).resolve()
            if not resolved.is_relative_to(repo) or not resolved.exists():
                found.append(f"{where}: {path} (not in the repository, seen from {doc.parent.relative_to(repo)}/)")
        for match in HOME.finditer(line):
            if not match.group().startswith(HOME_ALLOWED):
                found.append(f"{where}: {match.group()} (in a home folder)")
    return found


@pytest.mark.parametrize("doc", DOCS, ids=lambda doc: str(doc.relative_to(REPO)))
def test_docs_name_no_path_outside_the_repository(doc: Path) -> None:
    found = outside_paths(doc)
    assert not found, "paths a reader of a fresh clone does not have:\n" + "\n".join(found)


@pytest.mark.parametrize("doc", DOCS, ids=lambda doc: str(doc.relative_to(REPO)))
def test_every_repository_path_the_docs_name_exists(doc: Path) -> None:
    found = missing_paths(doc)
    assert not found, "paths the repository does not have (renamed or moved?):\n" + "\n".join(found)


def test_the_existence_check_sees_a_moved_file(tmp_path: Path) -> None:
    (tmp_path / "fmus").mkdir()
    (tmp_path / "fmus" / "realtime.py").write_text("")
    (tmp_path / "docs").mkdir()
    doc = tmp_path / "docs" / "probe.md"
    doc.write_text("pacing: `fmus/realtime.py`, once `fmus/realtime/py`, and `orchestrator/realtime.py`; "
                   "any of `configs/paper/*.toml`, `tests/<name>.py`\n")
    assert missing_paths(doc, tmp_path) == ["docs/probe.md:1: fmus/realtime/py", "docs/probe.md:1: orchestrator/realtime.py"]


def test_the_check_sees_each_kind_of_outside_path(tmp_path: Path) -> None:
    """The three kinds the docs had (a design note beside the repository, a machine's own folders, a
    home folder) are found; topic names, units, URLs, key tails and in-repository paths are not."""
    (tmp_path / "configs" / "paper").mkdir(parents=True)
    (tmp_path / "configs" / "paper" / "platoon.toml").write_text("")
    (tmp_path / "docs").mkdir()
    doc = tmp_path / "docs" / "probe.md"
    doc.write_text(
        "see /work/shared/design/field-notes.md and (../shared/viewer) or `LD_PRELOAD=/root/.pyenv/lib/x.so`\n"
        "../../elsewhere/notes.md, ~/notes/x.md\n"
        "fine: /platoon/vehicle1/pose, /tmp/hil-doc.mcap, 0.35 m/s, d*/R, ws://127.0.0.1:8765, tcp/127.0.0.1:7447,\n"
        "`.../alive`, ../configs/paper/platoon.toml, configs/hil/m3pi_live3.toml, ~/.cache/platoon-cosim/fmus/\n")
    found = outside_paths(doc, tmp_path)
    paths = [entry.split(": ", 1)[1].split(" (")[0] for entry in found]
    assert paths == ["/work/shared/design/field-notes.md", "/root/.pyenv/lib/x.so", "../shared/viewer",
                     "../../elsewhere/notes.md", "~/notes/x.md"], found
