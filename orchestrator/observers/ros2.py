"""Publish a run to ROS 2 while it goes (config ``[ros2] publish = true``; docs/hil.md, "Your lab").

An observer of the run (orchestrator/observers/base.py): it is handed every point (engines stepping in
Python) or blocks of flat rows ``[t, outputs...]`` (the native engine) and publishes, for every vehicle,
simulated or live alike, a ``geometry_msgs/msg/PoseStamped`` on ``<topic_prefix>/<vehicle>/pose`` and
one ``tf2_msgs/msg/TFMessage`` on ``/tf`` with a transform ``frame_id`` -> ``<vehicle>`` per vehicle,
so RViz shows the whole mixed platoon. Through rmw_zenoh's convention the run is a ROS node
(``ros2 node list``, ``ros2 topic echo``); through zenoh-bridge-ros2dds' it reaches a DDS graph.

Messages are stamped with the wall-clock time they are published at (what RViz compares with its
clock) and sent at most ``rate`` times a second: a run that is not paced finishes far faster than a
viewer can draw, and is then published thinned out. A publishing failure never stops the run: the
first one is logged, the rest counted.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from orchestrator.scenario.wiring import vehicle_name

from .base import Observer

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config


class Ros2RunPublisher(Observer):
    """Publishes every vehicle's pose to ROS 2 (see the module docstring); ``finish`` leaves the graph."""

    wants_rows = True

    def __init__(self, config: Config, components: Sequence[tuple[str, Sequence[str]]],
                 clock: Callable[[], float] = time.time) -> None:
        self.table, self.clock = config.ros2, clock
        self.allow_insecure = config.hil.allow_insecure  # endpoints off this machine: TLS unless the lab says not
        self.connect_wait = config.hil.connect_timeout  # s a client waits for its router at the start
        self.columns: list[tuple[str, int, int, int]] = []  # (vehicle, column of x, of y, of heading) in a flat row
        column = 1
        vehicles = {vehicle_name(k) for k in range(1, config.platoon.count + 1)}
        for name, outputs in components:
            if name in vehicles:
                self.columns.append((name, column + outputs.index("x"), column + outputs.index("y"),
                                     column + outputs.index("heading")))
            column += len(outputs)
        self.published = 0
        self.failures = 0
        self._last = -float("inf")
        self._session: Any = None
        self._node: Any = None
        self._poses: dict[str, Any] = {}
        self._tf: Any = None

    def open(self) -> None:
        """Open the Zenoh session (``bridge.session``) and declare the node, its publishers and tokens."""
        from bridge.ros2.messages import POSE_STAMPED, TF_MESSAGE
        from bridge.ros2.node import RosGraph, RosNode
        from bridge.session import open_session, session_mode, zenoh_config

        table = self.table
        self._session = open_session(zenoh_config(table.connect, table.listen, table.zenoh_config,
                                                  mode=session_mode(table.connect, table.listen),
                                                  allow_insecure=self.allow_insecure, connect_wait=self.connect_wait),
                                     "[ros2] publish")
        graph = RosGraph(table.convention, table.domain, table.namespace, table.node or "platoon",
                         table.node_namespace or "/")
        self._node = RosNode(self._session, graph)
        for name, *_ in self.columns:
            self._poses[name] = self._node.publisher(f"{table.topic_prefix}/{name}/pose", POSE_STAMPED)
        self._tf = self._node.publisher("/tf", TF_MESSAGE)

    def _due(self) -> float | None:
        """The time to stamp the next messages with, if ``1/rate`` s passed since the last ones; else None."""
        now = self.clock()
        return now if now - self._last >= 1.0 / self.table.rate else None

    def rows(self, rows: Any, now: float | None = None) -> None:
        """Publish the newest of ``rows`` (flat rows, oldest first) if ``1/rate`` s passed since the last."""
        now = self._due() if now is None else now
        if now is None:
            return
        row = np.asarray(rows, dtype=float)
        if row.ndim == 2:
            if not len(row):
                return
            row = row[-1]
        self._last = now
        self._publish(row, now)

    def _publish(self, row: np.ndarray, stamp: float) -> None:
        from bridge.ros2.messages import POSE_STAMPED, encode_pose, encode_tf

        frame = self.table.frame_id
        try:
            children = []
            for name, x, y, heading in self.columns:
                values = (float(row[x]), float(row[y]), float(row[heading]))
                self._poses[name].put(encode_pose(POSE_STAMPED, stamp, *values, frame_id=frame))
                children.append((name, *values))
            self._tf.put(encode_tf(stamp, frame, children))
            self.published += 1
        except Exception:  # zenoh.ZError or a non-finite pose: the run's trace matters more than the view
            self.failures += 1

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        now = self._due()
        if now is not None:  # a row built only when it is due
            row = [t]
            for values in outputs:
                row.extend(values)
            self.rows(row, now)

    def block(self, rows: Any) -> None:
        self.rows(rows.array())

    def finish(self) -> None:
        self.close()

    def close(self) -> None:
        if self._node is not None:
            self._node.close()
            self._node = None
        if self._session is not None:
            self._session.close()
            self._session = None


def ros2_publisher(config: Config, components: Sequence[tuple[str, Sequence[str]]]) -> Ros2RunPublisher | None:
    """An open publisher when the config says ``[ros2] publish = true``, else None."""
    if not config.ros2.publish:
        return None
    from bridge.session import SessionError, session_mode

    from fmus.errors import ComponentError

    publisher = Ros2RunPublisher(config, components)
    try:
        publisher.open()
    except SessionError as error:  # the run fails cleanly, its trace finalized, the message naming the endpoint
        publisher.close()
        text = str(error) if str(error).startswith("[ros2] publish") else f"[ros2] publish: {error}"
        table = config.ros2
        if "cannot open" in text and session_mode(table.connect, table.listen) == "client" and not table.zenoh_config:
            text += (f" (client mode: the ROS 2 graph's router at {list(table.connect)} did not answer within "
                     f"hil.connect_timeout {config.hil.connect_timeout:g} s: is it running?)")
        raise ComponentError("ros2", 0.0, text) from None
    return publisher
