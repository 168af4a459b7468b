"""The LiveVehicle FMU: a live m3pi robot on Zenoh behind the Vehicle FMU's interface.

Any FMI importer (libcosim, FMPy, an SSP exported by ``platoon export-ssp``) can put it where a
Vehicle FMU would be: same inputs, outputs and parameters, same names and units (declared by
importing the Vehicle's declarations), plus the ``hil.*`` parameters that say where the robot is.
Inside, it is ``bridge.live.LiveVehicle``, the host side of the hardware-in-the-loop link that
``platoon run`` uses, so the protocol, the checks and the safety rules are that code's:

* leaving initialization opens the Zenoh session and waits (``hil.connect_timeout``) for the robot's
  liveliness token and first valid pose (no robot: the reason is logged, and the first doStep fails
  with it);
* each doStep(t, h) evaluates the guidance on the robot's measured pose, sends the wheel command with
  its deadline, waits until wall-clock time has reached t + h (``fmus.realtime.Pacer``,
  started at the first step), then takes the pose the outputs describe;
* the robot lost (its token gone, or no valid pose for ``hil.pose_timeout``): a stop command is sent
  and doStep returns fmi2Error with the reason in the FMU's log; terminate stops the robot and leaves
  Zenoh, and with it every thread the link held;
* a host that never terminates the instance (or frees it only as its interpreter tears down) still exits:
  the link is closed as the host's interpreter begins to exit, before it joins its threads
  (``fmus.slaves.host_exit.close_at_host_exit``), which stops the robot as terminate would.

The FMU's resources carry the bridge code it needs (``fmus.builders.pythonfmu``); it needs the ``eclipse-zenoh``
package in the Python environment that runs it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from pythonfmu.default_experiment import DefaultExperiment
from pythonfmu.enums import Fmi2Status

from bridge.live import LiveSettings, LiveVehicle as LiveLink
from bridge.protocol import DEFAULT_PREFIX, check_prefix
from fmus.model.factory import controller_stepper, vehicle_parameter_errors
from fmus.model.vehicle import VehicleStepper
from fmus.slaves import Vehicle as vehicle_slave  # the module: pythonfmu wants one slave class here
from fmus.slaves.base import PlatoonSlave, VariableInfo, real
from fmus.slaves.host_exit import close_at_host_exit
from fmus.component import ComponentError
from fmus.realtime import Pacer

_LEVELS = {"Info": Fmi2Status.ok, "Warning": Fmi2Status.warning, "Error": Fmi2Status.error}
_DEFAULTS = LiveSettings(robot=3)


def _hil_parameters() -> tuple[VariableInfo, ...]:
    d = _DEFAULTS
    return (
        VariableInfo("hil.robot", "Integer", "parameter", "The robot's id in the Zenoh keys <prefix>/m3pi/<id>/...",
                     start=d.robot, min=0, max=2**31 - 1),
        VariableInfo("hil.prefix", "String", "parameter", "Zenoh key prefix", start=DEFAULT_PREFIX),
        VariableInfo("hil.connect", "String", "parameter", "Zenoh endpoints to connect to, comma-separated "
                     "(e.g. tcp/127.0.0.1:7447)", start="tcp/127.0.0.1:7447"),
        VariableInfo("hil.listen", "String", "parameter", "Zenoh endpoints to listen on, comma-separated", start=""),
        VariableInfo("hil.zenoh_config", "String", "parameter", "Zenoh config file (JSON5: TLS, access control, "
                     "router); empty: peer mode, no scouting", start=""),
        real("hil.pose_timeout", "parameter", "Time without a valid pose after which the robot is lost", "s",
             start=d.pose_timeout, min=0.0),
        real("hil.connect_timeout", "parameter", "Time to wait for the robot when initialization ends", "s",
             start=d.connect_timeout, min=0.0),
        real("hil.command_validity", "parameter", "Each wheel command's deadline: its send time plus this", "s",
             start=d.command_validity, min=0.0),
        real("hil.max_pose_age", "parameter", "An older pose (receive time minus stamp) is dropped as late", "s",
             start=d.max_pose_age, min=0.0),
        VariableInfo("hil.allow_insecure", "Boolean", "parameter", "Allow Zenoh endpoints off this machine without "
                     "TLS (docs/hil.md, \"A secure lab\")", start=d.allow_insecure),
        VariableInfo("hil.lab_key", "String", "parameter", "The lab key file the robot side shares (docs/hil.md, "
                     "\"Who can start the robot\"); empty: $PLATOON_LAB_KEY, else ~/.config/platoon/lab.key", start=""),
        VariableInfo("hil.mode", "String", "parameter", "The Zenoh session's mode without a zenoh_config: peer, or "
                     "client of a router (docs/hil.md, \"Recipe: ROS 2 with rmw_zenoh\")", start=d.mode),
    )


def _endpoints(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def hil_parameters(settings: LiveSettings) -> dict[str, Any]:
    """The ``hil.*`` parameter values that make this FMU reach the robot of ``settings``."""
    values = {f"hil.{field.name}": getattr(settings, field.name) for field in dataclasses.fields(settings)}
    values["hil.connect"] = ",".join(settings.connect)
    values["hil.listen"] = ",".join(settings.listen)
    values["hil.zenoh_config"] = settings.zenoh_config or ""
    values["hil.lab_key"] = settings.lab_key or ""
    return values


def live_settings(values: dict[str, Any]) -> LiveSettings:
    """``LiveSettings`` from the ``hil.*`` parameter values (the inverse of ``hil_parameters``)."""
    fields = {field.name: values[f"hil.{field.name}"] for field in dataclasses.fields(LiveSettings)}
    fields["connect"] = _endpoints(values["hil.connect"])
    fields["listen"] = _endpoints(values["hil.listen"])
    fields["zenoh_config"] = values["hil.zenoh_config"] or None
    fields["robot"] = int(values["hil.robot"])
    fields["allow_insecure"] = bool(values["hil.allow_insecure"])
    fields["lab_key"] = values["hil.lab_key"] or None
    return LiveSettings(**fields)


class LiveVehicle(PlatoonSlave):
    """Platoon vehicle driven by a live m3pi robot on Zenoh (the Vehicle FMU's interface)."""

    description = ("A platoon vehicle that is a live Pololu m3pi robot on Zenoh: trajectory shaping guidance on "
                   "the robot's measured pose, wheel commands to the robot, paced to wall-clock time")
    # the Vehicle's variables, with m3pi dynamics by default (a live robot is an m3pi)
    variables = tuple(dataclasses.replace(info, start="m3pi") if info.name == "dynamics" else info
                      for info in vehicle_slave.Vehicle.variables) + _hil_parameters()
    input_attributes = vehicle_slave.Vehicle.input_attributes
    default_experiment = DefaultExperiment(start_time=0.0, stop_time=60.0, step_size=0.01)
    # a real robot cannot be rolled back: no FMU state
    capabilities = {"canGetAndSetFMUstate": "false", "canSerializeFMUstate": "false"}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.link: LiveLink | None = None
        self.pacer: Pacer | None = None
        self.unreachable = ""  # why the robot could not be reached when initialization ended
        self._withdraw_exit_close: Callable[[], None] = lambda: None  # the host's exit no longer closes the link

    def parameter_errors(self) -> list[str]:
        values = self.values
        errors = vehicle_parameter_errors(values)
        if values["dynamics"] != "m3pi":
            errors.append(f"dynamics = {values['dynamics']!r}: a live robot is an m3pi (dynamics = \"m3pi\")")
        errors += [f"hil.prefix = {values['hil.prefix']!r}: {problem}" for problem in check_prefix(values["hil.prefix"])]
        for name in ("hil.pose_timeout", "hil.connect_timeout", "hil.command_validity", "hil.max_pose_age"):
            if not values[name] > 0.0:
                errors.append(f"{name} = {values[name]}: must be a number of seconds > 0")
        if not 0 <= values["hil.robot"] <= 2**31 - 1:
            errors.append(f"hil.robot = {values['hil.robot']}: expected 0 ... 2^31 - 1")
        if not _endpoints(values["hil.connect"]) and not _endpoints(values["hil.listen"]) \
                and not values["hil.zenoh_config"]:
            errors.append("hil.connect, hil.listen and hil.zenoh_config are all empty: nowhere to meet the robot")
        return errors

    def make_stepper(self, start_time: float) -> VehicleStepper:
        """The live run's controller: the robot itself, with whatever latencies it has, is out there."""
        return controller_stepper(self.values, start_time)

    def _forward_link_log(self, link: LiveLink | None = None) -> None:
        """The link's state changes and first drops into the FMU's log; its raw records are not kept."""
        link = link or self.link
        if link is None:
            return
        for event in link.drain_events():
            self.log(event.message, _LEVELS.get(event.level, Fmi2Status.ok))
        link.drain_records()

    def exit_initialization_mode(self) -> None:
        """Check the parameters (as every slave does), then meet the robot: its token and a first valid pose."""
        super().exit_initialization_mode()
        inputs = [info.name for info in self.variables if info.causality == "input"]
        outputs = [info.name for info in self.variables if info.causality == "output"]
        start_time = getattr(self, "start_time", 0.0)
        self.link = LiveLink(self.instance_name, self.values, inputs, outputs,
                             [float(self.values[name]) for name in inputs], live_settings(self.values))
        self._withdraw_exit_close = close_at_host_exit(self._close_at_exit)
        try:
            self.link.initialize(start_time)
            self.link.set_inputs([self.values[name] for name in inputs])
            self.link.end_initialization()
        except ComponentError as error:
            # No robot: reported now in the log and again by the first doStep, which fails. Raising here
            # would lose the reason (pythonfmu 0.7 drops the log of a call that raises).
            self._forward_link_log()
            self.log(str(error), Fmi2Status.error)
            self.link.close()
            self._withdraw_exit_close()
            self.link, self.unreachable = None, str(error)
            return
        self._forward_link_log()
        self.stepper = self.link.stepper  # inputs set by the master now go straight to the link's controller
        self._outputs = None

    def do_step(self, current_time: float, step_size: float) -> bool:
        link = self.link
        if link is None:
            self.log(self.unreachable or f"{self.instance_name}: doStep before initialization ended", Fmi2Status.error)
            return False
        if self.pacer is None:  # wall-clock time starts with the first step, whatever initialization took
            self.pacer = Pacer()
            self.pacer.start(current_time)
        try:
            link.step(current_time, step_size)
            self.pacer.wait_until(current_time + step_size)
            link.get_outputs()  # checks the link, takes the newest pose: the outputs describe t + h
        except ComponentError as error:  # the link already sent the stop command
            self._forward_link_log()
            self.log(str(error), Fmi2Status.error)
            return False
        self._forward_link_log()
        self._outputs = None
        return True

    def terminate(self) -> None:
        """Stop the robot and leave Zenoh; the link's and the pacing's statistics go to the log."""
        if self.link is None:
            return
        link, self.link = self.link, None
        self._withdraw_exit_close()
        try:
            link.close()
        except ComponentError as error:  # a command it never sent, applied while it stopped: said at Error level
            self._forward_link_log(link)  # (pythonfmu 0.7 drops the log of a call that raises)
            self.log(str(error), Fmi2Status.error)
        self._forward_link_log(link)
        statistics = link.link_statistics()
        pacing = self.pacer.summary() if self.pacer is not None else {}
        self.log(f"{self.instance_name}: {link.what}: commands sent {statistics.get('command.sent')}, poses accepted "
                 f"{statistics.get('pose.accepted')}, dropped {link.pose_counters.dropped_total}; paced points "
                 f"{pacing.get('points', 0)}, overruns {pacing.get('overruns', 0)}")

    def _close_at_exit(self) -> None:
        """The host's interpreter begins to exit with the link open: stop the robot and leave Zenoh now. The
        link is forgotten, so a terminate that comes later, in the interpreter's teardown (libcosim's execution
        collected with the host's globals), finds nothing to do: by then module globals may be gone."""
        link, self.link = self.link, None
        if link is not None:
            link.close()

    def _get_fmu_state(self) -> dict[str, Any]:
        raise RuntimeError("a live robot has no FMU state to save (canGetAndSetFMUstate = false)")

    def _set_fmu_state(self, state: dict[str, Any]) -> None:
        raise RuntimeError("a live robot cannot be rolled back (canGetAndSetFMUstate = false)")
