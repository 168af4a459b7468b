"""platoon-cosim FMUs: the guidance science (``fmus.model``) and its FMI 2.0 packaging."""

__version__ = "0.1.0"
