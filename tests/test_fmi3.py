"""The FMI 3.0 co-simulation FMUs: the native C Vehicle and VirtualTarget behind the FMI 3.0 API.

Their model description (``fmus.modeldescription3``) is checked against the FMI 3.0 schema that FMPy
ships and against the FMI 2.0 description of the same model: same names, value references, types,
start values, units. The FMUs themselves (``fmus/native/fmi3.c``) are checked against the FMI 2.0
native FMUs, which run the same C model: equal trajectories in FMPy, in a hand-stepped platoon and
in a plain C host.
"""

from __future__ import annotations

from pathlib import Path

import fmpy
from fmpy.validation import validate_fmu
import pytest
from lxml import etree

from fmus.build import _slave_instance
from fmus.modeldescription import guid_for, model_description
from fmus.modeldescription3 import TIME_VALUE_REFERENCE, instantiation_token_for, model_description3
from fmus.slaves.Vehicle import Vehicle
from fmus.slaves.VirtualTarget import VirtualTarget

MODELS = {"Vehicle": Vehicle, "VirtualTarget": VirtualTarget}
FMI3_SCHEMA = Path(fmpy.__file__).parent / "schema" / "fmi3" / "fmi3ModelDescription.xsd"
FMI3_TYPE = {"Real": "Float64", "Integer": "Int32", "Boolean": "Boolean", "String": "String"}


def _description3(name: str, tmp_path: Path, digest: str = "0" * 64) -> Path:
    """A folder holding only the FMI 3.0 modelDescription.xml of model ``name`` (FMPy reads folders)."""
    folder = tmp_path / f"{name}-{digest[:8]}"
    folder.mkdir()
    token = instantiation_token_for(digest, name)
    (folder / "modelDescription.xml").write_bytes(model_description3(MODELS[name], token, "test"))
    return folder


def _read_description2(name: str, tmp_path: Path):
    """The FMI 2.0 description of the same model (as the pythonfmu FMU carries it), read by FMPy."""
    folder = tmp_path / "fmi2"
    folder.mkdir()
    (folder / "modelDescription.xml").write_bytes(model_description(_slave_instance(name), guid_for("0" * 64, name), "test"))
    return fmpy.read_model_description(str(folder))


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_model_description_is_valid_against_the_fmi3_schema_and_fmpy(name, tmp_path):
    folder = _description3(name, tmp_path)
    schema = etree.XMLSchema(file=str(FMI3_SCHEMA))
    document = etree.parse(str(folder / "modelDescription.xml"))
    assert schema.validate(document), "\n".join(str(error) for error in schema.error_log)
    # FMPy's own checks beyond the schema: variable names, start values, causality/variability
    # combinations, units, exactly one independent variable, unique value references, ModelStructure
    assert validate_fmu(str(folder)) == []


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_variables_are_the_fmi2_variables_with_the_same_value_references(name, tmp_path):
    fmi3 = fmpy.read_model_description(str(_description3(name, tmp_path)))
    fmi2 = _read_description2(name, tmp_path)

    assert fmi3.fmiVersion == "3.0" and fmi3.coSimulation.modelIdentifier == name
    independent = [v for v in fmi3.modelVariables if v.causality == "independent"]
    assert [(v.name, v.type, v.valueReference) for v in independent] == [("time", "Float64", TIME_VALUE_REFERENCE)]
    declared = [v for v in fmi3.modelVariables if v.causality != "independent"]
    assert len(declared) == len(fmi2.modelVariables)
    for v3, v2 in zip(declared, fmi2.modelVariables):
        assert (v3.name, v3.valueReference) == (v2.name, v2.valueReference)
        assert v3.type == FMI3_TYPE[v2.type]
        assert (v3.causality, v3.variability, v3.unit) == (v2.causality, v2.variability, v2.unit)
        assert (v3.start, v3.min, v3.max) == (v2.start, v2.min, v2.max), v3.name
    # the references are 0..n-1, so time's is outside them
    assert sorted(v.valueReference for v in declared) == list(range(len(declared)))
    assert TIME_VALUE_REFERENCE >= len(declared)


def _dependency_names(unknowns) -> dict[str, set[str] | None]:
    return {u.variable.name: None if u.dependencies is None else {d.name for d in u.dependencies} for u in unknowns}


@pytest.mark.parametrize("name", MODELS)
def test_fmi3_dependencies_name_the_fmi2_ones_plus_parameters_and_time(name, tmp_path):
    """FMPy resolves ``dependencies`` as value references in FMI 3.0 (indices in FMI 2.0): the names it
    finds must be the FMI 2.0 dependencies, plus, at communication points, the parameters the output
    is computed from, and ``time`` for ``output_time``."""
    fmi3 = fmpy.read_model_description(str(_description3(name, tmp_path)))
    fmi2 = _read_description2(name, tmp_path)

    outputs3, outputs2 = _dependency_names(fmi3.outputs), _dependency_names(fmi2.outputs)
    initial3, initial2 = _dependency_names(fmi3.initialUnknowns), _dependency_names(fmi2.initialUnknowns)
    assert list(outputs3) == list(outputs2) and list(initial3) == list(initial2)
    for output in outputs2:
        if outputs2[output] is None:
            assert outputs3[output] is None, output
        else:
            assert outputs2[output] <= outputs3[output], output
            added = outputs3[output] - outputs2[output]
            assert all(n == "time" or n.startswith("path.") for n in added), (output, added)
        if initial2[output] is None:
            assert initial3[output] is None, output
        else:
            assert initial3[output] - initial2[output] <= {"time"}, output
    assert outputs3["output_time"] == initial3["output_time"] == {"time"}
    assert outputs3["x"] == ({"path.kind", "path.radius", "path.x0", "path.y0", "path.heading", "path.direction"}
                             if name == "VirtualTarget" else set())
    if name == "VirtualTarget":
        assert outputs3["curvature"] == {"path.kind", "path.radius", "path.direction"}
        assert outputs3["arc_length"] == set()


def test_instantiation_token_follows_the_sources_and_differs_from_the_fmi2_guid():
    token = instantiation_token_for("a" * 64, "Vehicle")
    assert token == instantiation_token_for("a" * 64, "Vehicle")  # reproducible
    assert token != instantiation_token_for("b" * 64, "Vehicle")
    assert token != instantiation_token_for("a" * 64, "VirtualTarget")
    assert token != guid_for("a" * 64, "Vehicle")
