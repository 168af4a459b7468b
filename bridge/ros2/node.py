"""A minimal ROS 2 node on a Zenoh session: publishers and subscriptions on ROS topics, under either
convention (``rmw_zenoh``: full keys, attachments, liveliness tokens so that ``ros2 node list`` and
``ros2 topic list`` see it; ``bridge_dds``: bare keys behind a zenoh-bridge-ros2dds). The session is
the caller's (opened through ``bridge.session``); the node declares on it and undeclares in ``close``.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from typing import Any, Callable, Literal

import zenoh

from ..session import undeclare_all
from . import bridge_dds, rmw_zenoh

Convention = Literal["rmw_zenoh", "bridge_dds"]
CONVENTIONS: tuple[str, ...] = ("rmw_zenoh", "bridge_dds")


@dataclass(frozen=True)
class RosGraph:
    """Which ROS 2 graph to meet, and as which node."""

    convention: Convention = "rmw_zenoh"
    domain: int = 0  # ROS_DOMAIN_ID (rmw_zenoh: first key segment)
    namespace: str = ""  # zenoh-bridge-ros2dds ``namespace`` (bridge_dds only)
    node: str = "platoon"  # our node's name (rmw_zenoh's graph)
    node_namespace: str = "/"

    def key(self, topic: str, typename: str) -> str:
        """The Zenoh key of ``topic`` carrying ``typename`` under this graph's convention."""
        if self.convention == "rmw_zenoh":
            return rmw_zenoh.topic_key(self.domain, topic, typename)
        return bridge_dds.topic_key(self.namespace, topic)


class RosPublisher:
    """Publishes already-encoded messages of one type on one topic; adds rmw_zenoh's attachment."""

    def __init__(self, publisher: Any, gid: bytes | None) -> None:
        self._publisher, self._gid = publisher, gid
        self.sequence = 0

    def put(self, payload: bytes) -> None:
        self.sequence += 1
        if self._gid is None:
            self._publisher.put(payload)
        else:
            self._publisher.put(payload, attachment=rmw_zenoh.attachment(self.sequence, self._gid, time.time_ns()))

    def undeclare(self) -> None:
        self._publisher.undeclare()


class RosNode:
    """One ROS 2 node (see the module docstring); ``close`` releases every token, publisher and subscriber."""

    def __init__(self, session: zenoh.Session, graph: RosGraph) -> None:
        self.session, self.graph = session, graph
        self._resources: list[Any] = []
        self._ids = itertools.count()
        self.zid = str(session.zid())
        self.node_id = next(self._ids)
        self.tokens: list[str] = []
        if graph.convention == "rmw_zenoh":
            self._token(rmw_zenoh.node_token(graph.domain, self.zid, self.node_id, graph.node_namespace, graph.node))

    def _token(self, key: str) -> None:
        self._resources.append(self.session.liveliness().declare_token(key))
        self.tokens.append(key)

    def _entity(self, kind: str, topic: str, typename: str, reliability: int, depth: int) -> str | None:
        graph = self.graph
        if graph.convention != "rmw_zenoh":
            return None
        token = rmw_zenoh.entity_token(graph.domain, self.zid, self.node_id, next(self._ids), kind, graph.node_namespace,
                                       graph.node, topic, typename, rmw_zenoh.qos_text(reliability, depth))
        self._token(token)
        return token

    def publisher(self, topic: str, typename: str, reliability: int = rmw_zenoh.RELIABLE, depth: int = 10,
                  express: bool = True) -> RosPublisher:
        """A publisher of ``typename`` on ``topic`` (fully qualified, e.g. ``/m3pi_3/cmd_vel``)."""
        publisher = self.session.declare_publisher(self.graph.key(topic, typename), express=express,
                                                   congestion_control=zenoh.CongestionControl.DROP)
        self._resources.append(publisher)
        token = self._entity(rmw_zenoh.PUBLISHER, topic, typename, reliability, depth)
        return RosPublisher(publisher, None if token is None else rmw_zenoh.gid(token))

    def subscriber(self, topic: str, typename: str, callback: Callable[[zenoh.Sample], None],
                   reliability: int = rmw_zenoh.BEST_EFFORT, depth: int = 1) -> str:
        """Calls ``callback(sample)`` on Zenoh's thread for each message on ``topic``; returns the key."""
        key = self.graph.key(topic, typename)
        self._resources.append(self.session.declare_subscriber(key, callback))
        self._entity(rmw_zenoh.SUBSCRIPTION, topic, typename, reliability, depth)
        return key

    def close(self) -> None:
        """Undeclare every token, publisher and subscriber of the node (the session stays open)."""
        undeclare_all(self._resources)

    undeclare = close  # a node sits among the resources a LiveVehicle undeclares when it closes
