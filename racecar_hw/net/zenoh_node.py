"""One ROS 2 node on an open Zenoh session, as rmw_zenoh makes it: the I/O shell of
:class:`~racecar_hw.net.rmw.NodeNames`, shared by the daemon's bridge and the Python client.

It declares what a node declares (publishers, subscribers, queryables, the liveliness tokens that
make ``ros2 node list`` / ``ros2 topic list`` show them) and undeclares all of it on
:meth:`ZenohNode.close`. The session belongs to the caller: the node never closes it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

from racecar_hw.base.messages import Message
from racecar_hw.net import rmw
from racecar_hw.net.topics import Qos


class ZenohNode:
    """The node ``names`` on ``session``; its own liveliness token is declared at once."""

    def __init__(self, session: Any, names: rmw.NodeNames) -> None:
        names.zid = str(session.zid())
        self.session = session
        self.names = names
        self._declared: list[Any] = []
        self.announce(names.node())

    def announce(self, entity: rmw.Entity) -> rmw.Entity:
        """Declare ``entity``'s liveliness token (undeclared on :meth:`close`)."""
        self._declared.append(self.session.liveliness().declare_token(entity.token()))
        return entity

    def track(self, declared: Any) -> Any:
        """Undeclare ``declared`` (a Zenoh publisher, subscriber, queryable, listener) on :meth:`close`."""
        self._declared.append(declared)
        return declared

    def publisher(self, topic: str, msgtype: type[Message], qos: Qos,
                  **options: Any) -> tuple[Any, rmw.SampleStamps]:
        """Declare a publisher of ``msgtype`` on ``topic`` (a full ROS name) with its token; returns
        it with its :class:`~racecar_hw.net.rmw.SampleStamps` (put every sample with
        ``attachment=stamps.next(wall_ns)``). ``options`` go to Zenoh's ``declare_publisher``."""
        entity = self.announce(self.names.endpoint(rmw.PUBLISHER, topic, msgtype.ROS_TYPE, qos))
        publisher = self.track(self.session.declare_publisher(self.names.key(topic, msgtype.ROS_TYPE),
                                                              **options))
        return publisher, rmw.SampleStamps(entity.gid())

    def subscriber(self, topic: str, msgtype: type[Message], qos: Qos, handler: Any) -> Any:
        """Declare a subscriber of ``msgtype`` on ``topic`` calling ``handler`` (or a Zenoh
        channel), with its token."""
        sub = self.track(self.session.declare_subscriber(self.names.key(topic, msgtype.ROS_TYPE), handler))
        self.announce(self.names.endpoint(rmw.SUBSCRIPTION, topic, msgtype.ROS_TYPE, qos))
        return sub

    def service(self, name: str, srv_type: str, qos: Qos, answer: Callable[[Any], None]) -> str:
        """Declare a service server (a complete queryable on the service's key, as
        ``rmw_service_data.cpp`` does) with its token; returns the key replies go on."""
        key = self.names.key(name, srv_type)
        self.track(self.session.declare_queryable(key, answer, complete=True))
        self.announce(self.names.endpoint(rmw.SERVICE, name, srv_type, qos))
        return key

    def close(self) -> None:
        """Undeclare everything declared through this node (safe twice; errors ignored: closing
        the session undeclares what is left)."""
        declared, self._declared = self._declared, []
        for entity in reversed(declared):
            with contextlib.suppress(Exception):
                entity.undeclare()
