"""A host that makes hostile FMI calls on one FMU instance: run as its own process, prints what it got.

    python tests/hostile_fmu_host.py <unzipped FMU folder> '<case as JSON>'

FMPy's FMU2Slave loads the FMU; the calls go through FMPy's fmi2 wrappers, an error status is
recorded (not raised) and the next call is made anyway, as a careless host would. The case is
``{"parameters": {name: value}, "calls": [[call, args...], ...]}``: the instance is instantiated with
logging on, set up at t = 0, given the parameters, put into initialization mode, then the calls run:

    ["exit"]                      fmi2ExitInitializationMode
    ["get"]                       fmi2GetReal of every Real output
    ["set", name, value]          fmi2Set<type> of one variable
    ["step", t, h]                fmi2DoStep(t, h)
    ["get_state"]                 fmi2GetFMUstate, then serialize it (kept for "set_state")
    ["set_state"]                 deserialize the kept state and fmi2SetFMUstate it
    ["set_state_bytes", text]     deserialize the bytes of ``text`` and set them as a state

then fmi2Terminate and fmi2FreeInstance. Every call prints one JSON line as soon as it returns
(``{"call": ..., "status": n, "values": [...]}``), every FMU log message one line
(``{"log": text, "status": n}``), and the end ``{"end": true}``: a host that crashes stops the lines
short and dies by a signal, which is how a test sees a crash.
"""

from __future__ import annotations

import json
import sys
from ctypes import byref
from typing import Any

from fmpy import read_model_description
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (
    FMU2Slave,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)
from fmpy.logging import addLoggerProxy
from fmpy.simulation import calloc, free

OK = 0


def emit(record: dict[str, Any]) -> None:
    print(json.dumps(record), flush=True)


def status_of(function: Any, *args: Any) -> tuple[int, Any]:
    try:
        return OK, function(*args)
    except FMICallException as error:
        return int(error.status), None


def main(directory: str, case: dict[str, Any]) -> None:
    description = read_model_description(directory)
    variables = {v.name: v for v in description.modelVariables}
    outputs = [v.valueReference for v in description.modelVariables if v.causality == "output"]
    slave = FMU2Slave(guid=description.guid, unzipDirectory=directory,
                      modelIdentifier=description.coSimulation.modelIdentifier, instanceName="hostile")

    def log(env: Any, instance: Any, status: int, category: Any, message: bytes) -> None:
        emit({"log": message.decode("utf-8", "replace") if message else "", "status": status})

    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(log)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
    addLoggerProxy(byref(callbacks))
    slave.instantiate(callbacks=callbacks, loggingOn=True)

    def set_value(name: str, value: Any) -> int:
        variable = variables[name]
        setter = {"Real": slave.setReal, "Integer": slave.setInteger, "Boolean": slave.setBoolean,
                  "String": slave.setString}[variable.type]
        return status_of(setter, [variable.valueReference], [value])[0]

    emit({"call": "setupExperiment", "status": status_of(slave.setupExperiment, None, 0.0)[0]})
    for name, value in case.get("parameters", {}).items():
        emit({"call": f"set {name}", "status": set_value(name, value)})
    emit({"call": "enterInitializationMode", "status": status_of(slave.enterInitializationMode)[0]})
    kept_state = None
    for call, *args in case["calls"]:
        record: dict[str, Any] = {"call": call, "args": args}
        if call == "exit":
            record["status"] = status_of(slave.exitInitializationMode)[0]
        elif call == "get":
            record["status"], values = status_of(slave.getReal, outputs)
            record["values"] = list(values) if values is not None else None
        elif call == "set":
            record["status"] = set_value(*args)
        elif call == "step":
            record["status"] = status_of(slave.doStep, float(args[0]), float(args[1]))[0]
        elif call == "get_state":
            record["status"], state = status_of(slave.getFMUstate)
            if state is not None:
                status, kept_state = status_of(slave.serializeFMUstate, state)
                record["status"] = max(record["status"], status)
        elif call == "set_state" or call == "set_state_bytes":
            data = kept_state if call == "set_state" else args[0].encode()
            record["status"], state = status_of(slave.deSerializeFMUstate, data)
            if state is not None:
                record["status"] = max(record["status"], status_of(slave.setFMUstate, state)[0])
        else:
            raise ValueError(f"unknown call {call!r}")
        emit(record)
    emit({"call": "terminate", "status": status_of(slave.terminate)[0]})
    # Free the instance but keep the library loaded, as orchestrator/components.py does (unloading a
    # pythonfmu binary from a Python host corrupts the heap at exit, a known pythonfmu problem).
    slave.fmi2FreeInstance(slave.component)
    emit({"end": True})


if __name__ == "__main__":
    main(sys.argv[1], json.loads(sys.argv[2]))
