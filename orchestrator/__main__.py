"""``python -m orchestrator ARGS``: the ``platoon`` command, for an environment without its console script."""

from orchestrator.cli.launch import main

main()
