"""A speed push on the virtual target (``[[disturbance]] vehicle = 0``): the platoon's head, prescribed.

Under acc and cacc the target moves at the constant V_c; a push adds to that speed exactly, as a vehicle's
push adds to its speed over ground: sampled at each communication point and held over the step, so the
target's recorded ``speed`` at t_k is V_c plus the push's value at t_(k-1) (the outputs follow the inputs
of the step before), on every engine. That is the clean probe the string-stability study drives acc and
cacc with (docs/model.md, section 12): the Python model and its C twin agree on it to the bit
(tests/test_native_fmus.py), the sampled-data cascade predicts every link from it (tests/test_sampled_chain.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from orchestrator.analysis.error_gains import clean_order, propagation, source_vehicle
from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import config_from_mapping, load_config
from orchestrator.scenario.raw_config import ConfigError
from orchestrator.trace import load

STUDY = Path(__file__).resolve().parent.parent / "configs" / "study" / "string_stability.toml"
STEP, START, VALUE, FREQUENCY = 0.02, 2.0, 0.1, 1.0


def _platoon(law: str, disturbance: list[dict]) -> dict:
    return {"name": "head", "simulation": {"stop_time": 10.0, "step": STEP}, "path": {"kind": "line"},
            "platoon": {"count": 3, "d_star": 75.0, "speed": 25.0, "k_v": 1.0, "time_gap": 0.5, "speed_law": law},
            "disturbance": disturbance}


SINE = {"vehicle": 0, "kind": "speed", "start": START, "duration": 5.0, "value": VALUE, "frequency": FREQUENCY}


@pytest.mark.parametrize("engine", ["native", "python", "monolithic"])
@pytest.mark.parametrize("law", ["acc", "cacc"])
def test_the_targets_speed_is_v_c_plus_the_push_held_over_each_step(law, engine, native_fmu_dir, fmu_dir, tmp_path):
    config = config_from_mapping(_platoon(law, [SINE]))
    result = run_scenario(config, "", tmp_path / "run.mcap", engine=engine, foxglove=False)
    assert result.status == "completed", result.error
    trace = load(result.trace)
    target, vehicle1 = trace.component("target"), trace.component("vehicle1")
    k = np.rint(target["t"] / STEP).astype(int)
    before = (k - 1) * STEP  # the push set at t_(k-1) acts over the step that ends at t_k
    inside = (before >= START - 1e-9) & (before < START + 5.0 - 1e-9)
    expected = 25.0 + np.where(inside, VALUE * np.sin(FREQUENCY * (before - START)), 0.0)
    assert np.abs(target["speed"] - expected).max() < 1e-12  # sin's rounding at these arguments, nothing more
    assert np.all(target["speed_rate"] == 0.0)  # a held push has no rate, as a vehicle's has none
    # the head's push is what moves the platoon: vehicle 1 follows it, and not before it starts
    assert np.abs(vehicle1["speed"][target["t"] <= START] - 25.0).max() < 1e-9
    assert np.abs(vehicle1["speed"][target["t"] > START + 1.0] - 25.0).max() > 0.05


def test_an_unpushed_target_is_todays_target(native_fmu_dir, tmp_path):
    """A push of zero adds nothing: the run of a config without it is the same to the last bit."""
    pushed = config_from_mapping(_platoon("cacc", [{**SINE, "value": 0.0}]))
    plain = config_from_mapping(_platoon("cacc", []))
    traces = [load(run_scenario(c, "", tmp_path / f"{i}.mcap", foxglove=False).trace) for i, c in enumerate((pushed, plain))]
    for name in ("target", "vehicle1", "vehicle3"):
        a, b = (trace.component(name) for trace in traces)
        assert a.keys() == b.keys() and all(np.array_equal(a[column], b[column]) for column in a)


@pytest.mark.parametrize("disturbance, key, words", [
    ({**SINE, "kind": "lateral_acceleration"}, "disturbance[0].kind", 'expected "speed" on vehicle 0'),
    ({**SINE, "vehicle": 4}, "disturbance[0].vehicle", "from 1 to platoon.count = 3 (or 0, the virtual target)"),
    ({**SINE, "vehicle": -1}, "disturbance[0].vehicle", ">= 0"),
])
def test_a_bad_target_push_is_a_one_line_error_naming_the_key(disturbance, key, words):
    with pytest.raises(ConfigError) as caught:
        config_from_mapping(_platoon("cacc", [disturbance]))
    message = str(caught.value)
    assert key in message and words in message and "\n" not in message, message


def test_the_study_pushes_the_head_under_acc_and_cacc_and_the_tail_under_the_papers_law():
    """The links that measure propagation start two receivers past the pushed end and stop before the other
    one: the first receivers of a held push carry what their extrapolation makes of a staircase without a
    rate (the head link's gain at 0.1 rad/s is 1.013 under cacc with 0.3 s links where the chain's is 0.999)."""
    names = [f"vehicle{k}" for k in range(1, 8)]
    for law, source, order, clean in (
            ("cacc", 0, ["target"] + names, names[2:6]),
            ("acc", 0, ["target"] + names, names[2:6]),
            ("paper", 7, names[::-1], names[3::-1])):
        config, _ = load_config(STUDY, [f"platoon.speed_law={law}"])
        assert source_vehicle(config) == source
        assert propagation(config, names, source) == order
        assert clean_order(config, names) == clean
    pushes = config.disturbance
    assert {d.vehicle for d in pushes} == {0, 7} and all(d.kind == "speed" and d.frequency > 0 for d in pushes)
    assert math.isclose(pushes[0].start + pushes[0].duration, config.simulation.stop_time, abs_tol=0.1)
