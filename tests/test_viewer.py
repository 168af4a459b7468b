"""What users look at: the layout fitted to each run (``platoon layout``, the one ``platoon run`` writes
beside its trace) and the paper's figure pair (``platoon figure``), from real runs' traces.

The commands run as a user runs them, in a subprocess, on traces written by ``platoon run``; the
layout is checked against the trace it was made for (every plotted message path names a topic and a
field the trace holds), the figure by reading its artists before saving and the files it writes.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orchestrator.scenario.config import config_from_mapping
from orchestrator.trace import load
from orchestrator.trace.foxglove import SCENE_TOPIC

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper" / "platoon.toml"
M3PI = REPO / "configs" / "paper" / "m3pi.toml"
FRONT_LATERAL = REPO / "configs" / "paper" / "platoon_front_lateral.toml"  # a disturbance: its legend entry is long
SHORT = ("--set", "simulation.stop_time=1.0", "-q")


def platoon(*args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``platoon ARGS`` from this checkout (PYTHONPATH), without a terminal."""
    env = {**os.environ, "COLUMNS": "80", "NO_COLOR": "1", "TERM": "dumb", "PYTHONPATH": str(REPO)}
    env.pop("FORCE_COLOR", None)
    return subprocess.run([sys.executable, "-c", "from orchestrator.cli import main; main()", *map(str, args)],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=180)


def error_line(result: subprocess.CompletedProcess[str]) -> str:
    assert "Traceback" not in result.stderr + result.stdout, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> dict[str, Path]:
    """Short real runs: the paper's 50 m circle (both laws), the m3pi's 1 m circle, a line, 14 vehicles, a
    disturbance (both laws; 1 s, before it strikes: the figure names it all the same)."""
    folder = tmp_path_factory.mktemp("viewer")
    cases = {
        "paper": (PAPER,), "regular": (PAPER, "--set", "platoon.law=regular"), "m3pi": (M3PI,),
        "line": (PAPER, "--set", "path.kind=line"), "many": (PAPER, "--set", "platoon.count=14"),
        "front": (FRONT_LATERAL,), "front-regular": (FRONT_LATERAL, "--set", "platoon.law=regular"),
    }
    traces = {}
    for name, (config, *overrides) in cases.items():
        trace = folder / f"{name}.mcap"
        result = platoon("run", config, *overrides, *SHORT, "--out", trace, cwd=folder)
        assert result.returncode == 0, result.stderr
        traces[name] = trace
    return traces


def split_message_path(path: str) -> tuple[str, list[str]]:
    """A message path's topic and field names, quotes removed (as the viewer parses it)."""
    topic, rest = re.match(r"(/[^.\"]+)(.*)", path).groups()
    fields = [quoted.replace('\\"', '"') if quoted else plain
              for quoted, plain in re.findall(r'\.(?:"((?:[^"\\]|\\.)*)"|([A-Za-z_][A-Za-z0-9_]*))', rest)]
    return topic, fields


def first_message(trace: Path, topic: str) -> dict:
    from mcap.reader import make_reader

    with open(trace, "rb") as stream:
        for _, _, message in make_reader(stream).iter_messages(topics=[topic]):
            return json.loads(message.data)
    raise AssertionError(f"{trace} has no message on {topic}")


def check_layout_against_trace(layout: dict, trace: Path) -> None:
    """Every panel titled, one series per recorded vehicle, every plotted path a topic and field of the trace."""
    loaded = load(trace)
    vehicles = loaded.vehicles()
    panels = layout["configById"]
    for key, panel in panels.items():
        assert panel.get("foxglovePanelTitle"), f"{key} has no title the viewer reads"
    plots = [panel for key, panel in panels.items() if key.startswith("Plot!")]
    assert len(plots) == 3
    for plot in plots:
        assert len(plot["paths"]) == len(vehicles)  # no empty series for vehicles the run lacks
        assert plot["legendDisplay"] in ("left", "top", "none") and not plot["showPlotValuesInLegend"]
        for series in plot["paths"]:
            topic, fields = split_message_path(series["value"])
            assert topic in loaded.topics, series["value"]
            value = first_message(trace, topic)
            for field in fields:
                assert field in value, f"{series['value']}: no field {field!r} in {topic}"
                value = value[field]
            assert isinstance(value, float | int), series["value"]
    three_d = panels["3D!platoon"]
    assert three_d["topics"][SCENE_TOPIC]["visible"] is True
    frames = {"world", "target", *vehicles}
    assert {f"frame:{frame}" for frame in frames} <= {k for k, v in three_d["transforms"].items() if v["visible"] is False}


