"""``python -m orchestrator.cli ARGS``: the ``platoon`` command, as ``python -m orchestrator``."""

from orchestrator.cli.launch import main

main()
