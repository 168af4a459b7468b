"""The Link FMU: one communication link between two platoon components (fmus/model/link.py).

Placed by the wiring on one direction of Fig. 2 when a config has a [links] table (docs/links.md):
the sender's message goes into the ``in.*`` inputs, the message in use comes out under the sender's
own output names, with the link's counters (sent, delivered, lost) and the message's age beside it.
"""

from __future__ import annotations

from typing import Any

from pythonfmu.default_experiment import DefaultExperiment

from fmus.model.factory import link_parameter_errors, link_stepper
from fmus.model.link import SIGNALS
from fmus.slaves import defaults as d
from fmus.slaves.base import PlatoonSlave, VariableInfo, real
from fmus.slaves.refusal import fmi_call

_UNITS = {"x": "m", "y": "m", "heading": "rad", "speed": "m/s", "speed_rate": "m/s2", "turn_rate": "rad/s",
          "gap": "m", "gap_rate": "m/s"}
# Start values: a Vehicle's own for its unconnected inputs (fmus/slaves/defaults.py), so a receiver reads
# sane values in the masters' first pass of initialization, before any value has propagated.
_STARTS = {"x": d.TARGET_X, "y": d.TARGET_Y, "heading": d.TARGET_HEADING, "speed": d.SPEED, "speed_rate": 0.0,
           "turn_rate": d.TARGET_TURN_RATE, "gap": d.D_STAR, "gap_rate": 0.0}
_INPUT_ATTRIBUTES = {f"in.{name}": f"in_{name}" for name in SIGNALS} | {"in.time": "in_time"}


def _parameters() -> tuple[VariableInfo, ...]:
    return (
        real("delay", "parameter", "Delay from a message's output_time to its arrival", "s", start=0.0, min=0.0),
        real("jitter", "parameter", "Upper end of each message's extra delay, uniform in [0, jitter]", "s", start=0.0, min=0.0),
        real("period", "parameter", "Time between beacons (0: every new message is sent)", "s", start=0.0, min=0.0),
        real("loss", "parameter", "Probability a sent message is lost (the mean, with bursts)", None, start=0.0, min=0.0, max=1.0),
        real("burst", "parameter", "Mean burst length of losses in messages; > 1 selects a Gilbert-Elliott channel", None, start=1.0, min=1.0),
        VariableInfo("seed", "Integer", "parameter", "Seed of the link's random stream (splitmix64)", start=0, min=0),
        VariableInfo("stream", "Integer", "parameter", "The link's own stream of the seed (its number in the wiring)", start=0, min=0),
    )


def _inputs() -> tuple[VariableInfo, ...]:
    return tuple(real(f"in.{name}", "input", f"The sender's {name}", _UNITS[name], start=_STARTS[name])
                 for name in SIGNALS) + (
        real("in.time", "input", "Time the sender's values describe (its output_time)", "s", start=0.0),)


def _outputs() -> tuple[VariableInfo, ...]:
    held = tuple(real(name, "output", f"{name} of the message in use (held until a newer one arrives)", _UNITS[name],
                      depends_on=(), initial_depends_on=(f"in.{name}",)) for name in SIGNALS)
    return held + (
        real("output_time", "output", "Time the message in use describes (the sender's output_time); wire it to the "
             "receiver's *.time input", "s", depends_on=(), initial_depends_on=("in.time",)),
        real("sent", "output", "Messages sent so far (the initial message not counted)", None, variability="discrete",
             depends_on=(), initial_depends_on=()),
        real("delivered", "output", "Messages delivered so far", None, variability="discrete", depends_on=(),
             initial_depends_on=()),
        real("lost", "output", "Messages lost so far", None, variability="discrete", depends_on=(), initial_depends_on=()),
        real("age", "output", "Age of the message in use: this time minus its output_time", "s", depends_on=(),
             initial_depends_on=("in.time",), depends_on_time=True),
    )


class Link(PlatoonSlave):
    """A link: delay, jitter, beacons (sample and hold), independent or Gilbert-Elliott loss; seeded."""

    description = "Communication link between two platoon components: delay, jitter, beacons, loss (seeded)"
    variables = _parameters() + _inputs() + _outputs()
    input_attributes = _INPUT_ATTRIBUTES
    default_experiment = DefaultExperiment(start_time=0.0, stop_time=d.STOP_TIME, step_size=d.STEP)

    parameter_errors_of = staticmethod(link_parameter_errors)
    stepper_of = staticmethod(link_stepper)

    @fmi_call
    def exit_initialization_mode(self) -> Any:
        """The message at the end of initialization is the one in use from the start."""
        result = super().exit_initialization_mode()
        self.stepper.take_initial()
        return result


assert set(_INPUT_ATTRIBUTES) == {i.name for i in _inputs()}
