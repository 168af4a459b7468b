"""The cache of validated configs (orchestrator/scenario/config_records.py): a config read back from it answers
as the pydantic models do, an entry of older code is not used, and runs and reports from it write and print
the same bytes as without it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from orchestrator.scenario import config_records
from orchestrator.scenario.config import Config, Links, NO_LINKS, parse_config
from orchestrator.scenario.config_logic import LINK_KEYS
from orchestrator.scenario.link_config import LinkKeys
from orchestrator.scenario.raw_config import read_config_text

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper" / "platoon.toml"
# every shipped config that validates on its own (a sweep's file is not a config); live, remote and ROS 2 ones
# are never stored
CONFIGS = sorted(path for path in (REPO / "configs").rglob("*.toml") if path.parent.name not in ("sweeps", "robots"))
NOT_STORED = {"calibrate.toml", "m3pi_live3.toml", "predict3.toml", "ros2_live3.toml"}  # live robots
NOT_STORED_REMOTE = {REPO / "configs" / "remote" / "platoon.toml"}
MORE = [  # the parts no shipped config sets: every table, per-vehicle robots, links per vehicle
    ["vehicles.2.m3pi.track=0.09", "vehicles.2.dynamics=\"m3pi\"", "vehicles.3.k_v=0.7", "vehicles.3.law=\"regular\"",
     "links.delay=0.02", "links.vehicles.2.forward.loss=0.1", "links.vehicles.2.forward.seed=3", "validity.min_gap=1.5",
     "platoon.speed_max=40.0", "hil.prefix=\"lab\"", "remote.step_timeout=3.0"],
    ["platoon.speed_law=\"acc\"", "platoon.standstill_gap=10.0", "vehicles.4.initial={x=1.0, y=2.0, heading=0.5, speed=3.0}",
     "disturbance=[{vehicle=0, kind=\"speed\", start=1.0, duration=2.0, value=0.5, frequency=0.3}]"],
]


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    return tmp_path / "cache" / "platoon-cosim" / "configs"


def _through_cache(path: Path, overrides: list[str] = ()) -> tuple[Config, object, dict]:
    config, raw = parse_config(read_config_text(path), path.stem, overrides, path.parent)
    config_records.store_config(raw, config)
    return config, config_records.cached_config(raw), raw


def _answers(config) -> dict:
    """Everything the run and the report ask a config, vehicle by vehicle."""
    vehicles = range(1, config.platoon.count + 1)
    return {
        "dump": config.model_dump(), "dump without none": config.model_dump(exclude_none=True),
        "json": config.model_dump_json(), "json without none": config.model_dump_json(exclude_none=True),
        "steps": config.steps, "linked": config.linked(), "sensing": config.sensing_vehicles(),
        "links": [config.resolve_link(direction, vehicle) for direction in ("backward", "forward") for vehicle in vehicles],
        "m3pi": [config.m3pi_of(vehicle).model_dump() for vehicle in vehicles],
        "m3pi parameters": [config.m3pi_of(vehicle).parameters() for vehicle in vehicles],
        "m3pi samples": [config.m3pi_of(vehicle).samples for vehicle in vehicles],
        "m3pi keys": [config.m3pi_key(vehicle, "track") for vehicle in vehicles],
        "per vehicle": [(config.speed_law_of(v), config.dynamics_of(v), config.robot_id(v), config.override(v).model_dump())
                        for v in vehicles],
        "m3pi vehicles": config.m3pi_vehicles(), "live": config.live_vehicles(), "remote": config.remote_vehicles(),
        "files": config.named_files(), "standstill gap": config.platoon.resolved_standstill_gap,
        "disturbances": [(d.text(), d.what(), d.unit, d.on_target) for d in config.disturbance],
        "tables": [repr(getattr(config, name)) for name in type(config).model_fields],
    }


@pytest.mark.parametrize("path", CONFIGS, ids=lambda path: str(path.relative_to(REPO / "configs")))
def test_a_cached_config_answers_as_the_models(path: Path, cache: Path) -> None:
    config, cached, _ = _through_cache(path)
    if path.name in NOT_STORED or path in NOT_STORED_REMOTE:
        assert cached is None and not cache.exists()  # their paths load pydantic anyway
        return
    assert cached is not None and type(cached).__name__ == "Config" and not isinstance(cached, Config)
    assert _answers(cached) == _answers(config)


@pytest.mark.parametrize("overrides", MORE)
def test_every_table_read_back(overrides: list[str], cache: Path) -> None:
    config, cached, _ = _through_cache(PAPER, overrides)
    assert cached is not None
    assert _answers(cached) == _answers(config)
    if "links.delay=0.02" in overrides:
        assert config.linked()


def test_the_link_keys_are_the_link_parameters(cache: Path) -> None:
    assert tuple(LinkKeys.model_fields) == LINK_KEYS
    assert NO_LINKS == Links()  # what a config without [links] is compared with


def test_an_entry_of_other_code_is_not_used(cache: Path) -> None:
    _, cached, raw = _through_cache(PAPER)
    assert cached is not None
    [entry] = cache.iterdir()
    stored = json.loads(entry.read_text())
    module = next(file for file in stored["modules"] if file.endswith("config_tables.py"))
    stored["modules"][module][1] -= 1  # the models' file changed since
    entry.write_text(json.dumps(stored))
    assert config_records.cached_config(raw) is None
    stored["modules"][module][1] += 1
    entry.write_text(json.dumps(stored))
    assert config_records.cached_config(raw) is not None
    stored["key"] = stored["key"].replace("platoon", "plat00n")  # another mapping whose file name would be the same
    entry.write_text(json.dumps(stored))
    assert config_records.cached_config(raw) is None
    entry.write_text("{")  # a damaged entry: validated again
    assert config_records.cached_config(raw) is None


def test_a_value_a_record_cannot_hold_is_not_stored(cache: Path) -> None:
    config, raw = parse_config(read_config_text(PAPER), PAPER.stem, [], PAPER.parent)
    raw["date"] = __import__("datetime").date(2026, 1, 1)  # TOML has dates; the mapping is then no JSON key
    config_records.store_config(raw, config)
    assert not cache.exists()


def _platoon(*args: object, cwd: Path, cache_home: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "XDG_CACHE_HOME": str(cache_home), "PYTHONPATH": str(REPO), "NO_COLOR": "1", "TERM": "dumb",
           "COLUMNS": "80"}
    env.pop("FORCE_COLOR", None)
    return subprocess.run([sys.executable, "-c", "from orchestrator.cli import main; main()", *map(str, args)],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def _records(path: Path) -> tuple[list, dict]:
    """Every message and the metadata of a trace, the run's start stamp left out."""
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        messages = [(channel.topic, message.log_time, message.data) for _, channel, message in reader.iter_messages()]
    with open(path, "rb") as stream:
        metadata = {record.name: dict(record.metadata) for record in make_reader(stream).iter_metadata()}
    metadata["platoon.start"].pop("started")
    return messages, metadata


