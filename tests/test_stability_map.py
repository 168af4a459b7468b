"""`platoon stability-map` on several processes draws what one process draws, and says what it does while
it works (it reads every trace of a sweep and solves the analysis on a grid: long enough to look hung)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.observers.progress import late_progress
from orchestrator.sweep.stability_map import draw_stability_map

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"


def env() -> dict[str, str]:
    out = {**os.environ, "COLUMNS": "120", "NO_COLOR": "1", "TERM": "dumb", "PLATOON_PROGRESS_SECONDS": "0"}
    out.pop("FORCE_COLOR", None)
    return out


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> Path:
    """Four runs of the study (paper and cacc, delays 0 and 0.3 s, no loss), as the docs' cut-short sweep."""
    folder = tmp_path_factory.mktemp("map")
    spec = folder / "sweep.toml"
    spec.write_text(f'base = "{REPO / "configs" / "study" / "string_stability.toml"}"\n[set]\n'
                    '"simulation.trace_every" = 5\n[grid]\n"platoon.speed_law" = ["paper", "cacc"]\n'
                    '"links.delay" = [0.0, 0.3]\n"links.loss" = [0.0]\n')
    done = subprocess.run([str(PLATOON), "sweep", str(spec), "--out", str(folder / "out"), "-q"], cwd=REPO, env=env(),
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return folder / "out"


def test_the_map_on_two_processes_is_the_map_on_one(sweep: Path, tmp_path: Path) -> None:
    ticks: dict[int, list[int]] = {}

    def progress(workers: int):
        def shown(traces: int, total: int):
            assert traces == 4 and total == 4 + 2 * 3  # 4 traces; 2 laws x 3 losses (the grid's resolution)
            ticks[workers] = []
            from contextlib import nullcontext
            return nullcontext(ticks[workers].append)
        return shown

    one, one_lines = draw_stability_map(sweep, tmp_path / "one.png", resolution=3, progress=progress(1), workers=1)
    two, two_lines = draw_stability_map(sweep, tmp_path / "two.png", resolution=3, progress=progress(2), workers=2)
    assert one.read_bytes() == two.read_bytes() and one_lines == two_lines and len(one_lines) == 2
    assert ticks[1] == ticks[2] == list(range(1, 11))


def test_the_command_says_what_it_measures_as_it_goes(sweep: Path, tmp_path: Path) -> None:
    done = subprocess.run([str(PLATOON), "stability-map", str(sweep), "--out", str(tmp_path / "map.png")], cwd=REPO,
                          env=env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert lines[0] == f"stability-map: reading {sweep} ...", lines  # before its imports and the sweep's files
    assert lines[1].startswith(f"stability-map: measuring 4 traces of {sweep} and computing the analytic maps ("), lines
    assert lines[-1].startswith("stability-map: 100% (") and "tasks)" in lines[-1], lines
    assert done.stdout.strip().splitlines()[-1] == f"wrote {tmp_path / 'map.png'}"


def test_a_late_progress_shows_only_work_that_takes_long(tmp_path: Path, monkeypatch) -> None:
    """A read done within its delay prints nothing; one that takes longer prints its progress lines."""
    from rich.console import Console

    monkeypatch.setenv("PLATOON_PROGRESS_SECONDS", "0")
    quick = tmp_path / "quick.txt"
    with open(quick, "w") as stream, late_progress("reading x.mcap", Console(file=stream), "chunks", after=3600.0) as tick:
        for done in range(1, 11):
            tick(done, 10)
    assert quick.read_text() == ""
    slow = tmp_path / "slow.txt"
    with open(slow, "w") as stream, late_progress("reading x.mcap", Console(file=stream), "chunks", after=0.0) as tick:
        for done in range(1, 11):
            tick(done, 10)
    lines = slow.read_text().splitlines()
    assert lines[0].startswith("reading x.mcap: 10% (1/10 chunks)") and lines[-1].startswith("reading x.mcap: 100% (10/10")


def test_a_late_progress_makes_its_console_only_to_show_it(tmp_path: Path, monkeypatch) -> None:
    """Given a function for its console (`platoon report`: rich then loads in the command's thread, while the
    trace is read), a quick read never calls it; a long one calls it once and shows the same lines."""
    from rich.console import Console

    monkeypatch.setenv("PLATOON_PROGRESS_SECONDS", "0")
    made: list[Console] = []
    with open(tmp_path / "slow.txt", "w") as stream:
        def make() -> Console:
            made.append(Console(file=stream))
            return made[-1]

        with late_progress("reading x.mcap", make, "chunks", after=3600.0) as tick:
            for done in range(1, 11):
                tick(done, 10)
        assert made == []
        with late_progress("reading x.mcap", make, "chunks", after=0.0) as tick:
            for done in range(1, 11):
                tick(done, 10)
    assert len(made) == 1
    lines = (tmp_path / "slow.txt").read_text().splitlines()
    assert lines[0].startswith("reading x.mcap: 10% (1/10 chunks)") and lines[-1].startswith("reading x.mcap: 100% (10/10")


def test_the_grid_holds_the_runs_values_and_gives_their_verdicts(sweep: Path) -> None:
    """Each run's closed-form verdict is read off the analytic grid's cell at its (delay, loss) when the
    grid holds it: the same verdict as the run's own peak growth."""
    from orchestrator.analysis.chain_model import chain_model
    from orchestrator.analysis.sampled_chain import peak_growth
    from orchestrator.analysis.string_stability import interior_vehicle
    from orchestrator.analysis.verdict import closed_form_verdict
    from orchestrator.sweep.stability_map import LAW, DELAY, LOSS, _compute, _points, grid_axis

    assert list(grid_axis([0.0, 0.1, 0.2, 0.3, 0.4], 11)) == pytest.approx([0.05 * k for k in range(9)], abs=1e-12)
    assert list(grid_axis([0.0, 0.05, 0.13], 4)) == pytest.approx([0.0, 0.13 / 3, 0.26 / 3, 0.13])  # on none: 4 points
    points = _points(sweep)
    laws = list(dict.fromkeys(p[LAW] for p in points))
    delays, losses = grid_axis([p[DELAY] for p in points], 3), grid_axis([p[LOSS] for p in points], 3)
    assert 0.3 in delays
    _, verdicts = _compute(points, laws, delays, losses, None, 1)
    for p in points:
        config = p["config"]
        verdict = verdicts[p[LAW]][(p[DELAY], p[LOSS])]
        assert verdict == closed_form_verdict(config, mean_square=False)  # the cell's peak is the run's own
        assert verdict.peak_growth_per_link == peak_growth(chain_model(config), interior_vehicle(config)).gain
    assert {verdicts[p[LAW]][(p[DELAY], p[LOSS])].string_stable for p in points} == {True, False}  # both are checked


def test_an_emptied_results_table_is_told_apart_from_a_sweep_with_no_run_and_resuming_rebuilds_it(
        sweep: Path, tmp_path: Path) -> None:
    """results.csv cut to its header while results/ holds the committed runs: stability-map said "no finished
    run yet"; it says what is there and how to get the table back, and resuming the sweep rebuilds it."""
    import shutil

    copy = tmp_path / "out"
    shutil.copytree(sweep, copy, symlinks=True)
    table = copy / "results.csv"
    header = table.read_text().splitlines()[0]
    table.write_text(header + "\n")
    shown = subprocess.run([str(PLATOON), "stability-map", str(copy), "--out", str(tmp_path / "map.png")], cwd=REPO,
                           env=env(), capture_output=True, text=True, timeout=600)
    assert shown.returncode == 2 and "Traceback" not in shown.stderr, shown.stderr
    assert "lists no run, but results/ holds 4 committed run(s)" in shown.stderr, shown.stderr
    spec = sweep.parent / "sweep.toml"
    resumed = subprocess.run([str(PLATOON), "sweep", str(spec), "--out", str(copy), "-q"], cwd=REPO, env=env(),
                             capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert len(table.read_text().splitlines()) == 5  # the header and the four runs again


def test_a_run_whose_probes_are_all_weak_is_counted_not_dropped() -> None:
    """The held sweep at 0.3-0.4 s and 60 % loss: every probe weak, no gain (NaN). The summary counts such a run
    with those inside the noise or with no probe to judge; runs that left the model are listed apart, and the
    counts add up to every run of the law."""
    import math

    from orchestrator.analysis.headline import Headline
    from orchestrator.analysis.verdict import CASCADE, NO_LOOP, ClosedFormVerdict, LoopState
    from orchestrator.sweep.stability_map import DELAY, LAW, LOSS, agreement_lines

    def point(delay: float, loss: float, headline: Headline | None, left: str = "") -> dict:
        gain = math.nan if headline is None else headline.growth
        return {LAW: "paper", DELAY: delay, LOSS: loss, "gain": gain, "headline": headline, "deviation": 0.01,
                "left": left, "settling": ""}

    points = [point(0.0, 0.0, Headline(1.16, 0.3, 1e-7, 4)),  # grows, outside the noise
              point(0.0, 0.2, Headline(1.10, 0.1, 0.05, 4)),  # inside the noise
              point(0.3, 0.6, Headline(math.nan, math.nan, None, 0, {0.1: "weak"})),  # no probe to judge
              point(0.0, 0.8, None, left="collision (vehicle4) from t = 83.5 s")]
    verdict = ClosedFormVerdict(CASCADE, 1.2, 0.43, LoopState(NO_LOOP))
    lines = agreement_lines(points, {"paper": {(p[DELAY], p[LOSS]): verdict for p in points}})
    assert lines[-1].endswith("closed form's in 1 of the 1 runs outside the noise (2 inside it or with no probe to judge)")
    assert any("delay 0.3 s, loss 0.6" in line and "NO PROBE TO JUDGE" in line for line in lines)
    assert any("delay 0 s, loss 0.8 left the model" in line for line in lines)
