"""pythonfmu slave classes: thin FMI wrappers around ``fmus.model`` steppers."""

# Eager for the same reason as fmus.model: FMUs in one process share sys.modules.
from . import base, defaults  # noqa: E402,F401
