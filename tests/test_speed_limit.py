"""The kinematic vehicle's optional speed limit (platoon.speed_max; docs/model.md, section 6): off by default and then
the same to the bit, on it clips the speed loop's command as an m3pi clips its wheels. The C twin's equality to the
Python model, with the limit biting, is tests/test_native_fmus.py's."""

from __future__ import annotations

import numpy as np
import pytest

from fmus.model.dynamics import KinematicDynamics, make_dynamics
from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import ConfigError, config_from_mapping, load_config
from orchestrator.scenario.scenario import build_scenario
from orchestrator.trace import load


@pytest.mark.parametrize("command", [-40.0, -3.0, 0.0, 12.5, 24.0, 24.0000001, 31.0, 1e6])
def test_the_limit_clips_the_speed_command_and_no_limit_changes_nothing(command):
    state = [1.0, 2.0, 0.3, 20.0]
    free = KinematicDynamics(k_v=0.7).derivative(state, 0.4, command, 0.5)
    assert free[3] == 0.7 * (command - 20.0)  # exactly the unlimited loop: no arithmetic added
    limited = make_dynamics("kinematic", 0.7, speed_max=24.0).derivative(state, 0.4, command, 0.5)
    assert limited[3] == 0.7 * (min(max(command, -24.0), 24.0) - 20.0)
    assert limited[:3] == free[:3]  # the limit acts on the speed loop only


def test_a_run_under_the_limit_stays_under_it(tmp_path):
    """The paper's platoon (vehicles started at 0.8 V_c) overshoots V_c = 25 m/s by up to 2.6 m/s; with
    platoon.speed_max = 26 m/s no vehicle passes 26 m/s, and the vehicle that would is held just under it."""
    speeds = {}
    for label, overrides in (("free", []), ("limited", ["platoon.speed_max=26"])):
        config, _ = load_config("configs/paper/platoon.toml", overrides)
        result = run_scenario(config, "", tmp_path / f"{label}.mcap", foxglove=False)
        assert result.status == "completed"
        trace = load(result.trace)
        speeds[label] = {name: np.asarray(trace.channels[name]["speed"]) for name in trace.vehicles()}
    assert max(s.max() for s in speeds["free"].values()) > 27.0
    assert max(s.max() for s in speeds["limited"].values()) <= 26.0
    assert speeds["limited"]["vehicle1"].max() > 25.9


def test_the_key_reaches_kinematic_vehicles_only_and_only_when_set():
    mixed = {"name": "mixed", "platoon": {"count": 3, "speed": 0.3, "d_star": 0.6}, "path": {"radius": 1.0},
             "vehicles": {"2": {"dynamics": "m3pi"}}}
    plain = build_scenario(config_from_mapping(mixed)).components[1:]
    assert all("speed_max" not in spec.parameters for spec in plain)  # a run without the key: the parameters of before
    limited = build_scenario(config_from_mapping({**mixed, "platoon": {**mixed["platoon"], "speed_max": 0.5}}))
    assert [spec.parameters.get("speed_max") for spec in limited.components[1:]] == [0.5, None, 0.5]


@pytest.mark.parametrize("value, message", [
    (20.0, "platoon.speed_max = 20.0: expected at least platoon.speed = 25 m/s (a limit below the cruise speed keeps "
           "the platoon from ever reaching it)"),
    (-1.0, "platoon.speed_max = -1.0: must be a finite number >= 0.001 m/s and <= 1000 m/s"),
])
def test_a_bad_limit_is_one_line_naming_the_key(value, message):
    with pytest.raises(ConfigError) as error:
        config_from_mapping({"name": "bad", "platoon": {"speed_max": value}})
    assert str(error.value) == message
