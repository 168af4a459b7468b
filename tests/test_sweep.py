"""``platoon sweep`` and ``platoon sweep-plot`` end to end, as real subprocesses.

What a user relies on: every point of the sweep gets exactly one row in results.csv, whatever stopped
the sweep before (SIGKILL included), and a restart redoes nothing finished; a failing or rejected run
is recorded with its error while the others go on; the row's per-vehicle columns are what
``platoon report --json`` says of the run's trace; a Dask cluster gives the same rows as local workers.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import matplotlib.image
import pytest

from orchestrator.analysis.metrics import report_json, summarize
from orchestrator.analysis.validity import departures_of_trace
from orchestrator.sweep.worker import flatten_report
from orchestrator.trace import load
from tests.conftest import SPEED_TO_ZERO
from tests.test_cli import error_line

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = REPO / "configs" / "paper" / "platoon.toml"
POLL = 0.05  # s between looks at a running sweep's folder (synchronization only, nothing timed is asserted)


def platoon(*args: object, cwd: Path = REPO, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """The console script on this tree's code (PYTHONPATH: the worktree, not another editable install)."""
    return subprocess.run([str(PLATOON), *map(str, args)], cwd=cwd, env=_env(), capture_output=True, text=True,
                          timeout=timeout)


def _env() -> dict[str, str]:
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb", "PYTHONPATH": str(REPO)}
    env.pop("FORCE_COLOR", None)
    return env


def sweep_file(folder: Path, text: str, base: Path = PAPER, name: str = "sweep.toml") -> Path:
    path = folder / name
    path.write_text(f'base = "{base}"\n{text}')
    return path


def rows(out: Path) -> list[dict[str, str]]:
    with open(out / "results.csv", newline="") as file:
        return list(csv.DictReader(file))


def report_of(out: Path, row: dict[str, str]) -> dict[str, float]:
    """What ``platoon report --json`` says of the row's trace, flattened as the row's columns."""
    trace = load(out / row["trace"])
    from orchestrator.scenario.config import config_from_mapping

    config = config_from_mapping(trace.config)
    return flatten_report(report_json(summarize(trace, config), config, departures_of_trace(trace, config)))


def assert_row_is_its_report(out: Path, row: dict[str, str]) -> None:
    """The row's summary is accumulated while the run records (as ``platoon run`` prints it), the report's
    from the trace read back: the same sums in blocks of other sizes, so equal to rounding (1e-12
    relative, as tests/test_summary.py argues), not bit for bit."""
    expected = report_of(out, row)
    assert row["run.left_model"] == expected.pop("run.left_model")  # text: where the run left the model, "" inside
    assert {k for k in row if k.startswith(("vehicle", "last.")) and row[k]} == set(expected)
    for key, value in expected.items():
        if math.isnan(value):  # path_error_max: no disturbance started within the run
            assert math.isnan(float(row[key])), key
        else:
            assert float(row[key]) == pytest.approx(value, rel=1e-12, abs=1e-15), key


# --- bad sweep files: exit 2, one line naming the file and the key ----------------------------------

BAD_SWEEPS = {
    "unknown-table": ('[grids]\n"platoon.count" = [1]\n', ["grids", "unknown key"]),
    "not-a-list": ('[grid]\n"platoon.count" = 4\n', ["grid 'platoon.count'", "list"]),
    "listed-twice": ('[grid]\n"platoon.count" = [2, 2]\n', ["'platoon.count'", "2 is listed twice"]),
    "unknown-config-key": ('[grid]\n"platoon.colour" = ["red"]\n', ["platoon.colour", "unknown key"]),
    "bad-range": ('[random]\nsamples = 2\nranges = { "platoon.k_v" = [2.0, 1.0] }\n', ["'platoon.k_v'", "low <= high"]),
    "nothing-varies": ('[set]\n"platoon.count" = 2\n', ["nothing varies"]),
    "both-set-and-grid": ('[set]\n"platoon.count" = 2\n[grid]\n"platoon.count" = [1, 2]\n', ["'platoon.count'", "both"]),
}


@pytest.mark.parametrize("text, pieces", BAD_SWEEPS.values(), ids=BAD_SWEEPS.keys())
def test_a_bad_sweep_file_exits_2_naming_file_and_key(tmp_path: Path, text: str, pieces: list[str]) -> None:
    path = sweep_file(tmp_path, text)
    result = platoon("sweep", path, "--out", tmp_path / "out")
    assert result.returncode == 2, result.stderr
    line = error_line(result)
    assert str(path) in line
    for piece in pieces:
        assert piece in line, line


def test_a_missing_base_exits_2(tmp_path: Path) -> None:
    path = sweep_file(tmp_path, '[grid]\n"platoon.count" = [1]\n', base=tmp_path / "nowhere.toml")
    result = platoon("sweep", path, "--out", tmp_path / "out")
    assert result.returncode == 2
    assert "nowhere.toml" in error_line(result) and "no such file" in error_line(result)


