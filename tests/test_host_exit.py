"""A plain FMPy script that ran our FMUs exits cleanly (fmus/slaves/host_exit.py says why it did not).

The fault is a use-after-free in pythonfmu's binary at process exit, which glibc turns into an abort
only sometimes (once in CI: "free(): corrupted unsorted chunks" after the results were printed). To
see it every time, the script runs under valgrind's memcheck, which reports the invalid access in
``finalizePythonInterpreter`` whenever the unguarded binary resets its freed PyState pointer.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

SCRIPT = (
    "import sys, fmpy\n"
    "for name in ('Vehicle', 'VirtualTarget'):\n"
    "    r = fmpy.simulate_fmu(f'{sys.argv[1]}/{name}.fmu', stop_time=0.05)\n"
    "    print(name, len(r))\n"
)


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="needs valgrind to see the invalid access")
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the guard and the fault are Linux-only")
def test_fmpy_script_leaves_without_touching_freed_memory(fmu_dir, tmp_path):
    result = subprocess.run(
        ["valgrind", "--error-limit=no", sys.executable, "-c", SCRIPT, str(fmu_dir)],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
        env={"PYTHONMALLOC": "malloc", "PATH": "/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.split() == ["Vehicle", "6", "VirtualTarget", "6"]
    assert "ERROR SUMMARY" in result.stderr  # valgrind really watched the run
    reports = result.stderr.split("\n==")
    at_exit = [r for r in reports if "finalizePythonInterpreter" in r]
    assert not at_exit, "invalid access at exit:\n" + "\n".join(at_exit)[:3000]
