"""The RemoteVehicle FMU: a client for a Vehicle FMU served by ``platoon serve`` on another host.

Any FMI importer (libcosim, FMPy, an SSP exported by ``platoon export-ssp`` of a config with
``endpoint = "remote"`` vehicles) puts it where a Vehicle FMU would be: the Vehicle's inputs, outputs
and parameters, same names and units (its declarations imported), plus the ``remote.*`` parameters
that say where the server is. Inside it is ``bridge.fmu_client.RemoteComponent``, the very client
``platoon run`` steps a remote vehicle with, so the wire protocol, its checks and its timeouts are
that code's (bridge/fmu_wire.py), and the numbers are the served FMU's, bit for bit:

* the instance is opened on the server (instantiate, the parameters the importer set, initialization
  mode) when its outputs are first read, at the latest when initialization ends; outputs read in
  initialization mode, or after inputs changed, are the server's (one exchange);
* each doStep(t, h) sends the inputs, t and h in one request and waits (``remote.step_timeout``) for
  the outputs at t + h. No reply (the server killed, the network parted, a server too slow): doStep
  fails (False: pythonfmu answers fmi2Discard) with one line at error level in the FMU's log naming the
  vehicle, the server's key and where it was reached;
* fmi2Terminate frees the served instance and leaves Zenoh; a host that never terminates it (or frees
  it only as its interpreter tears down) still exits, and the server is freed for the next run, as the
  host's interpreter begins to exit (``fmus.slaves.host_exit.close_at_host_exit``).

The FMU's resources carry the bridge code it needs (``fmus.builders.pythonfmu``); it needs the
``eclipse-zenoh`` package in the Python environment that runs it.
"""

from __future__ import annotations

from typing import Any, Callable

from pythonfmu.enums import Fmi2Status

from bridge.fmu_client import RemoteComponent, shared_host
from bridge.fmu_wire import fmu_key
from bridge.protocol import DEFAULT_PREFIX, check_prefix
from bridge.session import SessionError
from fmus.component import ComponentError
from fmus.slaves import Vehicle as vehicle_slave  # the module: pythonfmu wants one slave class here
from fmus.slaves.base import PlatoonSlave, VariableInfo, real
from fmus.slaves.host_exit import close_at_host_exit
from fmus.slaves.refusal import refuse

REMOTE = "remote."  # the prefix of this FMU's own parameters; the others are the served FMU's


def _remote_parameters() -> tuple[VariableInfo, ...]:
    return (
        VariableInfo("remote.server", "String", "parameter", "The server's name (`platoon serve --name`); its key is "
                     "<remote.prefix>/fmu/<remote.server>. Empty: this instance's name", start=""),
        VariableInfo("remote.prefix", "String", "parameter", "Zenoh key prefix", start=DEFAULT_PREFIX),
        VariableInfo("remote.connect", "String", "parameter", "Zenoh endpoints to connect to, comma-separated "
                     "(e.g. tcp/127.0.0.1:7501)", start="tcp/127.0.0.1:7447"),
        VariableInfo("remote.listen", "String", "parameter", "Zenoh endpoints to listen on, comma-separated", start=""),
        VariableInfo("remote.zenoh_config", "String", "parameter", "Zenoh config file (JSON5: TLS, access control); "
                     "empty: peer mode, no scouting", start=""),
        real("remote.step_timeout", "parameter", "Time to wait for the server's reply to one call: then the call fails",
             "s", start=2.0, min=0.0),
        real("remote.connect_timeout", "parameter", "Time to wait for the server when the instance opens", "s",
             start=10.0, min=0.0),
        VariableInfo("remote.allow_insecure", "Boolean", "parameter", "Allow Zenoh endpoints off this machine without "
                     "TLS (docs/hil.md, \"A secure lab\")", start=False),
    )


