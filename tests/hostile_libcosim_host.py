"""libcosim (C++, through libcosimpy) as a host of one FMU given hostile values: run as its own process.

    python tests/hostile_libcosim_host.py <fmu> '{"parameters": {...}, "override": {...}, "steps": n}'

One slave; ``parameters`` become libcosim initial values, ``override`` input values set with the
override manipulator before the first step. Then ``steps`` single steps of 0.01 s, each printed as a
JSON line ``{"step": k, "ok": bool}`` (a failing step raises or returns False in libcosimpy), and the
last values of every Real output as ``{"outputs": [...]}``. The end is ``{"end": true}``; a crashed
host prints no end and dies by a signal.
"""

from __future__ import annotations

import json
import sys

from libcosimpy.CosimEnums import CosimVariableCausality, CosimVariableType
from libcosimpy.CosimExecution import CosimExecution
from libcosimpy.CosimManipulator import CosimManipulator
from libcosimpy.CosimObserver import CosimObserver
from libcosimpy.CosimSlave import CosimLocalSlave

SETTERS = {
    CosimVariableType.REAL: "real_initial_value",
    CosimVariableType.INTEGER: "integer_initial_value",
    CosimVariableType.BOOLEAN: "boolean_initial_value",
    CosimVariableType.STRING: "string_initial_value",
}


def emit(record: dict) -> None:
    print(json.dumps(record), flush=True)


def main(fmu: str, case: dict) -> None:
    execution = CosimExecution.from_step_size(10_000_000)  # 0.01 s in ns
    slave = CosimLocalSlave(fmu, "hostile")
    index = execution.add_local_slave(slave)
    variables = {v.name.decode(): v for v in execution.slave_variables(index)}
    for name, value in case.get("parameters", {}).items():
        variable = variables[name]
        emit({"set": name, "ok": bool(getattr(execution, SETTERS[CosimVariableType(variable.type)])(
            index, variable.reference, value))})
    manipulator = CosimManipulator.create_override()
    execution.add_manipulator(manipulator)
    for name, value in case.get("override", {}).items():
        emit({"override": name, "ok": bool(manipulator.slave_real_values(index, [variables[name].reference], [value]))})
    last = CosimObserver.create_last_value()
    execution.add_observer(last)
    outputs = [v.reference for v in variables.values()
               if CosimVariableCausality(v.causality) == CosimVariableCausality.OUTPUT
               and CosimVariableType(v.type) == CosimVariableType.REAL]
    for k in range(case.get("steps", 3)):
        try:
            ok = bool(execution.step())
        except Exception as error:  # noqa: BLE001 - libcosimpy raises on some failures
            ok = False
            emit({"step_error": str(error)[:300]})
        emit({"step": k, "ok": ok})
    emit({"outputs": list(last.last_real_values(index, outputs))})
    del execution, slave
    emit({"end": True})


if __name__ == "__main__":
    main(sys.argv[1], json.loads(sys.argv[2]))
