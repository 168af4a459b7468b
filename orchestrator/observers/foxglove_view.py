"""``platoon run --live``: the running co-simulation on a Foxglove WebSocket, for Foxglove or Lichtblick.

The live view advertises the trace's own channels (``/platoon/<component>``, ``/platoon/errors``,
``/platoon/scene``, ``/platoon/tf``, ``/platoon/log`` and, with a live robot, its link's raw streams)
with the same schemas, and sends the same message bytes (orchestrator/trace/encoding.py and
trace/foxglove.py make them for both), stamped with the simulation time as in the trace. A viewer
opened at ``ws://127.0.0.1:PORT`` shows the layout written beside the trace as it shows the file.

What is sent, and when (docs/foxglove.md, "Watch a run live"):

* **Paced**: a co-simulation runs far faster than real time (the paper's 100 s in half a second), so
  with ``--live`` the run is held to ``speed`` simulated seconds per wall second (1: real time; 0: not
  paced) by the same ``Pacer`` that keeps a hardware-in-the-loop run on the wall clock. A run with a
  live robot is on the wall clock already and is not paced twice.
* **Bounded**: at most ``RATE`` frames per wall second, each the latest recorded point: every
  component's message, the errors, the transforms and the whole scene (so a viewer that connects late
  sees everything at once). Log lines and a robot link's raw messages are sent as they come.
* **In simulated time**: messages carry the simulated time, as in the trace, and the server announces
  it with each frame (the Time capability), so the viewer's clock and plot axes read simulated seconds.
* **Non-blocking**: the SDK's server runs in its own threads and drops the oldest messages of a
  client that does not keep up; the run never waits for a viewer, except with ``wait``
  (``--live-wait``), once, before its first step.

The trace is written exactly as without ``--live``: the view only reads the rows the writer gets.
"""

from __future__ import annotations

import sys

import errno
import logging
import math
import threading
import time as clock
from typing import TYPE_CHECKING, Any, Callable, Sequence

from orchestrator.observers.base import Observer
from orchestrator.observers.subprotocol_relay import SubprotocolRelay
from fmus.realtime import Pacer
from orchestrator.trace.encoding import ChannelSpec, ComponentMessages, LiveStream
from orchestrator.trace.foxglove import SCENE_TOPIC, FoxgloveChannels

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
RATE = 30.0  # frames per wall second at most: smooth to the eye, a few hundred messages a second
LOOPBACK = ("127.0.0.1", "localhost", "::1")
LAG_NOTE = 1.0  # wall seconds behind the pace from which the run says it could not keep up
SETTLE = 0.5  # s without a new subscription after which --live-wait takes a viewer's subscriptions as complete


# The SDK logs each client's read error at ERROR; a viewer closed without a goodbye (a browser tab shut,
# a laptop asleep) is how viewers leave, not a fault of the run: it is dropped (other errors still show)
SDK_CLIENT_LOGGER = "foxglove.websocket.connected_client.poller"
ABRUPT_DISCONNECTS = ("Connection reset without closing handshake", "Connection reset by peer", "Broken pipe")


