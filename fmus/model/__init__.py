"""The science of platoon-cosim, written once: guidance laws, paths, vehicle dynamics, coupling.

Everything in this package is pure computation on floats (standard library ``math`` only, no numpy,
no I/O), because the very same modules run inside the FMUs (bundled as FMU resources), in the
monolithic reference integrator and in the analysis tools.
"""

# Import every module eagerly. pythonfmu FMUs in one Python process share ``sys.modules``: the first
# FMU to load this package from its (temporary) resources folder defines it for all the others, and
# that folder may be gone by the time a later FMU would import a submodule lazily.
from . import angles, coupling, dynamics, factory, guidance, integrate, link, paths, platoon, target, vehicle  # noqa: E402,F401