def test_a_sweep_files_base_is_relative_to_the_sweep_file_not_the_current_folder(tmp_path: Path,
                                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from orchestrator.sweep.spec import SweepError, load_sweep

    folder = tmp_path / "studies" / "maps"
    folder.mkdir(parents=True)
    (tmp_path / "studies" / "base.toml").write_text(PAPER.read_text())
    (folder / "sweep.toml").write_text('base = "../base.toml"\n[grid]\n"platoon.count" = [1, 2]\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # neither the sweep's folder nor its base's
    assert load_sweep(folder / "sweep.toml").base.resolve() == (tmp_path / "studies" / "base.toml").resolve()
    shipped = load_sweep(REPO / "configs" / "sweeps" / "offset_map.toml")  # the shipped sweep, run from elsewhere
    assert shipped.base.resolve() == PAPER.resolve()
    (elsewhere / "base.toml").write_text(PAPER.read_text())  # a base beside the current folder is not the one named
    (folder / "near.toml").write_text('base = "base.toml"\n[grid]\n"platoon.count" = [1]\n')
    with pytest.raises(SweepError, match="relative to the sweep file's folder"):
        load_sweep(folder / "near.toml")


def test_a_file_a_config_names_is_relative_to_the_config_not_the_current_folder(tmp_path: Path,
                                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    from orchestrator.scenario.config import load_config

    (tmp_path / "hil").mkdir()
    config = tmp_path / "hil" / "live.toml"
    config.write_text((REPO / "configs" / "hil" / "m3pi_live3.toml").read_text()
                      + '\n[vehicles.2]\nendpoint = "zenoh"\nzenoh_config = "zenoh.json5"\n')
    monkeypatch.chdir(tmp_path)
    parsed, _ = load_config(config)
    assert Path(parsed.override(2).zenoh_config) == tmp_path / "hil" / "zenoh.json5"
    typed, _ = load_config(config, ['vehicles.2.zenoh_config="mine.json5"'])  # a --set path: the current folder's
    assert typed.override(2).zenoh_config == "mine.json5"


# --- failures are recorded, the sweep goes on ------------------------------------------------------

def test_failed_and_rejected_runs_are_recorded_and_the_others_run(tmp_path: Path, fmu_dir: Path) -> None:
    # A -100 m/s pulse on vehicle 4 from t = 1 s: a run that stops before it completes, one that goes past
    # it fails (speed below zero); d* = 120 m > 2R is rejected by the config and never runs.
    base = tmp_path / "base.toml"
    base.write_text(PAPER.read_text() + SPEED_TO_ZERO)
    path = sweep_file(tmp_path, '[grid]\n"simulation.stop_time" = [0.5, 2.0]\n"platoon.d_star" = [75.0, 120.0]\n', base=base)
    out = tmp_path / "out"
    result = platoon("sweep", path, "--out", out, "--workers", "2")
    assert result.returncode == 1, result.stderr
    assert "3 of 4 runs failed or were rejected" in result.stderr
    by_point = {(r["simulation.stop_time"], r["platoon.d_star"]): r for r in rows(out)}
    assert len(by_point) == 4
    completed = by_point[("0.5", "75.0")]
    assert completed["status"] == "completed" and completed["error"] == "" and float(completed["wall_time"]) > 0
    assert_row_is_its_report(out, completed)
    assert completed["last.path_offset"] == completed["vehicle4.path_offset"]
    failed = by_point[("2.0", "75.0")]
    assert failed["status"] == "failed" and "vehicle4 failed at t = 1" in failed["error"] and "speed" in failed["error"]
    assert load(out / failed["trace"]).run["status"] == "failed"  # its trace is kept, up to the failure
    assert failed["last.path_offset"] == ""
    for stop in ("0.5", "2.0"):
        rejected = by_point[(stop, "120.0")]
        assert rejected["status"] == "invalid" and "platoon.d_star = 120.0" in rejected["error"] and rejected["trace"] == ""
    # the map says what became of each point: a value, "failed", "invalid" (a refused config is no blank cell)
    figure = drawn_figure(out, "last.path_offset", tmp_path / "map.png", x="platoon.d_star", y="simulation.stop_time")
    (axis,) = [a for a in figure.axes if a.get_title().startswith("platoon.law = ")]
    texts = {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text() for t in axis.texts}
    assert texts[(1, 0)] == "failed" and texts[(0, 1)] == texts[(1, 1)] == "invalid" and texts[(0, 0)] not in ("", "failed")
    assert axis.get_xlabel() == "platoon.d_star [m]" and figure.axes[0].get_ylabel() == "simulation.stop_time [s]"

    # started again: everything is done, nothing is redone (the result files stay as they were)
    before = {p.name: p.read_bytes() for p in (out / "results").iterdir()}
    again = platoon("sweep", path, "--out", out)
    assert again.returncode == 1 and "4 done before, 0 to run" in again.stderr
    assert {p.name: p.read_bytes() for p in (out / "results").iterdir()} == before
    assert len(rows(out)) == 4

    # --retry-failed: the three runs not completed run again (and fail again), the completed one stays
    retried = platoon("sweep", path, "--out", out, "--retry-failed")
    assert retried.returncode == 1 and "1 done before, 3 to run" in retried.stderr
    assert (out / "results" / f"{completed['id']}.json").read_bytes() == before[f"{completed['id']}.json"]
    assert [(r["id"], r["status"]) for r in rows(out)] == [(r["id"], r["status"]) for r in by_point.values()]


# --- SIGKILL mid-way, then resume -------------------------------------------------------------------

def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def _descendants(pid: int) -> list[int]:
    """Processes below ``pid``: its children (the warm workers), theirs (the runs), and so on."""
    found = _children(pid)
    for child in list(found):
        found += _descendants(child)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_sweep_killed_with_sigkill_resumes_with_every_row_exactly_once(tmp_path: Path, fmu_dir: Path) -> None:
    k_v = [round(0.4 + 0.1 * i, 2) for i in range(8)]
    path = sweep_file(tmp_path, '[set]\n"simulation.stop_time" = 30.0\n[grid]\n'
                                f'"platoon.k_v" = [{", ".join(map(str, k_v))}]\n')
    out = tmp_path / "out"
    command = [str(PLATOON), "sweep", str(path), "--out", str(out), "--workers", "2"]
    sweep = subprocess.Popen(command, cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        runs_under_way: list[int] = []
        deadline = time.monotonic() + 240
        while len(list((out / "results").glob("*.json"))) < 2:  # two runs committed, others under way
            runs_under_way = [p for p in _children(sweep.pid) if _alive(p)] or runs_under_way
            assert sweep.poll() is None, sweep.communicate()
            assert time.monotonic() < deadline, "the sweep committed no run in 240 s"
            time.sleep(POLL)
        runs_under_way = [p for p in _children(sweep.pid) if _alive(p)] or runs_under_way
        sweep.kill()
    finally:
        if sweep.poll() is None:
            sweep.kill()
        sweep.communicate()
    assert sweep.returncode == -signal.SIGKILL
    done_before = {p.name: p.read_bytes() for p in (out / "results").glob("*.json")}
    assert 2 <= len(done_before) < len(k_v), "the sweep finished before the kill: nothing was tested"
    assert runs_under_way, "no run process was seen under the sweep"

    result = platoon("sweep", path, "--out", out, "--workers", "2")
    assert result.returncode == 0, result.stderr
    assert f"{len(done_before)} done before, {len(k_v) - len(done_before)} to run" in result.stderr
    table = rows(out)
    assert sorted(float(r["platoon.k_v"]) for r in table) == k_v  # every point, exactly once
    assert len({r["id"] for r in table}) == len(k_v)
    assert all(r["status"] == "completed" for r in table)
    for name, content in done_before.items():  # finished before the kill: not redone
        assert (out / "results" / name).read_bytes() == content
    assert not list((out / "traces").glob("*.part"))
    assert sorted(p.name for p in (out / "traces").iterdir()) == sorted(f"{r['id']}.mcap" for r in table)
    for row in table:
        assert_row_is_its_report(out, row)


def test_the_runs_die_with_a_killed_sweep(tmp_path: Path, fmu_dir: Path) -> None:
    # runs of 10^4 simulated seconds (10^6 steps, the most a run may take without --allow-long; minutes
    # here): alive after the kill only if they outlive their sweep
    path = sweep_file(tmp_path, '[grid]\n"simulation.stop_time" = [10000.0]\n"platoon.k_v" = [0.5, 0.6]\n')
    sweep = subprocess.Popen([str(PLATOON), "sweep", str(path), "--out", str(tmp_path / "out"), "--workers", "2"],
                             cwd=REPO, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    runs: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while True:
            runs = [p for p in _descendants(sweep.pid) if _alive(p)]  # the warm workers and the runs they forked
            # *.part.partial: run_scenario writes aside until it finalizes (docs/trace-format.md)
            if len(runs) >= 2 and len(list((tmp_path / "out" / "traces").glob("*.part*"))) == 2:
                break  # both runs are writing their traces
            assert sweep.poll() is None and time.monotonic() < deadline, "the sweep did not start its two runs"
            time.sleep(POLL)
        sweep.kill()
        sweep.wait()
        deadline = time.monotonic() + 30
        while any(_alive(p) for p in runs) and time.monotonic() < deadline:
            time.sleep(POLL)
        assert not any(_alive(p) for p in runs), "run processes outlived the killed sweep"
    finally:
        if sweep.poll() is None:
            sweep.kill()
        for pid in runs:  # only if the test failed: the orphans it found, by their pid
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_a_run_killed_by_a_signal_is_one_failed_row_and_the_sweep_goes_on(tmp_path: Path, fmu_dir: Path) -> None:
    # as a run that segfaults inside an FMU ends: its process killed by SIGSEGV (sent here, to the run's own pid)
    path = sweep_file(tmp_path, '[grid]\n"simulation.stop_time" = [10000.0, 2.0, 3.0]\n')
    out = tmp_path / "out"
    sweep = subprocess.Popen([str(PLATOON), "sweep", str(path), "--out", str(out), "--workers", "1"],
                             cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (runs := [run for worker in _children(sweep.pid) for run in _children(worker) if _alive(run)]) \
                or not list((out / "traces").glob("*.part*")):  # the run forked by the warm worker, writing
            assert sweep.poll() is None and time.monotonic() < deadline, "the sweep did not start its first run"
            time.sleep(POLL)
        (run,) = runs
        os.kill(run, signal.SIGSEGV)
        _, stderr = sweep.communicate(timeout=240)
    finally:
        if sweep.poll() is None:
            sweep.kill()
            sweep.communicate()
    assert sweep.returncode == 1 and "1 of 3 runs failed" in stderr, stderr
    by_stop = {r["simulation.stop_time"]: r for r in rows(out)}
    assert by_stop["10000.0"]["status"] == "failed" and "killed by SIGSEGV" in by_stop["10000.0"]["error"]
    for stop in ("2.0", "3.0"):  # forked from the same warm worker after the crash
        assert by_stop[stop]["status"] == "completed"
        assert_row_is_its_report(out, by_stop[stop])


# --- random samples ---------------------------------------------------------------------------------

def test_random_samples_are_reproducible_and_more_samples_keep_the_first(tmp_path: Path, fmu_dir: Path) -> None:
    sweep = '[set]\n"simulation.stop_time" = 0.5\n[grid]\n"platoon.law" = ["sine", "regular"]\n[random]\nseed = 7\n'
    ranges = 'ranges = { "platoon.k_v" = [0.3, 1.0], "platoon.count" = [2, 3] }\n'
    path = sweep_file(tmp_path, sweep + "samples = 2\n" + ranges)
    out = tmp_path / "out"
    assert platoon("sweep", path, "--out", out).returncode == 0
    first = rows(out)
    assert [(r["platoon.law"], r["sample"]) for r in first] == [("sine", "0"), ("sine", "1"), ("regular", "0"), ("regular", "1")]
    for row in first:
        assert 0.3 <= float(row["platoon.k_v"]) <= 1.0 and row["platoon.count"] in ("2", "3")
        assert row[f"vehicle{row['platoon.count']}.path_offset"] == row["last.path_offset"]
    samples = {r["sample"]: (r["platoon.k_v"], r["platoon.count"]) for r in first if r["platoon.law"] == "sine"}
    assert samples == {r["sample"]: (r["platoon.k_v"], r["platoon.count"]) for r in first if r["platoon.law"] == "regular"}

    path.write_text(path.read_text().replace("samples = 2", "samples = 3"))
    result = platoon("sweep", path, "--out", out)
    assert result.returncode == 0 and "4 done before, 2 to run" in result.stderr
    assert [r for r in rows(out) if r["sample"] != "2"] == first


# --- Dask -------------------------------------------------------------------------------------------

def test_a_dask_local_cluster_gives_the_rows_of_local_workers(tmp_path: Path, fmu_dir: Path) -> None:
    distributed = pytest.importorskip("distributed")
    path = sweep_file(tmp_path, '[set]\n"simulation.stop_time" = 5.0\n[grid]\n"platoon.law" = ["sine", "regular"]\n'
                                '"platoon.count" = [1, 3]\n"platoon.d_star" = [50.0, 150.0]\n')
    local = platoon("sweep", path, "--out", tmp_path / "local", "--workers", "2")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        remote = platoon("sweep", path, "--out", tmp_path / "dask", "--scheduler", cluster.scheduler_address)
    assert local.returncode == remote.returncode == 1, (local.stderr, remote.stderr)  # d* = 150 m is rejected
    local_rows, dask_rows = rows(tmp_path / "local"), rows(tmp_path / "dask")
    assert [r["status"] for r in dask_rows].count("completed") == 4
    strip = lambda table: [{k: v for k, v in r.items() if k != "wall_time"} for r in table]  # noqa: E731
    assert strip(dask_rows) == strip(local_rows)  # same metric values, to the last digit
    for row in dask_rows:
        if row["status"] == "completed":
            assert float(row["wall_time"]) > 0
            assert_row_is_its_report(tmp_path / "dask", row)  # the trace came back whole from the worker


def test_parquet_holds_the_rows_of_the_csv(tmp_path: Path, fmu_dir: Path) -> None:
    parquet = pytest.importorskip("pyarrow.parquet")
    path = sweep_file(tmp_path, '[set]\n"simulation.stop_time" = 0.5\n[grid]\n"platoon.count" = [1, 2]\n')
    out = tmp_path / "out"
    assert platoon("sweep", path, "--out", out).returncode == 0
    table = parquet.read_table(out / "results.parquet").to_pylist()
    csv_rows = rows(out)
    assert [r["id"] for r in table] == [r["id"] for r in csv_rows]
    assert [r["last.gap"] for r in table] == [float(r["last.gap"]) for r in csv_rows]
    assert table[0]["vehicle2.gap"] is None and math.isfinite(table[1]["vehicle2.gap"])


# --- the map ----------------------------------------------------------------------------------------

def drawn_figure(out: Path, value: str, png: Path, x: str = "d_star/R", y: str = "platoon.count"):
    """The figure ``platoon sweep-plot OUT --value VALUE`` draws, kept open to read what it holds."""
    from orchestrator.sweep import plot

    kept = []
    close = plot.plt.close
    plot.plt.close = kept.append  # draw_map closes its figure after saving it: keep it instead
    try:
        plot.draw_map(out, value, x, y, "platoon.law", png)
    finally:
        plot.plt.close = close
    (figure,) = kept
    return figure


def assert_map_shows(figure, pixels, expected: dict[tuple[str, int, float], float]) -> None:
    """Each cell (law panel, count row, d*/R column) says its run's signed value and is painted the
    colour of its magnitude on the one logarithmic scale of the colour bar, which covers the values:
    in the figure's objects and in ``pixels`` (the PNG the command wrote)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    axes = [axis for axis in figure.axes if axis.get_title().startswith("platoon.law = ")]
    assert [axis.get_title() for axis in axes] == ["platoon.law = regular", "platoon.law = sine"]
    (bar,) = [axis for axis in figure.axes if axis.get_label() == "<colorbar>"]
    assert bar.get_ylabel().endswith(" [m]"), bar.get_ylabel()  # path offsets and gap errors are metres
    figure.canvas.draw()  # the title whole inside the figure: no letter cut at either edge
    title = figure._suptitle.get_window_extent()
    assert title.x0 >= 0 and title.x1 <= figure.bbox.x1 and "[m]" in figure._suptitle.get_text()
    magnitudes = [abs(v) for v in expected.values()]
    norms = {id(axis.get_images()[0].norm) for axis in axes}
    norm = axes[0].get_images()[0].norm
    assert len(norms) == 1 and isinstance(norm, LogNorm), "one logarithmic colour scale for every panel"
    assert norm.vmin == min(magnitudes) and norm.vmax >= max(magnitudes)  # at least a decade wide
    height = pixels.shape[0]
    counts = [int(label.get_text()) for label in axes[0].get_yticklabels()]  # the panels share the y axis
    for axis in axes:
        law = axis.get_title().removeprefix("platoon.law = ")
        ratios = [float(label.get_text()) for label in axis.get_xticklabels()]
        assert counts == [1, 2] and ratios == [0.5, 1.5], (counts, ratios)
        (image,) = axis.get_images()
        shown, cmap = image.get_array(), image.get_cmap()
        texts = {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text() for t in axis.texts}
        for (row, count), (column, ratio) in itertools.product(enumerate(counts), enumerate(ratios)):
            value = expected[(law, count, ratio)]
            assert shown[row, column] == pytest.approx(abs(value), rel=1e-12), (law, count, ratio)
            assert texts[(row, column)] == f"{value:.2g}", (law, count, ratio)
            # a point inside the cell away from its centred text: the cell's colour in the written PNG
            x, y = axis.transData.transform((column - 0.3, row - 0.3))
            colour = pixels[height - 1 - int(round(y)), int(round(x)), :3]
            wanted = cmap(norm(abs(value)))[:3]
            assert colour == pytest.approx(wanted, abs=2 / 255), (law, count, ratio, colour, wanted)
    plt.close(figure)


def test_sweep_plot_draws_the_map_and_names_a_bad_column(tmp_path: Path, fmu_dir: Path) -> None:
    path = sweep_file(tmp_path, '[set]\n"simulation.stop_time" = 2.0\n[grid]\n"platoon.law" = ["regular", "sine"]\n'
                                '"platoon.count" = [1, 2]\n"platoon.d_star" = [25.0, 75.0]\n')
    out = tmp_path / "out"
    assert platoon("sweep", path, "--out", out).returncode == 0
    result = platoon("sweep-plot", out)
    assert result.returncode == 0, result.stderr
    png = out / "map.png"
    assert f"wrote {png}" in result.stdout.replace("\n", "")
    # what each cell must show: the run's signed value, its magnitude as the colour; the path offsets
    # are all positive here, the gap errors of both signs
    radius = 50.0  # path.radius of configs/paper/platoon.toml: the x axis is d*/R
    gap_png = tmp_path / "gap.png"
    assert platoon("sweep-plot", out, "--value", "last.gap_error", "--out", gap_png).returncode == 0
    for column, written in (("last.path_offset", png), ("last.gap_error", gap_png)):
        expected = {(row["platoon.law"], int(row["platoon.count"]), float(row["platoon.d_star"]) / radius):
                    float(row[column]) for row in rows(out)}
        assert len(expected) == 8 and all(math.isfinite(v) and v != 0.0 for v in expected.values())
        figure = drawn_figure(out, column, tmp_path / "again.png")
        assert_map_shows(figure, matplotlib.image.imread(written), expected)
    # a run that left the model (its row's run.left_model) is marked so, its value not drawn
    marked = rows(out)[0]
    record_path = out / "results" / f"{marked['id']}.json"
    record = json.loads(record_path.read_text())
    record["metrics"]["run.left_model"] = "collision (vehicle2) from t = 1 s"
    record_path.write_text(json.dumps(record))
    texts = [t.get_text() for axis in drawn_figure(out, "last.path_offset", tmp_path / "left.png").axes for t in axis.texts]
    assert texts.count("left\nmodel") == 1 and f"{float(marked['last.path_offset']):.2g}" not in texts
    bad = platoon("sweep-plot", out, "--value", "last.colour")
    assert bad.returncode == 2 and "--value last.colour" in error_line(bad)
    ambiguous = platoon("sweep-plot", out, "--panel", "platoon.k_v")  # law and k_v: two runs per cell
    assert ambiguous.returncode == 2 and "several runs fall on" in error_line(ambiguous)


def test_bench_sweep_measures_each_worker_count(tmp_path: Path, fmu_dir: Path) -> None:
    """Functional only: the suite runs real sweeps and reports a speed-up; the numbers are not asserted."""
    from tests.test_bench import written

    result = platoon("bench", "sweep", "--runs", "2", "--stop-time", "1", "--rounds", "1", "--workers", "1,2",
                     "--no-dask", "--out-dir", tmp_path, "-q")
    data = written(result, tmp_path, "sweep")
    assert set(data["medians"]) == {"local-1", "local-2"} and data["speedup"]["local-1"] == 1.0
    assert all(s["wall_time"] > 0 for s in data["samples"]) and len(data["samples"]) == 2
    assert "speed-up vs local-1" in result.stdout


def test_bench_sweep_bookkeeping_measures_each_size_and_the_first_run(tmp_path: Path) -> None:
    """Functional only: each size in its own interpreter through the real runner, the smallest measured
    before and after each larger one; the numbers are not asserted (speed is the benchmark's business)."""
    from tests.test_bench import written

    result = platoon("bench", "sweep-bookkeeping", "--points", "10,30", "--first-run", "1000", "--out-dir", tmp_path, "-q")
    data = written(result, tmp_path, "sweep-bookkeeping")
    assert [r["points"] for r in data["sizes"]] == [10, 30] and [r["points"] for r in data["references"]] == [10, 10]
    assert all(r["per_run"] > 0 and r["cpu_per_run"] > 0 and r["peak_rss_mib"] > 0 for r in data["sizes"])
    assert all(0 < r["runs_peak_rss_mib"] <= r["peak_rss_mib"] for r in data["sizes"])  # the runs', then the end's
    assert data["first_run_points"] == 1000 and data["first_run_after"] > 0
    assert "ratio largest/smallest" in result.stdout and "first run of a 1,000-point sweep" in result.stdout


def test_the_plan_is_streamed_memory_flat_in_the_number_of_points(tmp_path: Path) -> None:
    """A 10^6-point plan hands out its first runs without making the others (the same memory as
    a 10^3-point one), and its points are the ones the whole plan has, in order."""
    import tracemalloc

    from orchestrator.sweep.plan import count, plan, runs
    from orchestrator.sweep.spec import load_sweep

    def spec_of(samples: int):
        return load_sweep(sweep_file(tmp_path, '[grid]\n"platoon.law" = ["regular", "sine"]\n'
                                               f'[random]\nsamples = {samples}\nseed = 4\n'
                                               '[random.ranges]\n"platoon.k_v" = [0.3, 1.0]\n', name=f"s{samples}.toml"))

    peaks = {}
    for samples in (500, 500_000):
        spec = spec_of(samples)
        tracemalloc.start()
        first = list(itertools.islice(runs(spec), 50))
        peaks[samples] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert count(spec) == 2 * samples and [r.values["sample"] for r in first] == list(range(50))
    assert peaks[500_000] < 1.5 * peaks[500], peaks  # a list of 10^6 runs would be ~7 GB
    small = spec_of(3)
    assert [r.values for r in runs(small)] == [r.values for r in plan(small)]
    sine = [r.values["platoon.k_v"] for r in runs(small) if r.values["platoon.law"] == "sine"]
    assert sine == [r.values["platoon.k_v"] for r in runs(small) if r.values["platoon.law"] == "regular"]


def test_a_map_axis_names_its_key_with_the_unit() -> None:
    """sweep-plot's axes and panel titles are config keys: each with its unit, as configs state it."""
    from orchestrator.scenario.config import key_unit
    from orchestrator.sweep.plot import _axis_name

    assert _axis_name("platoon.k_v") == "platoon.k_v [1/s]"
    assert _axis_name("vehicles.3.k_v") == "vehicles.3.k_v [1/s]"
    assert _axis_name("path.center[0]") == "path.center[0] [m]"
    assert _axis_name("platoon.count") == "platoon.count"  # a count has no unit
    assert _axis_name("d_star/R") == "d*/R"  # a ratio neither
    assert key_unit("simulation.step") == "s" and key_unit("platoon.speed") == "m/s" and key_unit("no.such") is None


# --- a sweep that cannot fit on its disk -------------------------------------------------------------------

def test_a_sweep_that_cannot_fit_on_its_disk_is_refused_before_its_first_run(tmp_path: Path, fmu_dir: Path) -> None:
    """On a real 2 MB tmpfs (a private mount namespace), 1000 runs of ~0.2 MB each are refused in
    one line with the estimate and the free space, before any run; --allow-full-disk starts them, and when
    the disk is full the sweep stops with every committed run whole (its result readable, its trace there)."""
    from tests.test_hostile_traces import one_line_error, platoon as platoon_with
    from tests.test_output_rule import on_small_disk

    folder = tmp_path / "disk"
    folder.mkdir()
    prefix = on_small_disk(folder, "2m")
    (folder / "build").symlink_to(REPO / "build", target_is_directory=True)
    sweep = sweep_file(folder, '[set]\n"simulation.stop_time" = 2.0\n[random]\nsamples = 1000\nseed = 3\n'
                               '[random.ranges]\n"platoon.k_v" = [0.4, 1.0]\n')
    refused = platoon_with("sweep", sweep, "--out", "small/out", "--workers", "1", "-q", cwd=folder, prefix=prefix)
    assert refused.returncode == 2, (refused.stdout, refused.stderr)
    line = one_line_error(refused, "small/out", "1,000 runs need about", "MB free", "--allow-full-disk")
    needed = float(line.split("need about ")[1].split(" MB")[0])
    assert 150 < needed < 400, line  # 1000 x (a 201-row trace of 5 components, ~0.2 MB, and a result file)
    assert list((folder / "left").rglob("*")) == []  # nothing ran, and the folder it made is gone again

    allowed = platoon_with("sweep", sweep, "--out", "small/out", "--workers", "1", "-q", "--allow-full-disk",
                           cwd=folder, prefix=prefix, timeout=600)
    assert allowed.returncode == 1, (allowed.stdout, allowed.stderr)
    one_line_error(allowed, "No space left on device")
    left = folder / "left" / "out"
    results = sorted((left / "results").glob("*.json"))
    assert results, allowed.stderr  # some runs fitted
    records = [json.loads(path.read_text()) for path in results]  # every committed run whole: its result reads,
    for record in records:
        if record["status"] == "completed":
            load(left / record["trace"])  # its trace is there and reads
    assert any(record["status"] == "completed" for record in records), records


def _tree(folder: Path) -> list[tuple[str, bool]]:
    """Every path below ``folder`` (folders included), and whether it is a folder."""
    return sorted((str(path.relative_to(folder)), path.is_dir()) for path in folder.rglob("*"))


def test_a_sweep_refused_up_front_leaves_the_disk_as_it_found_it(tmp_path: Path, fmu_dir: Path) -> None:
    """Refused before its first run (here: 10^9 runs need petabytes, more than any disk has), a sweep
    removes the folders and files it made (new/out/results, traces, .lock, results.csv, and new/ itself),
    and nothing it did not make: a folder that was there, even an empty one, and what it holds stay."""
    from tests.test_hostile_traces import one_line_error

    (tmp_path / "build").symlink_to(REPO / "build", target_is_directory=True)
    sweep = sweep_file(tmp_path, '[random]\nsamples = 1000000000\nseed = 1\n[random.ranges]\n"platoon.k_v" = [0.4, 1.0]\n')
    before = _tree(tmp_path)
    refused = platoon("sweep", sweep, "--out", "new/out", "-q", cwd=tmp_path)
    assert refused.returncode == 2, (refused.stdout, refused.stderr)
    one_line_error(refused, "--out new/out", "1,000,000,000 runs need about", "free")
    assert _tree(tmp_path) == before  # no new/, no new/out/, nothing in them

    mine = tmp_path / "mine"
    (mine / "results").mkdir(parents=True)  # empty, but there before: not the sweep's to remove
    (mine / "notes.txt").write_text("mine\n")
    before = _tree(tmp_path)
    refused = platoon("sweep", sweep, "--out", mine, "-q", cwd=tmp_path)
    assert refused.returncode == 2, (refused.stdout, refused.stderr)
    one_line_error(refused, "runs need about")
    assert _tree(tmp_path) == before and (mine / "notes.txt").read_text() == "mine\n"

    bad = sweep_file(tmp_path, '[grid]\n"platoon.no_such_key" = [1, 2]\n', name="bad.toml")  # a bad config: the same
    before = _tree(tmp_path)
    refused = platoon("sweep", bad, "--out", "new/out", "-q", cwd=tmp_path)
    assert refused.returncode == 2, (refused.stdout, refused.stderr)
    one_line_error(refused, "platoon.no_such_key")
    assert _tree(tmp_path) == before


def test_a_sweep_waiting_for_the_folder_of_one_refused_up_front_takes_it_whole(tmp_path: Path) -> None:
    """Two sweeps start on one new folder; the first takes it and is refused up front, removing what it made
    (.lock included) while the second waits for the lock. The second then holds the folder's lock and its
    folders, not a lock on a removed file in a removed folder (it opens .lock again)."""
    import threading

    from orchestrator.sweep.store import OutputFolder

    out = tmp_path / "out"
    first, second = OutputFolder(out), OutputFolder(out)
    first.acquire()
    waiting = threading.Thread(target=second.acquire)
    waiting.start()
    lock = str(out / ".lock")
    deadline = time.monotonic() + 60
    while sum(os.path.realpath(f"/proc/self/fd/{fd}") == lock for fd in os.listdir("/proc/self/fd")) < 2:
        assert time.monotonic() < deadline, "the second sweep never opened the folder's .lock"
        time.sleep(POLL)
    first.undo()
    first.release()
    waiting.join(timeout=60)
    assert not waiting.is_alive()
    held = os.fstat(second._lock.fileno())
    assert (held.st_dev, held.st_ino) == (os.stat(lock).st_dev, os.stat(lock).st_ino)
    assert second.results.is_dir() and second.traces.is_dir()
    second.undo()
    second.release()
    assert not out.exists()


def test_a_placed_trace_is_synced_then_renamed_then_its_folder_synced(tmp_path: Path, monkeypatch) -> None:
    """A committed run's trace survives a power cut: its data is fsynced before the rename, and traces/ is
    fsynced after it (else the result file, the commit, could outlive the rename that put the trace in
    place). Watched on the real files: each fsync's target and what traces/ holds at that moment."""
    from orchestrator.sweep.plan import Run
    from orchestrator.sweep.store import OutputFolder

    folder = OutputFolder(tmp_path / "out")
    folder.acquire()
    run = Run("abc123", {}, [], None, None, "", "hash")
    partial = folder.partial_trace_path(run)
    partial.write_bytes(b"\x89MCAP0\r\n" + b"x" * 100)
    synced: list[tuple[str, list[str]]] = []
    real_fsync = os.fsync

    def watched(fd: int) -> None:
        synced.append((os.path.realpath(f"/proc/self/fd/{fd}"), sorted(p.name for p in folder.traces.iterdir())))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", watched)
    placed = folder.place_trace(run, partial)
    folder.release()
    assert placed == folder.trace_path(run) and placed.read_bytes().endswith(b"x" * 100)
    assert synced == [(str(partial), ["abc123.mcap.part"]), (str(folder.traces), ["abc123.mcap"])], synced


@pytest.mark.parametrize("links", [(), ("--set", "links.delay=0.05")], ids=["no links", "links"])
def test_the_disk_estimate_covers_a_real_trace_with_or_without_links(links: tuple[str, ...], tmp_path: Path,
                                                                     fmu_dir: Path) -> None:
    """The estimate counts every component the wiring makes (a [links] run records two link FMUs per
    vehicle, ~40% more trace here): a real trace is at most the estimate and not far below it."""
    from orchestrator.scenario.config import load_config
    from orchestrator.sweep.space import BLOCK, ROW_BYTES, run_bytes

    sets = ["simulation.stop_time=20", *links[1:]]
    trace = tmp_path / "t.mcap"
    done = platoon("run", PAPER, *(arg for s in sets for arg in ("--set", s)), "-q", "--out", trace)
    assert done.returncode == 0, done.stderr
    config, _ = load_config(PAPER, sets)
    estimate = run_bytes(config) - ROW_BYTES - BLOCK  # the trace's share (a result file of this config: one block)
    assert 0.75 * estimate < trace.stat().st_size <= estimate, (trace.stat().st_size, estimate)
