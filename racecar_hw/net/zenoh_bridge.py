"""The Zenoh bridge: the daemon's topics as ROS 2 topics in rmw_zenoh's format (:mod:`racecar_hw.net.rmw`).

A thin I/O shell around the codec, with one Zenoh session:

* **Out** (``/scan``, ``/odom``, ...). The bus callback only queues ``(row, message, wall ns)`` in
  an :class:`~racecar_hw.runtime.outbox.Outbox` (bounded, the oldest entry goes when it is full,
  counted), whose sender thread serializes with the recorder's serializers and puts the CDR
  bytes with the 33-byte attachment. Like the Foxglove server's, it runs in batches in the gap
  after a scan's motor command (:meth:`ZenohBridge.control_idle`), so its GIL time does not land
  on the next scan's way to the motor; the messages remote navigation code waits for (the scan,
  queued in that gap, odometry and ``/tf``) wake it at once. A row nobody subscribes to (Zenoh's matching
  status, kept up to date by a listener) is not even queued: no serialization while nobody
  listens. Latched rows (``/tf_static``: ROS 2 TRANSIENT_LOCAL) use Zenoh's advanced publisher
  with a cache of ``depth`` samples, so a subscriber that starts later still gets them; they are
  always queued.
* **In** (mux inputs, locks, e-stop, ``/cmd_vel``): :mod:`racecar_hw.net.zenoh_inputs` checks each
  sample's rmw_zenoh attachment in Zenoh's threads and gives the payload to the network
  :class:`~racecar_hw.net.inbox.Inbox` (shared with every network surface), which decodes it,
  checks every number is finite and keeps the latest message per input for the event loop (e-stops
  at once and first, with their origin: only an operator releases what an operator latched,
  :mod:`mux.estop`). In the loop it is published on the bus like any local input. Anything else is
  dropped and counted, samples of the wrong type on an input topic too, and every sample on a mux
  input closed to the network (``network: false``: ``safety`` and ``teleop`` by default).
* **Services** (the read-only parameter services, :mod:`racecar_hw.net.parameters`), answered by
  :mod:`racecar_hw.net.zenoh_services` on rmw_zenoh's service keys.
* **Graph.** A liveliness token for the node and one per publisher, subscriber and service server
  (``SS``), all declared through :class:`~racecar_hw.net.zenoh_node.ZenohNode` (as the client's),
  so ``ros2 node list``, ``ros2 topic list`` and ``ros2 node info`` on a machine running rmw_zenoh
  show the car. ``zenoh.ros_distro: humble`` writes ``TypeHashNotSupported`` where
  Jazzy and later write the RIHS01 hash (keys and tokens): the two never meet on a key.

Nothing here runs on the control path except the enqueue; a put that blocks (10 ms was seen with a
slow subscriber) holds up only the publisher thread.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from racecar_hw.base.bus import Bus
from racecar_hw.base.messages import Message
from racecar_hw.net import rmw
from racecar_hw.net.bridge import Bridge
from racecar_hw.net.inbox import Inbox, all_finite
from racecar_hw.net.parameters import ParameterService
from racecar_hw.net.topics import Direction, Reliability, Topic
from racecar_hw.net.zenoh_config import ZenohParams, config_for
from racecar_hw.net.zenoh_inputs import ORIGIN, ZenohInputs
from racecar_hw.net.zenoh_node import ZenohNode
from racecar_hw.net.zenoh_security import open_error
from racecar_hw.net.zenoh_services import ZenohServices
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

__all__ = ["ORIGIN", "BridgeStats", "ZenohBridge", "all_finite"]

#: The sporadic heartbeat of a RELIABLE + TRANSIENT_LOCAL publisher (s), as rmw_zenoh sets it.
HEARTBEAT_S = 0.5


@dataclass
class BridgeStats:
    """Counters of the bridge (read from any thread; written under the bridge's lock)."""

    published: int = 0       #: samples put
    skipped: int = 0         #: outgoing messages not queued: nobody subscribed
    publish_errors: int = 0  #: serialization or put failures
    received: int = 0        #: incoming samples handed to the bus
    no_attachment: int = 0   #: incoming samples without rmw_zenoh's attachment (dropped)
    malformed: int = 0       #: incoming samples whose payload did not decode (dropped)
    old_attachment: int = 0  #: incoming samples with rmw_zenoh 0.2.0-0.2.3's string-keyed attachment
    non_finite: int = 0      #: incoming messages with a NaN or infinite number (dropped)
    service_calls: int = 0   #: service requests answered
    service_errors: int = 0  #: service requests refused (no attachment, malformed, too big) or failed
    set_calls: int = 0       #: set_parameters calls answered (read-only: refused in the answer)
    wrong_type: int = 0      #: incoming samples on an input topic with another type or type hash
    closed: int = 0          #: incoming samples on a mux input closed to the network (refused)


class _Out:
    """One outgoing row: its Zenoh publisher, its attachments, and whether anyone listens."""

    def __init__(self, row: Topic, publisher: Any, stamps: rmw.SampleStamps, latched: bool) -> None:
        self.row = row
        self.publisher = publisher
        self.stamps = stamps
        self.latched = latched
        self.matching = latched
        self.listener: Any = None


class ZenohBridge(Bridge):
    """The bus's network rows on Zenoh. Build, ``open()`` (blocking, from any thread), ``close()``.

    ``on_input(bus_topic)`` is called in the event loop after an incoming message was published on
    the bus (the daemon uses it to send a fresh remote command to the VESC at once). Messages on
    ``urgent`` bus topics wake the publisher thread at once (the daemon names the scan, odometry and
    ``/tf``: remote navigation code waits for them); the rest go out in batches. Samples of the
    wrong type on an input topic are noted in ``refusals`` (the daemon passes its own).

    ``early`` bus topics (the daemon names the scan) are not taken from the bus: the daemon hands
    them over with :meth:`send_early` right after the scan's motor write, before its bookkeeping,
    the obstacle memory's update, the scan summaries and the recorder, which a bus subscription
    made after theirs would wait for. They wake the publisher thread at once.

    Incoming messages go to ``inbox`` (the daemon's, shared with the other network surfaces,
    which hands them over as it is told); without one the bridge has its own, which publishes
    them on the bus and then calls ``on_input``.
    """

    WIRE = "zenoh"

    def __init__(self, bus: Bus, params: ZenohParams, rows: list[Topic],
                 on_input: Callable[[str], None] | None = None,
                 urgent: frozenset[str] | set[str] = frozenset(),
                 refusals: Refusals | None = None,
                 parameters: ParameterService | None = None,
                 inbox: Inbox | None = None,
                 early: frozenset[str] | set[str] = frozenset()) -> None:
        self.bus = bus
        self.params = params
        self.rows = rows
        self.on_input = on_input
        self._own_inbox = inbox is None
        self.inbox = inbox if inbox is not None else Inbox(
            [r.bus for r in rows if r.direction is Direction.IN], self._deliver)
        self.domain_id = params.resolved_domain_id()
        self.namespace = rmw.check_namespace(params.namespace)
        self.names = rmw.NodeNames(self.domain_id, self.namespace, params.node_name, params.ros_distro)
        self.node: ZenohNode | None = None
        self.stats = BridgeStats()
        self.refusals = refusals if refusals is not None else Refusals()
        self.session: Any = None
        self.zid = ""
        self._lock = threading.Lock()
        self._init_outgoing("zenoh-publisher", params.queue_size, urgent, early)
        self._types = ros2_types()
        self._outs: list[_Out] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self.inputs = ZenohInputs(self.inbox, self.stats, self._lock, self.refusals, self.ros_name)
        #: answers the parameter services (None: no services)
        self.services = ZenohServices(parameters, self.stats, self._lock) if parameters is not None else None

    # --- names --------------------------------------------------------------------------------

    def key(self, row: Topic) -> str:
        """The Zenoh key of a row's samples."""
        return self.names.key(self.ros_name(row), row.msgtype.ROS_TYPE)

    # --- life cycle ---------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """Whether the session is open."""
        return self.session is not None

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        """Open the session, declare every row and token, start the publisher thread.

        Raises a one-line :class:`ConfigError` naming the key to fix when Zenoh cannot start: the
        ``zenoh.listen`` entry whose port is already in use (rmw_zenohd, say), ``zenoh.connect``
        for a client that reached no router, ``zenoh.auth`` or ``zenoh.tls`` keys when Zenoh
        refuses those (:func:`~racecar_hw.net.zenoh_security.open_error`).
        """
        import zenoh  # noqa: PLC0415 - the Rust extension loads only when the bridge runs
        import zenoh.ext  # noqa: PLC0415

        self._loop = loop
        self.inbox.bind(loop)
        p = self.params
        try:
            self.session = zenoh.open(config_for(p))
        except zenoh.ZError as err:
            raise open_error(err, p.mode, p.listen, p.connect, has_auth=bool(p.auth.user)) from None
        self.node = node = ZenohNode(self.session, self.names)
        self.zid = self.names.zid
        for row in self.rows:
            if row.direction is Direction.OUT:
                self._declare_out(row, node, zenoh)
            else:
                self.inputs.declare(row, node, zenoh)
        if self.services is not None:
            self.services.declare(node)
        self._take_rows(self._outs)
        self.inputs.start()
        log.info("zenoh bridge up: %s mode, session %s, domain %d, namespace %r, listen %s, "
                 "connect %s; %d topics out, %d in, %d services; peers: rmw_zenoh %s", p.mode, self.zid,
                 self.domain_id, self.namespace or "/", p.listen, p.connect, len(self._outs),
                 sum(row.direction is not Direction.OUT for row in self.rows),
                 self.services.declared if self.services is not None else 0,
                 "Humble (TypeHashNotSupported)" if p.ros_distro == "humble" else "Jazzy and later")

    def _declare_out(self, row: Topic, node: ZenohNode, zenoh: Any) -> None:
        reliable = row.qos.reliability is Reliability.RELIABLE
        options = dict(congestion_control=zenoh.CongestionControl.DROP,
                       reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT)
        topic = self.ros_name(row)
        if row.qos.latched:
            entity = node.announce(node.names.endpoint(rmw.PUBLISHER, topic, row.msgtype.ROS_TYPE, row.qos))
            miss = zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S) \
                if reliable else None
            publisher = node.track(zenoh.ext.declare_advanced_publisher(
                self.session, self.key(row), cache=zenoh.ext.CacheConfig(row.qos.depth),
                publisher_detection=True, sample_miss_detection=miss, **options))
            out = _Out(row, publisher, rmw.SampleStamps(entity.gid()), latched=True)
        else:
            publisher, stamps = node.publisher(topic, row.msgtype, row.qos, **options)
            out = _Out(row, publisher, stamps, latched=False)
            out.matching = bool(publisher.matching_status.matching)

            def on_matching(status: Any, out: _Out = out) -> None:
                out.matching = bool(status.matching)

            # called in Zenoh's own thread (not ``indirect``, which gives every callback a Python
            # thread of its own): it only sets a flag, when a subscriber comes or goes
            out.listener = node.track(publisher.declare_matching_listener(
                zenoh.handlers.Callback(on_matching, indirect=False)))
        self._outs.append(out)

    def close(self) -> None:
        """Undeclare everything, stop the publisher thread, close the session (safe twice)."""
        self.inputs.stop()
        if self._own_inbox:
            self.inbox.close()
        self._stop_outgoing()
        session, self.session = self.session, None
        if session is None:
            return
        if self.node is not None:
            self.node.close()
        self._outs.clear()
        try:
            session.close()
        except Exception as err:  # noqa: BLE001 - shutting down: report and go on
            log.warning("zenoh session close failed: %r", err)
        s = self.stats
        log.info("zenoh bridge closed: %d published (%d dropped, queue full), %d skipped (no subscriber); "
                 "%d received, %d without attachment, %d malformed, %d with an old rmw_zenoh's attachment, "
                 "%d non-finite, %d of a wrong type, %d on inputs closed to the network; %d service calls "
                 "answered, %d refused", s.published, self.outbox.dropped, s.skipped, s.received,
                 s.no_attachment, s.malformed, s.old_attachment, s.non_finite, s.wrong_type, s.closed,
                 s.service_calls, s.service_errors)

    # --- out: the publisher thread -----------------------------------------------------------

    def _write(self, out: _Out, msg: Message, stamp: int) -> None:
        """In the publisher thread: serialize ``msg`` and put it with rmw_zenoh's attachment."""
        out.publisher.put(self._types.serialize(msg), attachment=out.stamps.next(stamp))