def _endpoints(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def remote_parameters(server: str, prefix: str, connect: tuple[str, ...], listen: tuple[str, ...],
                      zenoh_config: str | None, step_timeout: float, connect_timeout: float,
                      allow_insecure: bool) -> dict[str, Any]:
    """The ``remote.*`` parameter values that make this FMU reach server ``server`` (what an export sets)."""
    return {"remote.server": server, "remote.prefix": prefix, "remote.connect": ",".join(connect),
            "remote.listen": ",".join(listen), "remote.zenoh_config": zenoh_config or "",
            "remote.step_timeout": float(step_timeout), "remote.connect_timeout": float(connect_timeout),
            "remote.allow_insecure": bool(allow_insecure)}


class RemoteVehicle(PlatoonSlave):
    """Platoon vehicle whose FMU instance lives in a ``platoon serve`` (the Vehicle FMU's interface)."""

    description = ("A platoon vehicle whose Vehicle FMU runs in a `platoon serve` on another host or process, "
                   "stepped over Zenoh: the served FMU's numbers, bit for bit")
    variables = vehicle_slave.Vehicle.variables + _remote_parameters()
    input_attributes = vehicle_slave.Vehicle.input_attributes
    default_experiment = vehicle_slave.Vehicle.default_experiment
    # the served instance cannot be rolled back through the wire protocol: no FMU state
    capabilities = {"canGetAndSetFMUstate": "false", "canSerializeFMUstate": "false"}

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.remote: RemoteComponent | None = None
        self.assigned: set[str] = set()  # the served FMU's parameters the importer set: what the server gets
        self.opened_with: dict[str, Any] = {}
        self.entering = False  # initialization mode entered: outputs are the server's from then on
        self.initialized = False
        self.lost = ""  # why the server can no longer be used (never reached, a failed step)
        self._inputs = [info.name for info in self.variables if info.causality == "input"]
        self._output_names = [info.name for info in self.variables if info.causality == "output"]
        self._served_parameters = {info.name for info in self.variables
                                   if info.causality == "parameter" and not info.name.startswith(REMOTE)}
        self._withdraw_exit_close: Callable[[], None] = lambda: None

    # --- what the importer sets ---------------------------------------------------------------

    def _set(self, name: str, value: Any) -> None:
        if name in self._served_parameters:
            self.assigned.add(name)
        super()._set(name, value)

    def set_real(self, vrs: list[int], values: list[float]) -> None:
        self.assigned.update(n for n in map(self._name_of.get, vrs) if n in self._served_parameters)
        super().set_real(vrs, values)

    def parameter_errors(self) -> list[str]:
        values = self.values
        errors = [f"remote.prefix = {values['remote.prefix']!r}: {problem}"
                  for problem in check_prefix(values["remote.prefix"])]
        if values["remote.server"]:
            errors += [f"remote.server = {values['remote.server']!r}: {problem}"
                       for problem in check_prefix(values["remote.server"])]
        for name in ("remote.step_timeout", "remote.connect_timeout"):
            if not values[name] > 0.0:
                errors.append(f"{name} = {values[name]}: must be a number of seconds > 0")
        if not _endpoints(values["remote.connect"]) and not _endpoints(values["remote.listen"]) \
                and not values["remote.zenoh_config"]:
            errors.append("remote.connect, remote.listen and remote.zenoh_config are all empty: nowhere to meet "
                          "the server")
        return errors

    # --- the served instance ------------------------------------------------------------------

    def _parameters(self) -> dict[str, Any]:
        return {name: self.values[name] for name in sorted(self.assigned)}

    def _open(self) -> RemoteComponent:
        """The served instance, opened with the parameters set so far (reopened if one changed since, while
        still initializing). Raises ``ComponentError`` (or ``SessionError``) when the server cannot be used."""
        if self.remote is not None and (self.initialized or self.opened_with == self._parameters()):
            return self.remote
        self._close_remote()
        errors = self.parameter_errors()
        if errors:
            raise ComponentError(self.instance_name, self._time(), "invalid parameter(s): " + "; ".join(errors))
        values = self.values
        connect, listen = _endpoints(values["remote.connect"]), _endpoints(values["remote.listen"])
        host = shared_host(connect, listen, values["remote.zenoh_config"] or None, bool(values["remote.allow_insecure"]))
        where = ", ".join(connect or listen) or values["remote.zenoh_config"]
        key = fmu_key(values["remote.prefix"], values["remote.server"] or self.instance_name)
        starts = {info.name: info.start for info in self.variables}
        remote = RemoteComponent(self.instance_name, key, where, self._parameters(), self._inputs, self._output_names,
                                 [float(starts[name]) for name in self._inputs], host,
                                 float(values["remote.step_timeout"]), float(values["remote.connect_timeout"]))
        self.opened_with = dict(remote.parameters)
        try:
            remote.initialize(getattr(self, "start_time", 0.0))
        except BaseException:
            remote.close()
            raise
        self.remote = remote
        self._withdraw_exit_close = close_at_host_exit(self._close_at_exit)
        return remote

    def _exchange(self) -> dict[str, float]:
        """The served FMU's outputs for the inputs set now (one round trip)."""
        remote = self._open()
        remote.set_inputs([float(self.values[name]) for name in self._inputs])
        return dict(zip(self._output_names, remote.get_outputs()))

    def enter_initialization_mode(self) -> None:
        self._refuse_if_failed()
        self.entering = True

    def _current_outputs(self) -> dict[str, float]:
        if not self.entering:  # FMI 2.0 has no outputs before initialization (pythonfmu's builder reads them)
            return {name: float(self.values[name]) for name in self._output_names}
        if self._outputs is None:
            if self.lost:
                refuse(self, self.lost)
            try:
                self._outputs = self._exchange()
            except (ComponentError, SessionError) as error:
                self._lose(str(error))
                refuse(self, str(error))
        return self._outputs

    def _lose(self, reason: str) -> None:
        """The server cannot be used any more: free what can be freed (a dead server: ``CLOSE_TIMEOUT`` at most)."""
        self.lost = self.lost or reason
        self._close_remote()

    def exit_initialization_mode(self) -> None:
        """Open the instance if the importer did not read an output yet, hand it the inputs set since, end
        its initialization. No server: the reason is logged, and the first doStep fails with it (raising here
        would lose it: pythonfmu 0.7 drops the log of a call that raises)."""
        self._refuse_if_failed()
        if self.lost:
            self.log(self.lost, Fmi2Status.error)
            return
        try:
            if self._outputs is None or self.remote is None:
                self._outputs = self._exchange()
            self.remote.end_initialization()  # type: ignore[union-attr]
            self.initialized = True
        except (ComponentError, SessionError) as error:
            self._lose(str(error))
            self.log(str(error), Fmi2Status.error)

    def do_step(self, current_time: float, step_size: float) -> bool:
        remote = self.remote
        if remote is None or not self.initialized or self.lost:
            self.log(self.lost or f"{self.instance_name}: doStep before initialization ended", Fmi2Status.error)
            return False
        try:
            remote.set_inputs([float(self.values[name]) for name in self._inputs])
            remote.step(current_time, step_size)
            self._outputs = dict(zip(self._output_names, remote.get_outputs()))
        except ComponentError as error:  # the instance is freed at fmi2Terminate (or exit), not here: a free
            self.lost = str(error)  # waits for a dead server's reply, and the step must fail within step_timeout
            self.log(self.lost, Fmi2Status.error)
            return False
        return True

    def terminate(self) -> None:
        """Free the served instance and leave Zenoh (the session's last user closes it)."""
        self._close_remote()

    def _close_remote(self) -> None:
        remote, self.remote = self.remote, None
        self.initialized = False
        if remote is not None:
            self._withdraw_exit_close()
            remote.close()

    def _close_at_exit(self) -> None:
        """The host's interpreter begins to exit with the instance open: free it on its server now, so the
        server serves the next run at once. Forgotten here, so a terminate in the interpreter's teardown
        (libcosim's execution collected with the host's globals) finds nothing to do."""
        remote, self.remote = self.remote, None
        if remote is not None:
            remote.close()

    def _get_fmu_state(self) -> dict[str, Any]:
        raise RuntimeError("a remote vehicle has no FMU state to save (canGetAndSetFMUstate = false)")

    def _set_fmu_state(self, state: dict[str, Any]) -> None:
        raise RuntimeError("a remote vehicle cannot be rolled back (canGetAndSetFMUstate = false)")
