"""The orchestrator: config -> components -> wiring -> master loop -> trace; CLI, metrics, plots, analysis.

It knows FMI (through FMPy), not guidance: the equations live in ``fmus.model``.
"""

__version__ = "0.1.0"
