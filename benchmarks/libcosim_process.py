"""libcosim running an SSP to its end, as a whole process: the baseline of ``platoon bench wholerun``.

Run by path (``python .../libcosim_process.py SSD STEPS OBSERVER``), not with ``-m``: it imports the
standard library and libcosimpy only, so its start-up is libcosim's own, as a user's script would be.

OBSERVER says what libcosim records while stepping, so that the baseline does the same work as the
run it is compared with:

* ``none``: nothing (as an untraced run);
* ``outputs``: a time-series observer on every output of every component, every step (the values a
  traced ``platoon run`` records);
* ``last-value``: libcosim's last-value observer, which reads every variable of every component
  after each step (what the earlier benchmark attached, more work than an untraced run);
* ``file``: libcosim's file observer, which writes every variable of every component, every step, to
  one CSV file per component in a fresh folder next to the SSD (libcosim's way of keeping a run on
  disk: the baseline of a traced run that writes its file; the folder is removed after the run).

Prints one ``RESULT {json}`` line (the time reached, which the benchmark checks) and leaves with ``os._exit``
(pythonfmu FMUs live in this interpreter; see benchmarks/child.py).
"""

from __future__ import annotations

import json
import os
import sys

OBSERVERS = ("none", "outputs", "last-value", "file")


def main(ssd: str, steps: int, observer: str) -> dict:
    from libcosimpy.CosimEnums import CosimVariableCausality, CosimVariableType
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver

    log_output_level(CosimLogLevel.ERROR)
    execution = CosimExecution.from_ssp_file(ssd)
    slaves = {info.name.decode(): info.index for info in execution.slave_infos()}
    variables = {name: execution.slave_variables(index) for name, index in slaves.items()}
    if observer == "last-value":
        watch = CosimObserver.create_last_value()
        if not execution.add_observer(watch):
            raise RuntimeError("libcosim: adding the last-value observer failed")
    elif observer == "outputs":
        series = CosimObserver.create_time_series(buffer_size=steps + 1)
        if not execution.add_observer(series):
            raise RuntimeError("libcosim: adding the time-series observer failed")
        for name, index in slaves.items():
            for variable in variables[name]:
                if CosimVariableCausality(variable.causality) == CosimVariableCausality.OUTPUT:
                    series.start_time_series(index, variable.reference, CosimVariableType(variable.type))
    elif observer == "file":
        import tempfile

        folder = tempfile.mkdtemp(prefix="libcosim-files-", dir=os.path.dirname(os.path.abspath(ssd)))
        if not execution.add_observer(CosimObserver.create_to_dir(folder)):
            raise RuntimeError("libcosim: adding the file observer failed")
    if not execution.step(steps):
        raise RuntimeError("libcosim: stepping failed")
    result = {"time_ns": execution.status().current_time}
    if observer == "file":
        del execution  # the observer closes its files with the execution
        import shutil

        result["bytes"] = sum(os.path.getsize(os.path.join(folder, name)) for name in os.listdir(folder))
        shutil.rmtree(folder)
    return result


if __name__ == "__main__":
    arguments = sys.argv[1:]
    usage = f"usage: libcosim_process.py SSD STEPS {'|'.join(OBSERVERS)}"
    if arguments[:1] in (["-h"], ["--help"]):  # standard library only here (see above): no shared helper
        print(f"{usage}\n\n{__doc__.strip()}")
        raise SystemExit(0)
    if len(arguments) != 3 or arguments[2] not in OBSERVERS:
        print(f"error: {usage}", file=sys.stderr)
        raise SystemExit(2)
    code = 0
    try:
        result = main(arguments[0], int(arguments[1]), arguments[2])
        sys.stdout.write("RESULT " + json.dumps(result) + "\n")
    except BaseException:  # report, then leave without interpreter teardown all the same
        import traceback

        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
