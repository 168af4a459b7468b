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
  (fmus/native_build.py) declare "false": their binary is the model.
* canBeInstantiatedOnlyOncePerProcess: false. All state lives on the instance (tested with two
  platoons in one process).
"""

from __future__ import annotations

import uuid
from typing import Any
from xml.dom.minidom import parseString
from xml.etree.ElementTree import Element, SubElement, tostring

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # annotations only: checking that the FMUs are current must not import pythonfmu
    from fmus.slaves.base import PlatoonSlave

# SI base-unit exponents of every unit our variables use.
UNITS: dict[str, dict[str, int]] = {
    "m": {"m": 1},
    "m/s": {"m": 1, "s": -1},
    "m/s2": {"m": 1, "s": -2},
    "rad": {"rad": 1},
    "rad/s": {"rad": 1, "s": -1},
    "s": {"s": 1},
    "1/m": {"m": -1},
    "1/s": {"s": -1},
}

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

GUID_NAMESPACE = uuid.UUID("7f1f5a8e-3b4c-4d39-9a57-9e0b3c2a4f10")


def guid_for(source_digest: str, model_name: str) -> str:
    """A GUID that changes exactly when the FMU's sources change (reproducible builds)."""
    return "{" + str(uuid.uuid5(GUID_NAMESPACE, f"{model_name}:{source_digest}")) + "}"


def _format(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.17g}"
    return str(value)


PYTHONFMU_TOOL = "pythonfmu runtime"


def model_description(slave: PlatoonSlave, guid: str, version: str, runtime: str = PYTHONFMU_TOOL,
                      capabilities: dict[str, str] | None = None, source_files: tuple[str, ...] = ()) -> bytes:
    """The modelDescription.xml of ``slave`` (an instance, so value references are known).

    The native twins (fmus/native_build.py) share it: same variables and references, their own
    ``runtime`` in generationTool, their own capability flags, and the C files in sources/."""
    cls = type(slave)
    model_name = cls.__name__
    root = Element(
        "fmiModelDescription",
        {
            "fmiVersion": "2.0",
            "modelName": model_name,
            "guid": guid,
            "description": cls.description,
            "author": cls.author,
            "version": version,
            "license": cls.license,
            "generationTool": f"platoon-cosim {version} ({runtime})",
            "variableNamingConvention": "structured",
            "numberOfEventIndicators": "0",
        },
    )
    # a slave class may override a flag (LiveVehicle: a real robot has no FMU state to save)
    flags = capabilities if capabilities is not None else {**CAPABILITIES, **getattr(cls, "capabilities", {})}
    co_simulation = SubElement(root, "CoSimulation", {"modelIdentifier": model_name, **flags})
    if source_files:
        sources = SubElement(co_simulation, "SourceFiles")
        for name in source_files:
            SubElement(sources, "File", {"name": name})

    used_units = sorted({info.unit for info in cls.variables if info.unit})
    unit_definitions = SubElement(root, "UnitDefinitions")
    for unit in used_units:
        unit_node = SubElement(unit_definitions, "Unit", {"name": unit})
        SubElement(unit_node, "BaseUnit", {k: str(v) for k, v in UNITS[unit].items()})

    categories = SubElement(root, "LogCategories")
    for name, text in slave.log_categories.items():
        SubElement(categories, "Category", {"name": name, "description": text})

    experiment = cls.default_experiment
    SubElement(
        root,
        "DefaultExperiment",
        {
            "startTime": _format(float(experiment.start_time)),
            "stopTime": _format(float(experiment.stop_time)),
            "stepSize": _format(float(experiment.step_size)),
        },
    )

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
            type_attributes["start"] = _format(info.start)
        if info.min is not None:
            type_attributes["min"] = _format(info.min)
        if info.max is not None:
            type_attributes["max"] = _format(info.max)
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

    return parseString(tostring(root, "UTF-8")).toprettyxml(indent="  ", encoding="UTF-8")
