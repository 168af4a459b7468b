"""``platoon hil-certs``: write a lab's CA, lab key and host configs (bridge/lab.py makes their contents).

Writing them is stricter than the output rule (orchestrator/support/lab_files.py says how and why);
this module is the command line only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from orchestrator.cli.common import fail
from orchestrator.support.lab_files import write_lab

def hil_certs(
    folder: Annotated[Path, typer.Argument(metavar="DIR", help="a folder of yours for the lab CA, lab key and hosts' "
                                                               "Zenoh configs (made 0700 if missing)")],
    run_hosts: Annotated[list[str], typer.Option("--run-host", metavar="HOST=ROBOTS",
                                                 help="a host that runs `platoon run` and may drive these robots, "
                                                      "e.g. laptop=3,4 (repeatable)")] = [],
    robot_sides: Annotated[list[str], typer.Option("--robot-side", metavar="HOST=ROBOTS",
                                                   help="a host with the emulator, m3pi-serial or motion capture of "
                                                        "these robots, e.g. xbee-pc=3,4 (repeatable)")] = [],
    addresses: Annotated[list[str], typer.Option("--address", metavar="HOST=ADDRESS",
                                                 help="a DNS name or IP peers reach HOST at (repeatable; localhost "
                                                      "and 127.0.0.1 are always in)")] = [],
    prefix: Annotated[str, typer.Option(metavar="PREFIX", help="the lab's Zenoh key prefix (hil.prefix)")] = "platoon",
    days: Annotated[int, typer.Option(help="validity of new certificates, 1 to 3650")] = 365,
    ca: Annotated[Optional[Path], typer.Option("--ca", metavar="CA.PEM", help="sign with this lab CA (its key ca.key "
                                               "beside it) to add hosts to a lab; without it DIR must hold no CA")] = None,
) -> None:
    """Create a lab CA, a lab key, a certificate per host and each host's Zenoh config (mutual TLS, access control)."""
    from bridge.lab import CA_FILE, LAB_KEY_FILE, Lab, LabError, parse_assignment
    from orchestrator.support.output import OutputError

    try:
        lab = Lab(prefix=prefix)
        for option, texts, table in (("--run-host", run_hosts, lab.run_hosts), ("--robot-side", robot_sides, lab.robot_sides)):
            for text in texts:
                name, robots = parse_assignment(text, option)
                table.setdefault(name, set()).update(robots)
        for text in addresses:
            name, _, address = text.partition("=")
            if not name or not address:
                raise LabError(f"--address {text!r}: expected HOST=ADDRESS, e.g. xbee-pc=192.168.1.20")
            lab.addresses.setdefault(name, []).append(address)
        written, new_ca = write_lab(lab, folder, days, ca)
    except (LabError, OutputError) as error:
        fail(2, str(error))
    ca_text = f"new lab CA: {folder / CA_FILE}" if new_ca else f"lab CA {ca}"
    print(f"{ca_text} (its key ca.key signs hosts: keep it off the lab's machines)")
    print(f"lab key: {folder / LAB_KEY_FILE} (every run host and robot side needs it: --lab-key, hil.lab_key)")
    for path in written:
        print(f"{path.stem}: {path}")
