"""``python -m orchestrator.cli ARGS``: the ``platoon`` command, as ``python -m orchestrator``."""

from orchestrator.cli.app import main

main()