class _QuietDisconnects(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(text in message for text in ABRUPT_DISCONNECTS)


def quiet_abrupt_disconnects() -> None:
    """Drop the SDK's log line for a viewer that left abruptly (once per process)."""
    logger = logging.getLogger(SDK_CLIENT_LOGGER)
    if not any(isinstance(f, _QuietDisconnects) for f in logger.filters):
        logger.addFilter(_QuietDisconnects())


class FoxgloveViewError(ValueError):
    """The live view cannot start (port in use, bad host): one line for the user."""


def app_url(url: str) -> str:
    """The Foxglove/Lichtblick address that opens the WebSocket ``url`` as a data source."""
    return f"https://app.foxglove.dev/?ds=foxglove-websocket&ds.url={url}"


class FoxgloveView(Observer):
    """A Foxglove WebSocket server for one run; ``open`` declares the run's channels, and as an observer of
    the run it is fed what the trace records."""

    wants_rows = True

    def __init__(self, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, speed: float = 1.0, rate: float = RATE,
                 wait: bool = False) -> None:
        import foxglove  # the Rust server and its threads start only for a live run
        from foxglove.websocket import ServerListener

        quiet_abrupt_disconnects()
        self._foxglove = foxglove
        self.context = foxglove.Context()
        self.wait = wait
        self.watched = threading.Event()  # set once a viewer subscribed to the scene
        self.subscribed_at = 0.0  # monotonic time of the latest subscription
        self.waited = 0.0  # s the run waited for a viewer before its first step (--live-wait)

        view = self

        class Watchers(ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                view.subscribed_at = clock.monotonic()
                if channel.topic == SCENE_TOPIC:
                    view.watched.set()

        try:  # the user's port: the relay that also lets older viewers in (orchestrator/observers/subprotocol_relay.py)
            self.relay = SubprotocolRelay(host, port)
        except OSError as error:
            hint = "; another run or program uses it: pick another with --live-port PORT" if error.errno == errno.EADDRINUSE else ""
            raise FoxgloveViewError(f"--live: cannot serve on {host}:{port}: {error.strerror or error}{hint}") from None
        try:  # the SDK's server, reached through the relay only
            # Time: the server says what time it is, the simulated time of the frames (stamped as in the
            # trace), so a viewer's clock and plot axes run in simulated seconds, as with the trace file
            self.server = foxglove.start_server(name="platoon-cosim", host="127.0.0.1", port=0, context=self.context,
                                                capabilities=[foxglove.Capability.Time], server_listener=Watchers())
        except RuntimeError as error:
            self.relay.close()
            raise FoxgloveViewError(f"--live: the Foxglove server did not start: {error}") from None
        self.host, self.port = host, self.relay.port
        self.speed, self.interval = speed, 1.0 / rate
        self.paced = speed > 0
        self._channels: list[Any] = []

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def open(self, config: "Config", components: Sequence[tuple[str, Sequence[str]]],
             descriptions: dict[str, dict[str, str]] | None, every: int, scene_rate: float, on_wall_clock: bool,
             check: Callable[[], object] = lambda: None, streams: dict[str, Sequence[str]] | None = None) -> None:
        """Advertise the run's channels; with ``wait``, return once a viewer subscribed to the scene (``check()``
        meanwhile, which raises to stop waiting, e.g. on Ctrl-C). ``on_wall_clock``: the run is paced already.
        ``streams``: the live robots' raw streams and their numbers (``hil_link.live_streams``), advertised now too."""
        self.rows = ComponentMessages(components, descriptions)
        self.components = [self._advertise(spec) for spec in self.rows.specs]
        self.foxglove = FoxgloveChannels(config, components, scene_rate)
        self.foxglove.bind(self._advertise)
        self.every = every
        self.streams: dict[str, tuple[LiveStream, int]] = {}
        for stream, keys in (streams or {}).items():
            link = LiveStream(stream, keys)
            self.streams[stream] = (link, self._advertise(link.spec))
        if on_wall_clock:
            self.paced = False
        self._pacer: Pacer | None = None
        if self.paced:  # a Pacer on a clock running `speed` times faster: simulated seconds per wall second
            speed = self.speed
            self._pacer = Pacer(clock=lambda: clock.perf_counter() * speed, sleep=lambda s: clock.sleep(s / speed))
        self._pacing = False
        self._frame_step: float | None = None  # set by ``delivery``: pace after each block-filling call
        self._count = 0  # points seen (``point``), for the trace's decimation
        self._latest: list[float] | None = None
        self._sent_at = -float("inf")
        # viewers reach the server only now (until then they wait in the port's backlog): the SDK's server
        # refuses a subscription to a channel advertised while a client is connected ("Unknown channel ID")
        # now and then, so every channel of the run, a live robot's streams too, exists before the first viewer
        self.relay.start(self.server.port)
        # a viewer subscribes to its panels' channels one after the other: once it has the scene, the
        # run starts when no subscription came for SETTLE seconds, so the first frame reaches them all
        waiting_since = clock.perf_counter()
        while self.wait and not (self.watched.wait(0.05) and clock.monotonic() - self.subscribed_at >= SETTLE):
            check()
        self.waited = clock.perf_counter() - waiting_since if self.wait else 0.0

    def _advertise(self, spec: ChannelSpec) -> int:
        channel = self._foxglove.Channel(
            spec.topic, message_encoding=spec.message_encoding, metadata=spec.metadata, context=self.context,
            schema=self._foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema))
        self._channels.append(channel)
        return len(self._channels) - 1

    def _send(self, messages: Sequence[tuple[int, bytes]], stamp: int) -> None:
        for channel, data in messages:
            self._channels[channel].log(data, log_time=stamp)

    # --- what the run hands over -------------------------------------------------------------

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        """A communication point of an engine stepping in Python: the recorded ones (the trace's
        decimation) are shown, each paced."""
        if self._count % self.every == 0:
            row = [t]
            for values in outputs:
                row.extend(values)
            self.row(row)
            self.pace(t)
        self._count += 1

    def row(self, row: list[float]) -> None:
        """One recorded row ``[t, outputs...]`` (every one the trace records, in order)."""
        if not math.isfinite(sum(row)):  # the trace stops before it and says why; so does the view
            return
        self.foxglove.advance(row[0], self.rows.outputs(row))
        self._latest = row
        if clock.monotonic() - self._sent_at >= self.interval:
            self.publish()

    def block(self, rows: Any) -> None:
        """A block of recorded rows (the native engine's ``RowBlock``): trails follow its scene ticks."""
        if len(rows) == 0:
            return
        rows = rows.array()
        times = rows[:, 0]
        while True:  # only the rows at scene ticks are looked at one by one (advance moves the next tick on)
            index = int(times.searchsorted(self.foxglove.next_scene - 1e-9))  # the first row at or after it
            if index == len(rows):
                break
            self.foxglove.advance(float(times[index]), self.rows.outputs(rows[index].tolist()))
        self._latest = rows[-1].tolist()
        # paced, a block is one frame's steps (block_options); else at most one frame per interval
        if self._pacer is not None or clock.monotonic() - self._sent_at >= self.interval:
            self.publish()

    def publish(self) -> None:
        """Send the latest row as one frame: every component, the errors, the transforms and the scene."""
        row, self._latest = self._latest, None
        if row is None:
            return
        time = row[0]
        stamp = int(round(time * 1e9))
        self.server.broadcast_time(stamp)
        self._send(list(zip(self.components, self.rows.encode(row))), stamp)
        self._send(self.foxglove.snapshot(time, stamp, self.rows.outputs(row)), stamp)
        self._sent_at = clock.monotonic()

    def log(self, time: float, level: str, message: str) -> None:
        self.foxglove.log(lambda channel, stamp, data: self._send([(channel, data)], stamp), time, level, message)

    def link(self, stream: str, time: float, fields: dict[str, float]) -> None:
        """A live robot link's raw message, on the channel the trace gives it (advertised by ``open``; a stream
        it was not told of gets its channel now, which a viewer connected meanwhile may not get to see)."""
        entry = self.streams.get(stream)
        if entry is None:
            link = LiveStream(stream, list(fields))
            entry = self.streams[stream] = (link, self._advertise(link.spec))
        link, channel = entry
        values = [fields.get(key, float("nan")) for key in link.keys]
        if math.isfinite(sum(values)):
            self._send([(channel, link.encode(time, values))], int(round(time * 1e9)))

    # --- pacing -------------------------------------------------------------------------------

    def pace(self, time: float) -> None:
        """Return once the wall clock has reached simulated ``time`` (at ``speed``); the first call sets the origin."""
        pacer = self._pacer
        if pacer is None:
            return
        if not self._pacing:
            pacer.start(time)
            self._pacing = True
        pacer.wait_until(time)

    def delivery(self, step: float, interval: float, call_steps: int | None) -> tuple[float, int | None]:
        """Blocks at the frame rate at least; paced, one call into C per frame, its rows going to the trace
        and the view at once, then the pacer waits (in ``advanced``)."""
        interval = min(interval, self.interval)
        if self._pacer is None:
            return interval, call_steps
        self._frame_step = step
        return 0.0, max(1, math.ceil(self.speed * self.interval / step - 1e-9))

    def advanced(self, steps_done: int) -> None:
        if self._frame_step is not None:  # a block-filling engine: paced after each frame's call into C
            self.pace(steps_done * self._frame_step)

    def lag_note(self) -> str | None:
        """One line if the run could not keep the pace it was asked for (it steps slower), else None."""
        pacer = getattr(self, "_pacer", None)
        late = 0.0 if pacer is None else pacer.worst_overrun / self.speed  # the pacer's clock runs `speed` times faster
        if late < LAG_NOTE:
            return None
        pace = "real time" if self.speed == 1.0 else f"{self.speed:g}x real time"
        return (f"live: the run fell behind {pace} by up to {late:.1f} s (it steps slower than that here; "
                f"a smaller --live-speed keeps the view even)")

    def close(self) -> None:
        """Send the last point, then stop the server (viewers see the connection close)."""
        if getattr(self, "_latest", None) is not None:
            self.publish()
        for channel in self._channels:
            channel.close()
        self.server.stop()
        self.relay.close()


def start_foxglove_view(config: "Config", host: str, port: int, speed: float, warn: Any, wait: bool = False) -> FoxgloveView:
    """The CLI's ``--live``: check the options against the config, start the server (``FoxgloveViewError``:
    one line, nothing started); ``warn`` (a rich Console) gets the warning for a host other machines reach."""
    live = config.live_vehicles()
    if live and speed != 1.0:
        raise FoxgloveViewError(f"--live-speed {speed:g}: this config has a live robot (vehicle {', '.join(map(str, live))}), "
                            f"which runs in real time; leave --live-speed at 1")
    view = FoxgloveView(host, port, speed, wait=wait)
    if host not in LOOPBACK:
        warn.print(f"warning: --live-host {host}: the live view is open to every machine that reaches this one "
                   f"on port {view.port} (no authentication; anyone there sees the run)", highlight=False, soft_wrap=True)
    return view


def announce(view: FoxgloveView, trace: Any, config: "Config", out: Any) -> None:
    """Write the run's layout now (a viewer needs it before the run ends) and print where to look."""
    from orchestrator.trace.layout import write_run_layout

    written = write_run_layout(trace, config)
    layout = written.path
    if written.warning is not None:  # on stderr, as every warning of a run
        print(written.warning, file=sys.stderr, flush=True)
    pace = ("as fast as it runs" if not view.paced else "real time" if view.speed == 1.0
            else f"{view.speed:g} simulated seconds per second")
    out.print(f"live: {view.url}  ({pace}; Ctrl-C stops the run and keeps the trace)", highlight=False, soft_wrap=True)
    out.print(f"  open: {app_url(view.url)}  (Lichtblick: the same ?ds=foxglove-websocket&ds.url={view.url} "
              f"on its address, or Open connection > Foxglove WebSocket)", highlight=False, soft_wrap=True)
    if layout is not None:
        out.print(f"  layout: {layout}  (Layouts > Import from file)", highlight=False, soft_wrap=True)
    if view.wait:
        out.print("  waiting for a viewer to open the scene before the run starts ...", highlight=False)
