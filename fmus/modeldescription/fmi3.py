"""The FMI 3.0 model description of a native FMU, from the same ``VariableInfo`` declarations.

The FMI 2.0 description (``fmus.modeldescription.fmi2``) and this one describe the same variables with
the same value references: the i-th declared variable has value reference i, 0..n-1, in both
versions, so a host's wiring and the C variable tables serve both. What FMI 3.0 changes:

* Types: Real is Float64, Integer is Int32; a String's start value is a ``<Start value=.../>`` child.
* ``instantiationToken`` replaces ``guid``: derived like the FMI 2.0 GUID from the digest of the
  sources, with the FMI version in the name, so the two FMUs of one model never share a token.
* Exactly one independent variable, ``time`` (FMI 3.0, section 2.4.7.4, causality: "Exactly one
  variable of an FMU must be defined as independent"; FMPy's validation checks it), never set.
  Its value reference is ``TIME_VALUE_REFERENCE``, see there.
* ModelStructure lists unknowns and their dependencies by value reference (FMI 2.0: by index into
  ModelVariables), in ``<Output>`` and ``<InitialUnknown>`` elements. The knowns at communication
  points also include the parameters and the independent variable (FMI 3.0, section 2.4.8, the
  ``dependencies`` attribute; FMI 2.0 knew only inputs and states there), so an output computed from
  parameters lists them (``VariableInfo.parameter_dependencies``) and ``output_time`` lists ``time``
  (``VariableInfo.depends_on_time``).

Capability flags of the native C FMUs, each set on purpose:

* needsExecutionTool: false. The binary is the whole model, compiled C needing only libc and libm.
* canHandleVariableCommunicationStepSize: true. A step is split into equal RK4 substeps no longer
  than ``max_substep``, so any step size integrates with the same accuracy.
* canGetAndSetFMUState / canSerializeFMUState: true. A state copies the whole instance (parameters,
  inputs, stepper), tested by a round trip.
* providesIntermediateUpdate, mightReturnEarlyFromDoStep, hasEventMode: false. A step runs to its
  end in one call and there are no events.
* canBeInstantiatedOnlyOncePerProcess: false. All state lives on the instance.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping
from xml.etree.ElementTree import Element, SubElement

from fmus.modeldescription.core import (add_units_categories_experiment, format_value, instantiation_token,
                                        root_element, serialize)

if TYPE_CHECKING:  # annotations only: writing a description must not need pythonfmu's runtime
    from fmus.slaves.base import VariableInfo

# The independent variable's value reference. Not n (one past the last variable): that would move
# whenever a model gains a variable, and differ between Vehicle and VirtualTarget. A fixed number far
# above any model's 0..n-1 keeps the declared variables' references those of the FMI 2.0 FMUs, never
# collides, and is the same in every FMU. Not 0xFFFFFFFF, which some importers use as "no reference".
TIME_VALUE_REFERENCE = 1_000_000
TIME_NAME = "time"

TYPE_NAMES = {"Real": "Float64", "Integer": "Int32", "Boolean": "Boolean", "String": "String"}

CAPABILITIES = {
    "needsExecutionTool": "false",
    "canBeInstantiatedOnlyOncePerProcess": "false",
    "canGetAndSetFMUState": "true",
    "canSerializeFMUState": "true",
    "providesDirectionalDerivatives": "false",
    "providesAdjointDerivatives": "false",
    "providesPerElementDependencies": "false",
    "canHandleVariableCommunicationStepSize": "true",
    "maxOutputDerivativeOrder": "0",
    "providesIntermediateUpdate": "false",
    "mightReturnEarlyFromDoStep": "false",
    "canReturnEarlyAfterIntermediateUpdate": "false",
    "hasEventMode": "false",
    "providesEvaluateDiscreteStates": "false",
}

# What the framework logs under (fmus/native/framework.c, the same names as the FMI 2.0 FMUs'):
# refusals always, other messages when the host turned logging on.
LOG_CATEGORIES = {
    "logStatusWarning": "Messages with status fmi3Warning",
    "logStatusDiscard": "Steps refused with fmi3Discard (the motion breaks down or its outputs would not be "
                        "finite; the state is kept)",
    "logStatusError": "Calls refused with fmi3Error, with the reason (invalid parameters, unknown value "
                      "references, calls in the wrong state, unsupported functions)",
    "logStatusFatal": "Messages with status fmi3Fatal",
    "logAll": "Every message, also those with status fmi3OK (with logging on)",
}


def instantiation_token_for(source_digest: str, model_name: str) -> str:
    """The FMI 3.0 instantiationToken: changes exactly when the sources change, like the FMI 2.0 GUID
    (``fmus.modeldescription.fmi2.guid_for``), and differs from it for the same sources."""
    return instantiation_token(source_digest, model_name, fmi_version=3)


def value_references(variables: tuple[VariableInfo, ...]) -> dict[str, int]:
    """Value reference by name: declaration order, 0..n-1 (as pythonfmu numbers the FMI 2.0 FMUs)."""
    return {info.name: position for position, info in enumerate(variables)}


def _variable(parent: Element, info: VariableInfo, reference: int) -> None:
    attributes = {
        "name": info.name,
        "valueReference": str(reference),
        "description": info.description,
        "causality": info.causality,
        "variability": info.resolved_variability,
    }
    if info.causality == "output":
        attributes["initial"] = "calculated"
    if info.unit:
        attributes["unit"] = info.unit
    if info.min is not None:
        attributes["min"] = format_value(info.min)
    if info.max is not None:
        attributes["max"] = format_value(info.max)
    has_start = info.causality != "output"
    if has_start and info.type != "String":
        attributes["start"] = format_value(info.start)
    node = SubElement(parent, TYPE_NAMES[info.type], attributes)
    if has_start and info.type == "String":
        SubElement(node, "Start", {"value": info.start})


def _dependencies(names: tuple[str, ...], with_time: bool, reference_of: Mapping[str, int]) -> str:
    references = sorted({reference_of[name] for name in names})
    if with_time:
        references.append(TIME_VALUE_REFERENCE)  # the largest: the list stays ordered
    return " ".join(map(str, references))


def model_description(model: type, instantiation_token: str, version: str,
                       log_categories: Mapping[str, str] = LOG_CATEGORIES) -> bytes:
    """The FMI 3.0 modelDescription.xml of ``model`` (a slave class: ``variables``, ``description``,
    ``author``, ``license``, ``default_experiment``), for a co-simulation FMU of the same name."""
    variables: tuple[VariableInfo, ...] = model.variables
    reference_of = value_references(variables)
    assert TIME_VALUE_REFERENCE not in reference_of.values() and TIME_NAME not in reference_of
    root = root_element(model, 3, instantiation_token, version, "native C")
    SubElement(root, "CoSimulation", {"modelIdentifier": model.__name__, **CAPABILITIES})
    add_units_categories_experiment(root, model, {info.unit for info in variables if info.unit} | {"s"},
                                    log_categories)

    variables_node = SubElement(root, "ModelVariables")
    # FMI 3.0: no start value and no initial for the independent variable; its value is the startTime
    # given to fmi3EnterInitializationMode, then the current communication point.
    SubElement(variables_node, "Float64", {
        "name": TIME_NAME, "valueReference": str(TIME_VALUE_REFERENCE),
        "description": "Simulation time: the current communication point",
        "causality": "independent", "variability": "continuous", "unit": "s",
    })
    for info in variables:
        _variable(variables_node, info, reference_of[info.name])

    # Output: knowns at communication points are the inputs, the (hidden) states, the parameters and
    # time. An output that is a function of the state alone lists none of them ("").
    # InitialUnknown: knowns in Initialization Mode are the inputs, the variables with initial="exact"
    # (all our parameters) and time (the start time); see fmus.modeldescription.fmi2 for the FMI 2.0 twin.
    # No attribute at all means "depends on every known".
    structure = SubElement(root, "ModelStructure")
    outputs = [info for info in variables if info.causality == "output"]
    for info in outputs:
        attributes = {"valueReference": str(reference_of[info.name])}
        if info.depends_on is not None:
            attributes["dependencies"] = _dependencies(info.depends_on + info.parameter_dependencies,
                                                       info.depends_on_time, reference_of)
        SubElement(structure, "Output", attributes)
    for info in outputs:
        attributes = {"valueReference": str(reference_of[info.name])}
        if info.initial_depends_on is not None:
            attributes["dependencies"] = _dependencies(info.initial_depends_on, info.depends_on_time, reference_of)
        SubElement(structure, "InitialUnknown", attributes)

    return serialize(root)
