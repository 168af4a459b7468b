"""``python -m orchestrator ARGS``: the ``platoon`` command, for an environment without its console script."""

from .cli import main

main()
