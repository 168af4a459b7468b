"""Links in the wiring (docs/links.md): the [links] config, the Link FMU and its C twin, placed by the
scenario between components and stepped by every engine like any FMU, refused by the monolithic
reference, exported to SSP and run by libcosim to our numbers."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fmus.model.link import CAPACITY
from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import ConfigError, config_from_mapping, parse_config
from orchestrator.scenario.scenario import build_scenario
from orchestrator.trace import load
from orchestrator.scenario.config_text import links_text

REPO = Path(__file__).resolve().parents[1]
PLATOON = [sys.executable, "-c", "import sys; sys.argv[0] = 'platoon'; from orchestrator.cli import main; main()"]

# A platoon of three, vehicle 1 2 m off the path, every link delayed, jittered and bursty-lossy, the
# forward links at 10 beacons a second.
LOSSY = {"name": "lossy", "simulation": {"stop_time": 10.0, "step": 0.01}, "platoon": {"count": 3},
         "initial": {"radial_offset": 2.0, "heading_error": 0.1},
         "links": {"delay": 0.1, "jitter": 0.05, "loss": 0.2, "burst": 3.0, "seed": 7, "forward": {"period": 0.1}}}


def lossy(**simulation) -> dict:
    return {**LOSSY, "simulation": {**LOSSY["simulation"], **simulation}}


def platoon(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([*PLATOON, *arguments], cwd=REPO, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def link_fmus(fmu_dir, native_fmu_dir):
    """The pythonfmu and native Link FMUs (tests/conftest.py builds them beside the others)."""
    return fmu_dir, native_fmu_dir


def test_fmpy_validates_the_pythonfmu_link(link_fmus):
    from fmpy.validation import validate_fmu

    assert validate_fmu(str(link_fmus[0] / "Link.fmu")) == []


# --- the config ------------------------------------------------------------------------------------


def test_the_narrowest_table_sets_each_key_and_set_overrides_work():
    text = "[links]\ndelay = 0.1\n[links.forward]\nloss = 0.2\n[links.vehicles.2.backward]\nloss = 0.5\n"
    config, _ = parse_config(text, "x", ["links.jitter=0.02", "links.vehicles.2.backward.seed=9"])
    backward2, forward2, backward1 = (config.resolve_link("backward", 2), config.resolve_link("forward", 2),
                                      config.resolve_link("backward", 1))
    assert (backward2.delay, backward2.jitter, backward2.loss, backward2.seed) == (0.1, 0.02, 0.5, 9)
    assert (forward2.loss, forward2.seed, backward1.loss) == (0.2, 0, 0.0)
    assert len({link.stream for link in (backward2, forward2, backward1)}) == 3  # each its own stream


@pytest.mark.parametrize("overrides, message", [
    (["links.vehicles.5.backward.loss=0.1"], "links.vehicles.5 = '5': expected a vehicle number from 1 to platoon.count = 4"),
    (["links.delay=-0.1"], "links.delay = -0.1: must be a finite number >= 0 s and <= 3600 s"),
    (["links.loss=1.5"], "links.loss = 1.5: must be a finite number >= 0 and <= 1"),
    (["links.forward.burst=0.5"], "links.forward.burst = 0.5: must be a finite number >= 1 and <= 1e+06"),
    (["links.delya=0.1"], "links.delya: unknown key (did you mean links.delay?)"),
    (["links.loss=0.8", "links.burst=2"], "links (vehicle 1's backward link): loss = 0.8: with burst = 2.0 at most "
                                          "burst / (burst + 1) = 0.666667"),
    (["links.delay=5"], f"a link holds at most {CAPACITY}"),
])
def test_bad_links_are_refused_in_one_line_naming_the_key(overrides, message):
    with pytest.raises(ConfigError) as error:
        parse_config("", "x", overrides)
    assert message in str(error.value) and "\n" not in str(error.value)


def test_a_delay_that_needs_too_many_messages_is_fine_at_a_lower_beacon_rate():
    parse_config("", "x", ["links.delay=5", "links.period=0.1"])


# --- the wiring --------------------------------------------------------------------------------------


def test_perfect_links_leave_the_wiring_exactly_as_without_links():
    plain = build_scenario(config_from_mapping({"name": "x"}))
    perfect = build_scenario(config_from_mapping({"name": "x", "links": {"delay": 0.0, "loss": 0.0, "seed": 5,
                                                                         "burst": 4.0, "backward": {"jitter": 0.0}}}))
    assert perfect.components == plain.components and perfect.connections == plain.connections


def test_each_link_sits_between_its_two_components_and_steps_after_its_sender():
    scenario = build_scenario(config_from_mapping({"name": "x", "platoon": {"count": 2},
                                                   "links": {"vehicles": {"2": {"backward": {"delay": 0.1}}},
                                                             "forward": {"loss": 0.1}}}))
    assert [c.name for c in scenario.components] == ["target", "vehicle1", "link_forward1", "link_backward2",
                                                     "vehicle2", "link_forward2"]
    into = {(c.destination, c.input): (c.source, c.output) for c in scenario.connections}
    assert into[("vehicle2", "target.x")] == ("link_backward2", "x")
    assert into[("link_backward2", "in.x")] == ("vehicle1", "x")
    assert into[("vehicle2", "target.time")] == ("link_backward2", "output_time")
    assert into[("link_backward2", "in.time")] == ("vehicle1", "output_time")
    assert into[("target", "lead.gap")] == ("link_forward1", "gap")
    assert into[("link_forward1", "in.gap")] == ("vehicle1", "gap")
    assert into[("vehicle1", "target.x")] == ("target", "x")  # vehicle 1's backward link is perfect: no Link
    assert into[("vehicle1", "follower.speed")] == ("link_forward2", "speed")


def test_the_monolithic_reference_refuses_links(tmp_path):
    config = tmp_path / "lossy.toml"
    config.write_text("[links]\ndelay = 0.1\n")
    for option in ("--monolithic", "--compare-monolithic"):
        refused = platoon("run", str(config), option, "--out", str(tmp_path / "x.mcap"))
        assert refused.returncode == 2
        assert f"{option}: the monolithic reference has no messages, so it cannot run links (8 in this config" in refused.stderr
        assert "or without the [links] table" in refused.stderr
    plain = tmp_path / "plain.toml"  # the links made by --set: the remedy names the option, not a table it lacks
    plain.write_text('name = "plain"\n')
    refused = platoon("run", str(plain), "--monolithic", "--set", "links.delay=0.1", "--out", str(tmp_path / "x.mcap"))
    assert refused.returncode == 2 and "or without --set links.delay" in refused.stderr, refused.stderr
    assert "[links] table" not in refused.stderr
    assert not (tmp_path / "x.mcap").exists()
    result = run_scenario(config_from_mapping({"name": "x", "links": {"loss": 0.1}}), "", None, engine="monolithic")
    assert result.status == "failed" and "cannot run links" in result.error


# --- the Link FMU, its twin, the engines ------------------------------------------------------------------


def _columns(trace) -> dict[str, dict[str, np.ndarray]]:
    return {name: channel for name, channel in trace.channels.items()}


@pytest.mark.parametrize("master", ["jacobi", "gauss-seidel"])
def test_python_and_native_twins_and_engines_run_the_same_lossy_platoon_to_the_last_bit(link_fmus, tmp_path, master):
    fmu_dir, _ = link_fmus
    config = config_from_mapping(lossy(master=master, fmus="python"))
    runs = {}
    for engine in ("python", "native"):
        for kind in ("python", "native"):
            out = tmp_path / f"{engine}-{kind}.mcap"
            chosen = config.model_copy(update={"simulation": config.simulation.model_copy(update={"fmus": kind})})
            result = run_scenario(chosen, "", out, engine=engine, fmu_dir=fmu_dir)
            assert result.status == "completed", result.error
            runs[(engine, kind)] = _columns(load(out))
    reference = runs[("python", "python")]
    assert "link_backward2" in reference and "link_forward3" in reference
    for key, channels in runs.items():
        assert list(channels) == list(reference)
        for name, channel in channels.items():
            for output, values in channel.items():
                assert np.array_equal(values, reference[name][output]), (key, name, output)


def test_what_a_receiver_gets_is_the_newest_message_delivered_and_the_counters_add_up(link_fmus, run):
    trace = run(config_from_mapping(lossy(stop_time=20.0)))
    t = trace.channels["vehicle2"]["t"]
    link = trace.channels["link_backward2"]
    sender = trace.channels["vehicle1"]
    # every message in use is one the sender sent: its values at its output_time
    index = np.searchsorted(sender["t"], link["output_time"] - 1e-9)
    assert np.array_equal(sender["x"][index], link["x"]) and np.array_equal(sender["speed"][index], link["speed"])
    # a delivered message (not the initial one) is never used before its delay has passed
    delivered = link["output_time"] > 0.0
    assert np.all(t[delivered] - link["output_time"][delivered] >= 0.1 - 1e-9)
    assert np.array_equal(link["age"], t - link["output_time"])
    in_flight = link["sent"] - link["delivered"] - link["lost"]
    assert np.all(in_flight >= 0) and np.all(in_flight <= (0.1 + 0.05) / 0.01 + 2)
    # 1999 messages (one per step after the initial one), a fifth lost on average: with bursts of mean 3
    # the count's standard deviation is about sqrt(n p (1 - p) (1 + lam) / (1 - lam)) = 35 (tests/test_link_model.py)
    assert link["sent"][-1] == 1999 and abs(link["lost"][-1] - 0.2 * 1999) < 5 * 35
    # the forward links send 10 beacons a second: the target's lead values are held between them
    forward = trace.channels["link_forward1"]
    assert forward["sent"][-1] == 199 and len(np.unique(forward["output_time"])) <= 200


# --- SSP and libcosim ----------------------------------------------------------------------------------


def test_libcosim_runs_the_exported_lossy_platoon_to_our_numbers(link_fmus, tmp_path):
    """The lossy, delayed platoon exported with its Link FMUs and run by libcosim from the package
    matches `platoon run` (Jacobi, as libcosim's fixed-step algorithm) to 1e-9 m at the end, every
    component. Not bit for bit: libcosim's integer-nanosecond time grid moves the FMUs' times by an
    ulp (tests/test_ssp.py); the link's 1e-9 s time tolerance keeps every delivery on the same step.
    Measured: 6.2e-13 m after 20 s."""
    pytest.importorskip("libcosimpy")
    config = tmp_path / "lossy.toml"
    config.write_text((REPO / "configs" / "paper" / "platoon_lossy.toml").read_text())
    package, trace = tmp_path / "lossy.ssp", tmp_path / "ours.mcap"
    exported = platoon("export-ssp", str(config), "--set", "simulation.stop_time=20", "--out", str(package))
    assert exported.returncode == 0, exported.stderr
    assert "13 components" in exported.stdout  # the target, 4 vehicles and their 8 links
    ours = platoon("run", str(config), "--set", "simulation.stop_time=20", "--out", str(trace), "-q")
    assert ours.returncode == 0, ours.stderr
    theirs = subprocess.run([sys.executable, str(REPO / "tests" / "ssp_libcosim.py"), str(package)],
                            cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert theirs.returncode == 0, theirs.stdout + theirs.stderr
    final = {line.split()[0]: (float(line.split()[1]), float(line.split()[2]))
             for line in theirs.stdout.splitlines() if line.startswith(("target", "vehicle", "link_"))}
    loaded = load(trace)
    assert set(final) == set(loaded.channels) and "end 20.0" in theirs.stdout
    worst = max(float(np.hypot(x - loaded.component(name)["x"][-1], y - loaded.component(name)["y"][-1]))
                for name, (x, y) in final.items())
    print(f"\n[libcosim from SSP vs platoon run, lossy links] largest final position difference {worst:.3e} m")
    assert worst <= 1e-9
    assert loaded.component("link_backward2")["lost"][-1] > 0  # the links really lost messages


@pytest.mark.parametrize("engine", ["python", "native"])
def test_the_scene_draws_the_target_and_the_vehicles_never_a_link(link_fmus, run, engine):
    """A Link repeats its sender's stale pose (or, forward, none at all): the 3D scene and its frames
    hold the target and the vehicles only, from either engine's trace encoder; the links' counters
    and ages are in the trace as their components' channels."""
    from tests.test_traces import _protobuf_messages

    trace = run(config_from_mapping(lossy(stop_time=1.0)), engine)
    scenes = 0
    for topic, _, message in _protobuf_messages(trace.path, ["/platoon/scene", "/platoon/tf"]):
        names = ([f.child_frame_id for f in message.transforms] if topic == "/platoon/tf"
                 else [e.id for e in message.entities if e.id != "path"])
        assert names == ["target", "vehicle1", "vehicle2", "vehicle3"]
        scenes += 1
    assert scenes > 0
    assert {"sent", "delivered", "lost", "age"} <= set(trace.channels["link_forward2"])


def test_the_layout_of_a_run_with_links_plots_each_links_age(link_fmus, run, tmp_path):
    """`platoon run` writes a layout whose extra panel plots every link's age of information, each
    series a column of the trace; a run without links keeps the layout it had."""
    import json

    from orchestrator.trace.layout import layout_path, run_layout, write_run_layout

    config = config_from_mapping(lossy(stop_time=0.5))
    trace = run(config)
    written = write_run_layout(trace.path, config)
    assert written.path == layout_path(trace.path)
    panels = json.loads(written.path.read_text())["configById"]
    series = [path["value"] for path in panels["Plot!links"]["paths"]]
    assert series == [f"/platoon/{name}.age" for name in trace.channels if name.startswith("link_")]
    assert all("age" in trace.channels[value.split("/")[2].split(".")[0]] for value in series)
    plain = config_from_mapping({**lossy(stop_time=0.5), "links": {}})
    assert "Plot!links" not in run_layout(plain, 3)["configById"]

    def heights(node, share: float = 100.0) -> dict[str, float]:  # % of the column each plot gets
        if isinstance(node, str):
            return {node: share}
        first = share * node.get("splitPercentage", 50.0) / 100.0
        return {**heights(node["first"], first), **heights(node["second"], share - first)}

    # four plots stacked: each a quarter of the column, so the links' legend (8 lines) is not cut to 3
    column = heights(json.loads(written.path.read_text())["layout"]["second"])
    assert list(column) == ["Plot!path", "Plot!gap", "Plot!speed", "Plot!links"]
    assert all(abs(share - 25.0) < 1e-9 for share in column.values()), column


def link_table_rows(stdout: str) -> dict[str, list[str]]:
    """The links table `platoon run` / `platoon report` print: cells by link."""
    return {cells[0]: cells[1:] for line in stdout.splitlines() if line.startswith("│ link_")
            for cells in [[cell.strip() for cell in line.strip("│").split("│")]]}


def test_a_lossy_runs_summary_says_what_its_links_did(link_fmus, tmp_path):
    """The header names the imperfect links (not a perfect-link run's header), and a table gives each link's
    sent, delivered and lost messages and its mean age of information: what the trace's link channels hold
    (the counters at the end, the mean of the recorded ages), and what `report --json` gives."""
    config = REPO / "configs" / "paper" / "platoon_lossy.toml"
    trace = tmp_path / "lossy.mcap"
    run = platoon("run", str(config), "--set", "simulation.stop_time=5", "--out", str(trace))
    assert run.returncode == 0, run.stderr
    header = "platoon_lossy: sine law, 8 imperfect links (delay 0.1-0.12 s, 10% lost, beacons every 0.1 s on 4)"
    assert " ".join(run.stdout.split()).startswith(header), run.stdout  # the title may wrap at 80 columns
    rows = link_table_rows(run.stdout)
    loaded = load(trace)
    links = [name for name in loaded.channels if name.startswith("link_")]
    assert sorted(rows) == sorted(links) and len(links) == 8
    as_json = {link["name"]: link for link in json.loads(platoon("report", str(trace), "--json").stdout)["links"]}
    for name in links:
        channel = loaded.component(name)
        sent, delivered, lost = (int(channel[key][-1]) for key in ("sent", "delivered", "lost"))
        mean_age = float(np.mean(channel["age"]))
        assert sent > 0 and lost > 0 and mean_age > 0.1  # a 0.1 s delay at least, some losses in 500 steps
        assert rows[name] == [str(sent), str(delivered), str(lost), f"{100 * lost / sent:.1f}", f"{mean_age:.4f}"]
        assert (as_json[name]["sent"], as_json[name]["lost"]) == (sent, lost)
        assert as_json[name]["mean_age"] == pytest.approx(mean_age, rel=1e-12)  # summed in another order
    assert link_table_rows(platoon("report", str(trace)).stdout) == rows
    assert "imperfect links" in loaded.log[0].message  # the trace's first log line says it too


def test_a_perfect_link_run_has_no_links_table(tmp_path):
    run = platoon("run", str(REPO / "configs" / "paper" / "platoon.toml"), "--set", "simulation.stop_time=1",
                  "--out", str(tmp_path / "perfect.mcap"))
    assert run.returncode == 0, run.stderr
    assert "imperfect" not in run.stdout and not link_table_rows(run.stdout) and "links (" not in run.stdout


@pytest.mark.parametrize("stop, lines", [
    (40.0, ["disturbance starts: +35 m/s² lateral acceleration on vehicle 1 at 35 s for 1 s",
            "disturbance ends: +35 m/s² lateral acceleration on vehicle 1"]),
    (35.5, ["disturbance starts: +35 m/s² lateral acceleration on vehicle 1 at 35 s for 1 s"]),  # stopped inside it
    (30.0, []),
])
@pytest.mark.parametrize("engine", ["native", "python"])
def test_the_run_log_says_when_a_disturbance_starts_and_ends(tmp_path, engine, stop, lines):
    trace = tmp_path / "front.mcap"
    run = platoon("run", str(REPO / "configs" / "paper" / "platoon_front_lateral.toml"), "-q", "--engine", engine,
                  "--set", f"simulation.stop_time={stop}", "--out", str(trace))
    assert run.returncode == 0, run.stderr
    log = load(trace).log
    logged = [(line.t, line.message) for line in log if line.message.startswith("disturbance")]
    assert logged == list(zip([35.0, 36.0][:len(lines)], lines))
    assert [line.t for line in log] == sorted(line.t for line in log)  # in time order, between start and end


def test_a_link_that_sent_nothing_reports_null_not_nan():
    """`report --json` stays valid JSON (no NaN) for a link with nothing sent or recorded."""
    from orchestrator.analysis.link_stats import LinkStats, link_rows

    rows = link_rows([LinkStats("link_forward1", 0, 0, 0, float("nan")), LinkStats("link_backward1", 4, 3, 1, 0.25)])
    assert json.loads(json.dumps(rows, allow_nan=False)) == [
        {"name": "link_forward1", "sent": 0, "delivered": 0, "lost": 0, "lost_share": None, "mean_age": None},
        {"name": "link_backward1", "sent": 4, "delivered": 3, "lost": 1, "lost_share": 0.25, "mean_age": 0.25}]


def test_report_plots_of_a_lossy_run_say_lossy_and_draw_each_links_age(link_fmus, run, tmp_path, monkeypatch):
    """`platoon report --plots` of a run with imperfect links: every panel's title names them (the header's
    words), and links.png draws each link's age of information from the trace, one line per link; a run
    whose links are perfect gets no links.png."""
    from orchestrator.analysis import plots as plots_module

    config = config_from_mapping(lossy(stop_time=2.0))
    trace = run(config)
    kept: list = []
    monkeypatch.setattr(plots_module.plt, "close", kept.append)  # each figure kept once saved, to read back
    written = plots_module.write_plots(trace, config, tmp_path / "plots")
    assert [path.name for path in written][-1] == "links.png" and written[-1].read_bytes()[:4] == b"\x89PNG"
    assert all(links_text(config) in figure.axes[0].get_title() for figure in kept), links_text(config)
    lines = kept[-1].axes[0].get_lines()
    names = [name for name in trace.channels if name.startswith("link_")]
    assert [line.get_label() for line in lines] == [name.removeprefix("link_") for name in names]
    for line, name in zip(lines, names):
        assert np.array_equal(line.get_ydata(), trace.component(name)["age"])
    plain = config_from_mapping({**lossy(stop_time=0.5), "links": {}})
    assert [path.name for path in plots_module.write_plots(run(plain), plain, tmp_path / "plain")][-1] == "xy.png"