def test_layout_is_fitted_to_each_run_and_valid_for_its_trace(runs: dict[str, Path], tmp_path: Path) -> None:
    layouts = {}
    for name in ("paper", "m3pi", "line", "many"):
        out = tmp_path / f"{name}.json"
        result = platoon("layout", runs[name], "--out", out, cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        layouts[name] = json.loads(out.read_text())
        check_layout_against_trace(layouts[name], runs[name])
        # platoon run wrote the same layout beside the trace, named after its stem
        assert json.loads(runs[name].with_name(f"{name}.layout.json").read_text()) == layouts[name]
    paper = layouts["paper"]["configById"]["3D!platoon"]["cameraState"]
    m3pi = layouts["m3pi"]["configById"]["3D!platoon"]["cameraState"]
    # an orthographic top view shows about `distance` across: the whole circle and a margin, at either scale
    assert 100.0 < paper["distance"] < 200.0  # R = 50 m
    assert 2.0 < m3pi["distance"] < 4.0  # R = 1 m
    assert paper["distance"] / m3pi["distance"] == pytest.approx(50.0)
    assert not paper["perspective"] and paper["target"][:2] == [0.0, 0.0]
    line = layouts["line"]["configById"]["3D!platoon"]
    assert line["followMode"] == "follow-position" and line["followTf"] == "vehicle2"  # moves with the platoon
    assert line["cameraState"]["distance"] > 5 * 75.0  # target and 4 vehicles, d* = 75 m apart


def test_scene_sizes_follow_the_runs_scale(runs: dict[str, Path]) -> None:
    """A vehicle's box is the same share of the circle on a 50 m and a 1 m circle, so both look alike."""
    from tests.test_traces import _protobuf_messages

    shares = {}
    for name in ("paper", "m3pi"):
        config = config_from_mapping(load(runs[name]).config)
        _, _, scene = next(_protobuf_messages(runs[name], [SCENE_TOPIC]))
        vehicle = next(entity for entity in scene.entities if entity.id == "vehicle1")
        shares[name] = vehicle.cubes[0].size.x / config.path.radius
        path = next(entity for entity in scene.entities if entity.id == "path")
        assert path.lines[0].scale_invariant  # the path's width in screen pixels, at any zoom
        assert any(line.scale_invariant for line in vehicle.lines)  # a mark that never shrinks below pixels
    assert shares["paper"] == pytest.approx(shares["m3pi"])


def test_message_path_quotes_dotted_field_names() -> None:
    from orchestrator.trace.foxglove import message_path

    assert message_path("/platoon/vehicle1", "wheel.right") == '/platoon/vehicle1."wheel.right"'
    assert message_path("/platoon/errors", "vehicle1", "path_error") == "/platoon/errors.vehicle1.path_error"
    assert split_message_path(message_path("/t", 'odd"name', "x")) == ("/t", ['odd"name', "x"])


def test_figure_draws_both_laws_side_by_side(runs: dict[str, Path]) -> None:
    from orchestrator.analysis.figure import draw_pair

    pair = [(load(runs[name]), config_from_mapping(load(runs[name]).config)) for name in ("regular", "paper")]
    figure = draw_pair(pair)
    axes = [a for a in figure.axes if a.get_label() != "<colorbar>"]
    assert len(axes) == 8  # speed, gap, path errors and X-Y, for each law
    titles = " ".join(a.get_title() for a in axes)
    assert "regular law" in titles and "sine law" in titles
    # the titles name what the axes and the files (speed_errors, gap_errors) name
    assert [a.get_title().splitlines()[-1] for a in axes[0:6:2]] == ["Speed errors", "Gap errors", "Path errors"]
    assert axes[2].get_ylabel() == "gap error d - d* [m]"
    assert axes[6].get_xlim() == axes[7].get_xlim() and axes[6].get_ylim() == axes[7].get_ylim()  # same X-Y ranges
    for column, (trace, _) in zip((axes[0::2], axes[1::2]), pair):
        for time_axes in column[:3]:
            assert len(time_axes.get_lines()) == 4  # a line per vehicle
        labels = [text.get_text() for text in column[3].get_legend().get_texts()]
        assert labels == ["vehicle 1", "vehicle 2", "vehicle 3", "vehicle 4", "path", "vehicle at the end",
                          "virtual target at the end"]
    # each column draws its own run: the errors over time and the tracks are that trace's data
    from tests.test_cli import panel_series

    for column, (trace, config) in zip((axes[0::2], axes[1::2]), pair):
        series = panel_series(trace, config)
        for time_axes, stem in zip(column[:3], ("speed_errors", "gap_errors", "path_errors")):
            for line, vehicle in zip(time_axes.get_lines(), trace.vehicles()):
                assert np.array_equal(line.get_ydata(), series[stem](vehicle)), (config.platoon.law, stem, vehicle)
        for k, vehicle in enumerate(trace.vehicles()):  # the path first, then each vehicle's track and its end
            track = column[3].get_lines()[1 + 2 * k]
            assert np.array_equal(track.get_xdata(), trace.component(vehicle)["x"]), (config.platoon.law, vehicle)
            assert np.array_equal(track.get_ydata(), trace.component(vehicle)["y"]), (config.platoon.law, vehicle)


def pair_of(runs: dict[str, Path], *names: str) -> list:
    return [(load(runs[name]), config_from_mapping(load(runs[name]).config)) for name in names]


def test_each_row_of_the_figure_has_one_y_range(runs: dict[str, Path]) -> None:
    """Regular beside sine: the same height is the same error in both columns (the eye compares them),
    and the range holds both columns' data."""
    from orchestrator.analysis.figure import draw_pair

    figure = draw_pair(pair_of(runs, "regular", "paper"))
    axes = [a for a in figure.axes if a.get_label() != "<colorbar>"]
    for row in range(3):
        left, right = axes[2 * row], axes[2 * row + 1]
        assert left.get_ylim() == right.get_ylim(), (row, left.get_ylim(), right.get_ylim())
        low, high = left.get_ylim()
        for panel in (left, right):
            for line in panel.get_lines():
                assert low <= np.min(line.get_ydata()) and np.max(line.get_ydata()) <= high
    spans = [np.ptp(np.concatenate([line.get_ydata() for line in axes[k].get_lines()])) for k in (0, 1)]
    assert spans[0] != spans[1]  # the two columns' own ranges differ: the shared one is not a coincidence


def test_the_column_headers_name_the_traces_when_the_laws_are_the_same(runs: dict[str, Path]) -> None:
    from orchestrator.analysis.figure import draw_pair

    def headers(*names: str) -> list[str]:
        figure = draw_pair(pair_of(runs, *names))
        return [a.get_title() for a in figure.axes[:2]]

    same = headers("paper", "front")  # both sine law, 4 vehicles, R = 50 m: the laws alone read alike
    assert same[0] != same[1] and "paper.mcap" in same[0] and "front.mcap" in same[1], same
    differ = headers("regular", "paper")
    assert "regular law" in differ[0] and "sine law" in differ[1] and ".mcap" not in " ".join(differ), differ


def test_the_figures_legends_stay_inside_it_at_a_low_dpi(runs: dict[str, Path], tmp_path: Path) -> None:
    """A disturbance's long legend entry in both columns, at --dpi 80: each legend is whole inside the
    figure and beside, not over, the other; the PNG has a background margin on every side."""
    import matplotlib.image as image

    from orchestrator.analysis.figure import draw_pair

    figure = draw_pair(pair_of(runs, "front-regular", "front"))
    figure.set_dpi(80)
    figure.canvas.draw()  # the constrained layout is made at drawing
    renderer = figure.canvas.get_renderer()
    page = figure.bbox
    boxes = [a.get_legend().get_window_extent(renderer) for a in figure.axes[-2:]]
    for box in boxes:
        assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1, (box, page)
    assert boxes[0].x1 < boxes[1].x0, boxes
    out = tmp_path / "pair.png"
    result = platoon("figure", runs["front-regular"], runs["front"], "--out", out, "--dpi", 80, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    ink = (image.imread(out)[..., :3] < 0.95).any(axis=2)
    for edge in (ink[:2], ink[-2:], ink[:, :2], ink[:, -2:]):  # two pixels of white on each side
        assert not edge.any()


def test_a_figure_of_several_orbits_draws_the_last_one_over_faded_tracks(tmp_path: Path, fmu_dir: Path) -> None:
    """The regular law's X-Y panel after several orbits: the steady rings readable, not a tangle."""
    from orchestrator.analysis.figure import draw_pair

    trace_path = tmp_path / "regular.mcap"
    result = platoon("run", PAPER, "--set", "platoon.law=regular", "--set", "simulation.stop_time=30", "-q",
                     "--out", trace_path, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    trace = load(trace_path)
    config = config_from_mapping(trace.config)
    figure = draw_pair([(trace, config)])
    xy = [a for a in figure.axes if a.get_title().startswith("X-Y")][0]
    orbit = 2 * np.pi * config.path.radius / config.platoon.speed  # 12.6 s at 25 m/s on 50 m
    assert f"from {30 - orbit:.0f} s" in xy.get_title()
    lines = xy.get_lines()
    for k, vehicle in enumerate(trace.vehicles()):
        channel = trace.component(vehicle)
        whole, last = lines[1 + 2 * k], lines[1 + 2 * len(trace.vehicles()) + k]  # after every (track, end dot)
        assert whole.get_alpha() == 0.25 and np.array_equal(whole.get_xdata(), channel["x"])
        t = channel["t"]
        assert np.array_equal(last.get_xdata(), channel["x"][t >= t[-1] - orbit]) and last.get_alpha() is None
    labels = [text.get_text() for text in xy.get_legend().get_texts()]
    assert labels[:4] == ["vehicle 1", "vehicle 2", "vehicle 3", "vehicle 4"]


def test_the_disturbance_band_says_what_struck_with_its_unit() -> None:
    """A pulse's value means m/s² or m/s by its kind: the legend of the grey band says which."""
    from matplotlib.figure import Figure

    from orchestrator.analysis.plots import time_legend_handles

    pulse = {"start": 30.0, "duration": 1.0}
    one = config_from_mapping({"disturbance": [{"vehicle": 1, "kind": "lateral_acceleration", "value": 35.0, **pulse}]})
    two = config_from_mapping({"disturbance": [{"vehicle": 1, "kind": "lateral_acceleration", "value": 35.0, **pulse},
                                               {"vehicle": 2, "kind": "speed", "value": -5.0, **pulse}]})
    axes = Figure().subplots()
    assert time_legend_handles(axes, one, [])[-1].get_label() == "disturbance: +35 m/s² lateral acceleration on vehicle 1"
    assert time_legend_handles(axes, two, [])[-1].get_label() == (
        "disturbances: +35 m/s² lateral acceleration on vehicle 1; -5 m/s speed on vehicle 2")


def test_figure_of_a_large_platoon_has_a_colour_bar_and_a_line_shows_deviations(runs: dict[str, Path]) -> None:
    from orchestrator.analysis.figure import draw_pair

    pair = [(load(runs[name]), config_from_mapping(load(runs[name]).config)) for name in ("many", "line")]
    figure = draw_pair(pair)
    assert any(a.get_label() == "<colorbar>" for a in figure.axes)  # 14 vehicles: a scale, not 14 entries
    axes = [a for a in figure.axes if a.get_label() != "<colorbar>"]
    many_labels = [text.get_text() for text in axes[6].get_legend().get_texts()]
    assert many_labels and not any(re.fullmatch(r"vehicle \d+", label) for label in many_labels)
    line_xy = axes[7]
    assert "along the line" in line_xy.get_xlabel()
    # vehicle 1 starts 5 m off the line: in path coordinates its first y is that offset, not its raw y
    assert line_xy.get_lines()[1].get_ydata()[0] == pytest.approx(5.0, abs=1e-6)


@pytest.mark.parametrize("suffix, magic", [(".pdf", b"%PDF"), (".png", b"\x89PNG"), (".svg", b"<?xml")])
def test_figure_command_writes_each_format(runs: dict[str, Path], tmp_path: Path, suffix: str, magic: bytes) -> None:
    out = tmp_path / f"fig{suffix}"
    result = platoon("figure", runs["regular"], runs["paper"], "--out", out, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    # said before it reads (tens of seconds on a loaded machine), the only line on stderr
    assert result.stderr.splitlines() == [f"figure: drawing {out} from {runs['regular']} and {runs['paper']} ..."]
    data = out.read_bytes()
    assert data.startswith(magic) and len(data) > 20_000


def test_bad_inputs_exit_2_with_one_line(runs: dict[str, Path], tmp_path: Path) -> None:
    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_text("hello\n")
    cases = [
        (("layout", tmp_path / "missing.mcap"), "no such file"),
        (("layout", not_mcap), "not an MCAP file"),
        (("figure", runs["paper"], runs["regular"], "--out", tmp_path / "fig.jpg"), "expected a file ending in"),
        (("figure", runs["paper"], tmp_path / "missing.mcap", "--out", tmp_path / "fig.pdf"), "no such file"),
        (("figure", runs["paper"], not_mcap, "--out", tmp_path / "fig.pdf"), "not a readable MCAP trace"),
    ]
    for args, reason in cases:
        result = platoon(*args, cwd=tmp_path)
        assert result.returncode == 2, (args, result.stderr)
        assert reason in error_line(result), result.stderr
    assert not (tmp_path / "fig.jpg").exists() and not (tmp_path / "fig.pdf").exists()


def test_run_whose_layout_cannot_be_written_keeps_its_trace(tmp_path: Path) -> None:
    (tmp_path / "x.layout.json").mkdir()  # a folder where the layout goes
    result = platoon("run", PAPER, *SHORT, "--out", tmp_path / "x.mcap", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stderr.strip().startswith("warning: layout") and len(result.stderr.strip().splitlines()) == 1
    assert load(tmp_path / "x.mcap").run["status"] == "completed"


# --- in the real viewer (Lichtblick in headless Chromium, the project's viewer tools; ~25 s) -----------

RENDER = Path(os.environ.get("PLATOON_VIEWER_RENDER", REPO.parent / "shared" / "viewer" / "render.mjs"))


def _viewer_missing() -> str | None:
    import shutil

    if shutil.which("node") is None:
        return "node is not installed"
    if not RENDER.is_file():
        return f"no viewer at {RENDER} (set PLATOON_VIEWER_RENDER to render.mjs)"
    if not Path("/usr/bin/chromium").is_file() and shutil.which("chromium") is None:
        return "chromium is not installed"
    return None


def test_the_viewer_shows_every_m3pi_robot_and_titled_plots(tmp_path: Path) -> None:
    """The m3pi's 1 m circle, opened with the layout `platoon run` wrote: each robot's colour shows in the
    3D panel's screenshot (the paper-sized static layout shows an empty panel there) and each plot has
    its title."""
    missing = _viewer_missing()
    if missing:
        pytest.skip(missing)
    import matplotlib.image
    import numpy as np

    from orchestrator.trace.foxglove import vehicle_colors

    trace = tmp_path / "m3pi.mcap"
    result = platoon("run", M3PI, "--set", "simulation.stop_time=2.0", "-q", "--out", trace, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "m3pi.layout.json").is_file()  # written by platoon run, beside the trace
    shots = tmp_path / "shots"
    rendered = subprocess.run(["node", str(RENDER), "--settle", "2", str(trace), str(tmp_path / "m3pi.layout.json"),
                               str(shots)], capture_output=True, text=True, timeout=170)
    if rendered.returncode == 2:
        pytest.skip(f"viewer not set up: {rendered.stderr.strip()[-200:]}")
    assert rendered.returncode == 0, rendered.stdout[-2000:] + rendered.stderr[-2000:]
    report = json.loads((shots / "report.json").read_text())
    titles = {panel["id"]: panel["title"] for panel in report["panels"]}
    assert titles["Plot!path"] == "path error [m]" and titles["Plot!gap"] == "gap error d - d* [m]"
    assert titles["Plot!speed"] == "speed error V - V_c [m/s]"
    three_d = next(panel for panel in report["panels"] if panel["id"] == "3D!platoon")
    image = matplotlib.image.imread(shots / three_d["file"])[..., :3]
    for number, color in enumerate(vehicle_colors(6), start=1):
        # within 0.1 of the vehicle's colour on every channel (its flat screen-size dash, lit box faces)
        pixels = int((np.abs(image - np.array(color)).max(axis=2) < 0.1).sum())
        assert pixels >= 100, f"vehicle{number}: {pixels} pixels of its colour in the 3D panel"
