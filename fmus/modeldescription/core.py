"""What the FMI 2.0 and FMI 3.0 model descriptions share: units, number formatting, the GUID or
instantiationToken, the header attributes, UnitDefinitions, LogCategories, DefaultExperiment and the
serialization. The version-specific parts (capability flags, variables, ModelStructure) are in
``fmus.modeldescription.fmi2`` and ``fmus.modeldescription.fmi3``.
"""

from __future__ import annotations

import uuid
from typing import Any, Iterable, Mapping
from xml.dom.minidom import parseString
from xml.etree.ElementTree import Element, SubElement, tostring

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
    "1": {},  # dimensionless: a ratio (an m3pi wheel's gain)
}

GUID_NAMESPACE = uuid.UUID("7f1f5a8e-3b4c-4d39-9a57-9e0b3c2a4f10")
FMI_VERSION_TEXT = {2: "2.0", 3: "3.0"}
# the attribute that names the build: FMI 2.0's guid, FMI 3.0's instantiationToken
TOKEN_ATTRIBUTE = {2: "guid", 3: "instantiationToken"}


def instantiation_token(source_digest: str, model_name: str, fmi_version: int = 2) -> str:
    """The FMI 2.0 GUID or FMI 3.0 instantiationToken: changes exactly when the FMU's sources change
    (reproducible builds); the FMI 3.0 token has the version in its name, so the two FMUs of one model
    never share one."""
    name = model_name if fmi_version == 2 else f"{model_name}:fmi{FMI_VERSION_TEXT[fmi_version]}"
    return "{" + str(uuid.uuid5(GUID_NAMESPACE, f"{name}:{source_digest}")) + "}"


def format_value(value: Any) -> str:
    """A start value or bound as the model description writes it (floats to 17 significant digits)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.17g}"
    return str(value)


def root_element(model: type, fmi_version: int, token: str, version: str, runtime: str,
                 extra: Mapping[str, str] = {}) -> Element:
    """<fmiModelDescription> with the attributes both versions write, then ``extra``."""
    return Element("fmiModelDescription", {
        "fmiVersion": FMI_VERSION_TEXT[fmi_version],
        "modelName": model.__name__,
        TOKEN_ATTRIBUTE[fmi_version]: token,
        "description": model.description,
        "author": model.author,
        "version": version,
        "license": model.license,
        "generationTool": f"platoon-cosim {version} ({runtime})",
        "variableNamingConvention": "structured",
        **extra,
    })


def add_units_categories_experiment(root: Element, model: type, units: Iterable[str],
                                    log_categories: Mapping[str, str]) -> None:
    """<UnitDefinitions> (``units``, sorted), <LogCategories> and <DefaultExperiment>, in that order."""
    unit_definitions = SubElement(root, "UnitDefinitions")
    for unit in sorted(units):
        SubElement(SubElement(unit_definitions, "Unit", {"name": unit}), "BaseUnit",
                   {k: str(v) for k, v in UNITS[unit].items()})

    categories = SubElement(root, "LogCategories")
    for name, text in log_categories.items():
        SubElement(categories, "Category", {"name": name, "description": text})

    experiment = model.default_experiment
    SubElement(root, "DefaultExperiment", {
        "startTime": format_value(float(experiment.start_time)),
        "stopTime": format_value(float(experiment.stop_time)),
        "stepSize": format_value(float(experiment.step_size)),
    })


def serialize(root: Element) -> bytes:
    """The document as every one of our FMUs writes it: UTF-8, two-space indents."""
    return parseString(tostring(root, "UTF-8")).toprettyxml(indent="  ", encoding="UTF-8")