@pytest.mark.parametrize("config, overrides", [
    ("paper/platoon.toml", ["platoon.count=16"]),  # a warning line, too
    ("paper/platoon_lossy.toml", []), ("paper/m3pi_front_lateral.toml", []), ("paper/platoon_cacc.toml", [])])
def test_runs_and_reports_from_the_cache_are_the_same(config: str, overrides: list[str], tmp_path: Path,
                                                      fmu_dir: Path, native_fmu_dir: Path) -> None:
    """The first run validates and stores, the second comes from the cache: the same trace but for its start
    stamp, the same lines; their reports (table and JSON), the first validating and the second not, the same."""
    sets = [item for override in ["simulation.stop_time=3", *overrides] for item in ("--set", override)]
    runs = [_platoon("run", REPO / "configs" / config, *sets, "--out", tmp_path / f"{name}.mcap", cwd=REPO,
                     cache_home=tmp_path / "cache") for name in ("first", "second")]
    assert [run.returncode for run in runs] == [0, 0], runs[0].stderr + runs[1].stderr
    assert len(list((tmp_path / "cache" / "platoon-cosim" / "configs").iterdir())) == 1
    assert _records(tmp_path / "first.mcap") == _records(tmp_path / "second.mcap")
    lines = [[line.replace(str(tmp_path / name), "X") for line in run.stdout.splitlines() + run.stderr.splitlines() if "steps in" not in line]
             for name, run in zip(("first", "second"), runs)]
    assert lines[0] == lines[1]
    for form in ([], ["--json"]):
        reports = [_platoon("report", tmp_path / "first.mcap", *form, cwd=REPO, cache_home=tmp_path / "cache")
                   for _ in range(2)]
        assert reports[0].returncode == 0 and (reports[0].stdout, reports[0].stderr) == (reports[1].stdout, reports[1].stderr)


def test_a_bad_config_is_never_stored(tmp_path: Path) -> None:
    results = [_platoon("run", PAPER, "--set", "platoon.k_v=0", "-q", "--out", tmp_path / "t.mcap", cwd=REPO,
                        cache_home=tmp_path / "cache") for _ in range(2)]
    assert [r.returncode for r in results] == [2, 2]
    assert results[0].stderr == results[1].stderr and "platoon.k_v = 0: must be" in results[0].stderr
    assert not (tmp_path / "cache" / "platoon-cosim" / "configs").exists()
