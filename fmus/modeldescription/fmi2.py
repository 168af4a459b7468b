"""A complete FMI 2.0 model description from a slave's declared variables.

pythonfmu writes no units, no ranges, no InitialUnknowns and leaves variabilities unset (illegal for
Integer and Boolean parameters); this module writes everything from ``VariableInfo`` declarations,
including the capability flags, each set on purpose:

* canHandleVariableCommunicationStepSize: true. Each step is split into equal RK4 substeps no longer
  than ``max_substep``, so any step size integrates with the same accuracy.
* canGetAndSetFMUstate / canSerializeFMUstate: true. The slaves save every value and the whole
  stepper (state vector, time, input samples), tested by a rollback test.
* needsExecutionTool: true. FMI 2.0 (section 2.2.x, the CoSimulation element): "If true, a tool is
  needed to execute the model". Our binary executes nothing itself: it hands the model (Python
  source in resources/) to the Python installation of the host, which must provide libpython 3.11
  and its standard library (docs/fmus.md, "What a host needs"). That installation is the tool. The
  importers we run them with (FMPy simulate and validate, libcosim, our C host) treat the flag as
  information and run the FMUs as before (tests/test_hostile_fmus.py). The native twins
  (fmus/builders/native.py) declare "false": their binary is the model.
* canBeInstantiatedOnlyOncePerProcess: false. All state lives on the instance (tested with two
  platoons in one process).
"""

from __future__ import annotations

from typing import TYPE_CHECKING
from xml.etree.ElementTree import SubElement

from fmus.modeldescription.core import (add_units_categories_experiment, format_value, instantiation_token,
                                        root_element, serialize)

if TYPE_CHECKING:  # annotations only: checking that the FMUs are current must not import pythonfmu
    from fmus.slaves.base import PlatoonSlave

CAPABILITIES = {
    "needsExecutionTool": "true",
    "canHandleVariableCommunicationStepSize": "true",
    "canInterpolateInputs": "false",
    "maxOutputDerivativeOrder": "0",
    "canRunAsynchronuously": "false",
    "canBeInstantiatedOnlyOncePerProcess": "false",
    "canNotUseMemoryManagementFunctions": "true",
    "canGetAndSetFMUstate": "true",
    "canSerializeFMUstate": "true",
    "providesDirectionalDerivative": "false",
}


def guid_for(source_digest: str, model_name: str) -> str:
    """A GUID that changes exactly when the FMU's sources change (reproducible builds)."""
    return instantiation_token(source_digest, model_name, fmi_version=2)


PYTHONFMU_TOOL = "pythonfmu runtime"


def model_description(slave: PlatoonSlave, guid: str, version: str, runtime: str = PYTHONFMU_TOOL,
                      capabilities: dict[str, str] | None = None, source_files: tuple[str, ...] = ()) -> bytes:
    """The modelDescription.xml of ``slave`` (an instance, so value references are known).

    The native twins (fmus/builders/native.py) share it: same variables and references, their own
    ``runtime`` in generationTool, their own capability flags, and the C files in sources/."""
    cls = type(slave)
    root = root_element(cls, 2, guid, version, runtime, {"numberOfEventIndicators": "0"})
    # a slave class may override a flag (LiveVehicle: a real robot has no FMU state to save)
    flags = capabilities if capabilities is not None else {**CAPABILITIES, **getattr(cls, "capabilities", {})}
    co_simulation = SubElement(root, "CoSimulation", {"modelIdentifier": cls.__name__, **flags})
    if source_files:
        sources = SubElement(co_simulation, "SourceFiles")
        for name in source_files:
            SubElement(sources, "File", {"name": name})
    add_units_categories_experiment(root, cls, {info.unit for info in cls.variables if info.unit},
                                    slave.log_categories)

    variables_node = SubElement(root, "ModelVariables")
    reference_of = {variable.name: reference for reference, variable in slave.vars.items()}
    index_of: dict[str, int] = {}
    for position, info in enumerate(cls.variables, start=1):
        index_of[info.name] = position
        attributes = {
            "name": info.name,
            "valueReference": str(reference_of[info.name]),
            "description": info.description,
            "causality": info.causality,
            "variability": info.resolved_variability,
        }
        if info.causality == "output":
            attributes["initial"] = "calculated"
        scalar = SubElement(variables_node, "ScalarVariable", attributes)
        type_attributes: dict[str, str] = {}
        if info.unit:
            type_attributes["unit"] = info.unit
        if info.causality != "output":
            type_attributes["start"] = format_value(info.start)
        if info.min is not None:
            type_attributes["min"] = format_value(info.min)
        if info.max is not None:
            type_attributes["max"] = format_value(info.max)
        SubElement(scalar, info.type, type_attributes)

    # FMI 2.0.x, section 2.2.8 (ModelStructure): an Unknown's dependencies name the knowns it is
    # computed from, and no dependencies attribute means "all of them". The knowns differ per list:
    # for <Outputs> (at communication points) they are the inputs and the states, so a parameter is
    # never listed; for <InitialUnknowns> (Initialization Mode) they are the inputs, the variables
    # with initial="exact" - all our parameters (causality parameter, variability fixed: initial
    # defaults to exact) - and the independent variable. So an output that starts from a parameter
    # (a vehicle's x from initial.x) names it there (``initial_depends_on``).
    structure = SubElement(root, "ModelStructure")
    for section, dependencies_of in (("Outputs", lambda info: info.depends_on),
                                     ("InitialUnknowns", lambda info: info.initial_depends_on)):
        node = SubElement(structure, section)
        for info in cls.variables:
            if info.causality != "output":
                continue
            attributes = {"index": str(index_of[info.name])}
            dependencies = dependencies_of(info)
            if dependencies is not None:
                attributes["dependencies"] = " ".join(str(index_of[n]) for n in sorted(dependencies, key=index_of.get))
            SubElement(node, "Unknown", attributes)

    return serialize(root)
