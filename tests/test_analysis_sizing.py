"""Analyses size their work before they start: what would eat the machine is refused in one line naming the
key, links that deliver nothing are answered (orchestrator/analysis/sizing.py)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from orchestrator.analysis.chain_model import chain_model, loss_weights
from orchestrator.analysis.sampled_chain import COARSE_FREQUENCIES, Lifted, receiver_maps
from orchestrator.analysis.sizing import BYTES_PER_LIFTED, loss_terms
from orchestrator.scenario.config import load_config

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
STUDY = REPO / "configs" / "study" / "string_stability.toml"
MEMORY = 2 * 2**30  # bytes of address space every analysis below runs in (prlimit --as)


@pytest.mark.parametrize("loss, burst", [(0.1, 1.0), (0.6, 1.0), (0.99, 1.0), (0.1, 3.0), (0.8, 5.0), (0.5, 40.0),
                                         (1.0, 1.0)])
def test_the_loss_terms_counted_are_those_the_cascade_builds(loss: float, burst: float) -> None:
    assert loss_terms(loss, burst) == len(loss_weights(loss, burst))


def test_the_lifting_estimate_covers_the_memory_it_takes() -> None:
    """tracemalloc's peak of ``receiver_maps`` on the peak search's frequencies, lifted over 20 steps (0.4 s
    beacons on 0.02 s steps): the estimate is above it, and not far (the bound must not refuse what fits)."""
    config, _ = load_config(STUDY, ["links.period=0.4"])
    chain = chain_model(config)
    period = chain.lifting_period()
    assert period == 20
    w = np.geomspace(1e-3, 1.0, COARSE_FREQUENCIES)
    tracemalloc.start()
    try:
        receiver_maps(Lifted(w, config.simulation.step, period), chain.vehicle(1))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    estimate = BYTES_PER_LIFTED * COARSE_FREQUENCIES * period**2
    assert peak <= estimate <= 1.3 * peak, (peak, estimate)


def analyze(*sets: str, measure: bool = False, config: Path = STUDY) -> subprocess.CompletedProcess:
    """``platoon analyze`` in 2 GiB of address space (as the issue's floor asks)."""
    arguments = ["prlimit", f"--as={MEMORY}", str(PLATOON), "analyze", str(config),
                 "--measure" if measure else "--no-measure"]
    for assignment in sets:
        arguments += ["--set", assignment]
    return subprocess.run(arguments, cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "COLUMNS": "200"})


needs_prlimit = pytest.mark.skipif(shutil.which("prlimit") is None, reason="needs prlimit (util-linux)")


@needs_prlimit
@pytest.mark.parametrize("sets, key", [
    (("links.period=3600",), "links.period = 3600 s: the sampled-data cascade is lifted over 180,000 steps"),
    (("links.forward.period=10",), "links.forward.period = 10 s"),
    (("links.loss=0.999999", "links.burst=1000000"), "links.loss = 0.999999 with links.burst = 1e+06"),
])
def test_an_analysis_that_would_eat_the_machine_refuses_in_one_line_naming_the_key(sets: tuple[str, ...],
                                                                                   key: str) -> None:
    """Before: 23.9 GB and the OOM killer; "Unable to allocate 15.4 GiB" after 120 s. Now: one line, exit 2,
    within 2 GiB of address space."""
    done = analyze(*sets)
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert "Traceback" not in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert key in done.stderr, done.stderr


@needs_prlimit
def test_links_that_deliver_nothing_are_answered_not_divided_by() -> None:
    """Before: "cannot convert float NaN to integer" (paper law), a verdict of NaN (cacc). acc reads no link,
    so its analysis goes on."""
    for law in ("paper", "cacc"):
        done = analyze("links.loss=1.0", f"platoon.speed_law={law}")
        assert done.returncode == 0 and not done.stderr, (law, done.stderr)
        assert "links.loss = 1: no message sent over the links it sets ever arrives" in done.stdout, done.stdout
        assert "nan" not in done.stdout
    done = analyze("links.loss=1.0", "platoon.speed_law=acc")
    assert done.returncode == 0 and "sampled-data cascade" in done.stdout, done.stderr


@needs_prlimit
def test_a_disturbance_after_the_run_ends_is_refused_before_running_the_scenario() -> None:
    """Before: a traceback ("zero-size array to reduction operation maximum")."""
    done = analyze('disturbance=[{vehicle=2,kind="speed",start=500.0,duration=1.0,value=1.0}]', measure=True,
                   config=REPO / "configs" / "paper" / "platoon.toml")
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "disturbance 1 (vehicle 2): start = 500 s is not before the run's end (simulation.stop_time = 100 s)" \
           in done.stderr, done.stderr


@needs_prlimit
def test_stability_map_refuses_a_sweep_whose_analysis_would_eat_the_machine(tmp_path: Path, fmu_dir: Path) -> None:
    """A sweep of 1-hour beacons (runs fine: they are short) whose map would lift the cascade over 180 000
    steps: refused in one line naming the run and the key, before any trace is read."""
    spec = tmp_path / "sweep.toml"
    spec.write_text(f'base = "{STUDY}"\n[set]\n"simulation.stop_time" = 2.0\n[grid]\n'
                    '"platoon.speed_law" = ["cacc"]\n"links.delay" = [0.0]\n"links.loss" = [0.0]\n'
                    '"links.period" = [3600.0]\n')
    env = {**os.environ, "COLUMNS": "200"}
    done = subprocess.run([str(PLATOON), "sweep", str(spec), "--out", str(tmp_path / "out"), "-q"], cwd=REPO,
                          capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr
    done = subprocess.run(["prlimit", f"--as={MEMORY}", str(PLATOON), "stability-map", str(tmp_path / "out")],
                          cwd=REPO, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "links.period = 3600 s: the sampled-data cascade is lifted over 180,000 steps" in done.stderr, done.stderr


def test_stability_map_refuses_a_trace_replaced_by_a_link_to_a_fifo_instead_of_hanging(tmp_path: Path,
                                                                                      fmu_dir: Path) -> None:
    """Report and stability refuse a trace that is a FIFO; stability-map blocked on it forever."""
    spec = tmp_path / "sweep.toml"
    spec.write_text(f'base = "{STUDY}"\n[set]\n"simulation.stop_time" = 2.0\n[grid]\n"platoon.speed_law" = ["cacc"]\n'
                    '"links.delay" = [0.0]\n"links.loss" = [0.0]\n')
    env = {**os.environ, "COLUMNS": "200"}
    done = subprocess.run([str(PLATOON), "sweep", str(spec), "--out", str(tmp_path / "out"), "-q"], cwd=REPO,
                          capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stderr
    [trace] = list((tmp_path / "out").rglob("*.mcap"))
    trace.unlink()
    os.mkfifo(tmp_path / "fifo")
    trace.symlink_to(tmp_path / "fifo")
    done = subprocess.run([str(PLATOON), "stability-map", str(tmp_path / "out")], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env=env)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "is not a regular file" in done.stderr, done.stderr
