"""The DDS interface: the daemon's topics as ROS 2 topics on DDS, ROS 2's default middleware.

The same topic table as the Zenoh bridge (:mod:`racecar_hw.net.topics`: profile, namespace, remaps,
``/cmd_vel``), on a thin Cyclone DDS shell beside it:

* **Names and types** as ROS 2's DDS middlewares use them: ``/scan`` is the DDS topic ``rt/scan``
  of type ``sensor_msgs::msg::dds_::LaserScan_`` (:mod:`racecar_hw.net.dds_types`, generated from
  the typestore and sending the CDR bytes :mod:`racecar_hw.rosmsg` makes, as the recorder and the
  Zenoh bridge do). Each writer and reader has the row's QoS as ROS 2 nodes declare it (best
  effort depth 5 for ``/scan``, transient local depth 1 for ``/tf_static`` and the mux's active
  source, reliable depth 10 otherwise) and ``typehash=RIHS01_...;`` in its USER_DATA (Iron+).
* **Out**: exactly as the Zenoh bridge: the bus callback only queues ``(row, message, wall ns)`` in
  an :class:`~racecar_hw.runtime.outbox.Outbox` (bounded, drop-oldest), and nothing at all while no
  reader matches the writer (Cyclone's publication-matched status, kept by a listener); the
  sender thread serializes and writes. Latched rows are always queued, and Cyclone's writer
  history (transient local) gives late joiners the last ``depth`` samples.
* **In**: the same hand-over as the Zenoh bridge's, the daemon's shared
  :class:`~racecar_hw.net.inbox.Inbox` (decoded and checked there: well-formed CDR, every number
  finite; one hand-over per input per control tick, the newest; e-stops in order and first). A
  command row's reader keeps only its newest sample (KEEP_LAST 1, in Cyclone's C code, without the
  GIL) and a thread per row takes it at most once per control period (``period_s``), so a flood
  of ``/cmd_vel`` costs no Python work per message. The e-stop and its release are never
  coalesced: Cyclone calls their readers' listeners for every sample, in order, and each goes to
  the inbox's e-stop queue. On a
  non-loopback interface without ``accept_unauthenticated_commands`` every command is refused and
  counted (:class:`~racecar_hw.runtime.refusals.Refusals`, surface ``dds``).
* **Graph**: ``ros_discovery_info`` names the participant's node (``/<namespace>/<node_name>``) and
  its readers' and writers' GIDs, so ``ros2 node list`` and ``ros2 topic info -v`` show the car.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import Message
from racecar_hw.net import dds_graph, rmw
from racecar_hw.net.bridge import Bridge
from racecar_hw.net.dds_config import MAX_PARTICIPANT_INDEX, DdsParams, cyclone_xml, participant_ports
from racecar_hw.net.dds_inbound import DdsReceiver
from racecar_hw.net.dds_types import TypeFactory, raw_sample, ros2_factory
from racecar_hw.net.inbox import Inbox
from racecar_hw.net.ports import port_taken
from racecar_hw.net.topics import Direction, Qos, Reliability, Topic
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: How long a reliable writer may block when its history is full (ns); never reached with KEEP_LAST.
MAX_BLOCKING_NS = 100_000_000


@dataclass
class DdsStats:
    """Counters of the DDS interface (read from any thread)."""

    published: int = 0       #: samples written
    skipped: int = 0         #: outgoing messages not queued: no reader matched
    publish_errors: int = 0  #: serialization or write failures
    received: int = 0        #: incoming samples taken in by the inbox
    malformed: int = 0       #: incoming samples whose payload did not decode (dropped)
    non_finite: int = 0      #: incoming messages with a NaN or infinite number (dropped)
    #: incoming commands refused: unauthenticated interface, not an input, a mux input closed to
    #: the network (``mux.inputs[N].network: false``)
    refused: int = 0


class _Out:
    """One outgoing row: its writer, its topic type, and whether any reader matches."""

    def __init__(self, row: Topic, writer: Any, topic_type: Any, latched: bool) -> None:
        self.row = row
        self.writer = writer
        self.topic_type = topic_type
        self.latched = latched
        self.matching = latched


def qos_of(qos: Qos, user_data: bytes = b"") -> Any:
    """Cyclone QoS for a row's :class:`~racecar_hw.net.topics.Qos` (KEEP_LAST ``depth``)."""
    from cyclonedds.qos import Policy  # noqa: PLC0415
    from cyclonedds.qos import Qos as CQos  # noqa: PLC0415

    policies = [
        Policy.Reliability.Reliable(max_blocking_time=MAX_BLOCKING_NS)
        if qos.reliability is Reliability.RELIABLE else Policy.Reliability.BestEffort,
        Policy.Durability.TransientLocal if qos.latched else Policy.Durability.Volatile,
        Policy.History.KeepLast(qos.depth),
    ]
    if user_data:
        policies.append(Policy.Userdata(data=user_data))
    return CQos(*policies)


class DdsBridge(Bridge):
    """The bus's network rows on DDS. Build, ``open()`` (blocking, from any thread), ``close()``.

    ``namespace``, ``node_name``: the zenoh section's naming: one table, two wires.
    Incoming messages go to ``inbox`` (the daemon's, shared with the Zenoh bridge, which knows the
    e-stop topics and hands over in the event loop). Without one the bridge makes its own, whose
    hand-over publishes on the bus then calls ``on_input(bus_topic)``, with ``estop_topic`` and
    ``release_topic`` going to ``on_estop(topic, msg, "dds")`` instead. Messages on ``urgent`` bus
    topics wake the publisher thread at once. ``early`` bus topics (the daemon names the scan) are
    not taken from the bus: the daemon hands them over with :meth:`send_early` right after the
    scan's motor write, before its bookkeeping (as to the Zenoh bridge); they wake the thread at once.
    """

    WIRE = "dds"

    def __init__(self, bus: Bus, params: DdsParams, rows: list[Topic], *, namespace: str = "",
                 node_name: str = "racecar_hw", on_input: Callable[[str], None] | None = None,
                 urgent: frozenset[str] | set[str] = frozenset(),
                 refusals: Refusals | None = None,
                 inbox: Inbox | None = None,
                 on_estop: Callable[[str, Message, str], None] | None = None,
                 estop_topic: str | None = None, release_topic: str | None = None,
                 period_s: float = 0.02, early: frozenset[str] | set[str] = frozenset()) -> None:
        self.bus = bus
        self.params = params
        self.rows = rows
        self.on_input = on_input
        self.namespace = rmw.check_namespace(namespace)
        self.node_name = node_name
        self.domain_id = params.resolved_domain_id()
        self.refusals = refusals if refusals is not None else Refusals()
        self._own_inbox = inbox is None
        self.inbox = inbox if inbox is not None else Inbox(
            [r.bus for r in rows if r.direction is Direction.IN], self._deliver, period_s=period_s,
            estop_topic=estop_topic, release_topic=release_topic, on_estop=on_estop,
            refusals=self.refusals)
        self.period_s = self.inbox.period_ns / 1e9
        self.stats = DdsStats()
        #: the readers' samples into the inbox (a thread per command row)
        self.receiver = DdsReceiver(self.inbox, self.stats, self.refusals,
                                    accepts_commands=params.accepts_commands, period_s=self.period_s)
        self._init_outgoing("dds-publisher", params.queue_size, urgent, early)
        self.factory: TypeFactory = ros2_factory()
        self._types = ros2_types()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._domain: Any = None
        self.participant: Any = None
        self._outs: list[_Out] = []
        self._readers: list[Any] = []
        self._info_writer: Any = None
        self._open = False

    @property
    def is_open(self) -> bool:
        """Whether the participant is up."""
        return self._open

    # --- life cycle ---------------------------------------------------------------------------

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        """Join the domain, create every writer and reader, publish the node, start the thread.

        Raises a one-line :class:`ConfigError` naming ``dds.interface`` when Cyclone cannot start
        on the configured interface.
        """
        from cyclonedds.core import DDSException, Listener  # noqa: PLC0415 - loads the C library
        from cyclonedds.domain import Domain, DomainParticipant  # noqa: PLC0415
        from cyclonedds.pub import DataWriter  # noqa: PLC0415
        from cyclonedds.sub import DataReader  # noqa: PLC0415
        from cyclonedds.topic import Topic as DdsTopic  # noqa: PLC0415

        self._loop = loop
        self.inbox.bind(loop)
        p = self.params
        try:
            self._domain = Domain(self.domain_id, cyclone_xml(p))
            self.participant = DomainParticipant(self.domain_id)
        except DDSException as err:
            taken = sum(port_taken(p.interface, port, "udp") for port in participant_ports(self.domain_id))
            if taken == MAX_PARTICIPANT_INDEX + 1:
                raise ConfigError("dds.domain_id", f"no free DDS participant index in domain "
                                  f"{self.domain_id}: every discovery port of indices 0-"
                                  f"{MAX_PARTICIPANT_INDEX} on {p.interface} is held (that many DDS "
                                  "participants, ROS 2 processes among them, run on this computer); "
                                  "stop some, or use another ROS_DOMAIN_ID") from None
            raise ConfigError("dds.interface", f"Cyclone DDS could not start on {p.interface!r} "
                                               f"(domain {self.domain_id}): {err}") from None
        self._open = True
        hashes = p.ros_distro != "humble"
        writer_gids, reader_gids = [], []
        for row in self.rows:
            ros_type = row.msgtype.ROS_TYPE
            topic_type = self.factory.topic_type(ros_type)
            topic = DdsTopic(self.participant, dds_graph.topic_name(self.ros_name(row)), topic_type)
            qos = qos_of(row.qos, dds_graph.user_data(rmw.type_hash(ros_type) if hashes else None))
            if row.direction is Direction.OUT:
                out = _Out(row, None, topic_type, latched=row.qos.latched)

                def matched(writer: Any, status: Any, out: _Out = out) -> None:
                    out.matching = out.latched or status.current_count > 0

                out.writer = DataWriter(self.participant, topic, qos,
                                        listener=Listener(on_publication_matched=matched))
                self._outs.append(out)
                writer_gids.append(out.writer.guid.bytes)
            elif row.bus in self.inbox.stop_topics or row.qos.latched or row.refused:
                # every e-stop message, in order, from Cyclone's thread: never coalesced (and every
                # sample of a row closed to the network, each refused and counted)
                reader = DataReader(self.participant, topic, qos,
                                    listener=Listener(on_data_available=self._receiver(row)))
                self._readers.append(reader)
                reader_gids.append(reader.guid.bytes)
            else:
                # a command: the reader keeps only the newest sample (in C), taken at most once
                # per control tick (DdsReceiver.gated)
                newest = qos_of(dataclasses.replace(row.qos, depth=1), dds_graph.user_data(
                    rmw.type_hash(ros_type) if hashes else None))
                gated = self.receiver.gated(row, self.ros_name(row))
                reader = DataReader(self.participant, topic, newest,
                                    listener=Listener(on_data_available=gated))
                self._readers.append(reader)
                reader_gids.append(reader.guid.bytes)
        self._publish_graph(reader_gids, writer_gids, DdsTopic, DataWriter)
        self._take_rows(self._outs)
        self.receiver.start()
        log.info("dds interface up: domain %d, interface %s, peers %s, node %s/%s; %d topics out, %d in%s",
                 self.domain_id, p.interface, ",".join(p.peers), self.namespace, self.node_name,
                 len(self._outs), len(self._readers), "" if p.accepts_commands else " (commands refused)")
        notice = p.start_notice()
        if notice:
            log.warning("%s", notice)

    def _publish_graph(self, readers: list[bytes], writers: list[bytes], topic_cls: Any,
                       writer_cls: Any) -> None:
        """Publish ``ros_discovery_info``: this participant's one node and its endpoints."""
        factory = TypeFactory(dds_graph.graph_store(self.params.gid_size))
        topic_type = factory.topic_type(dds_graph.DISCOVERY_TYPE)
        topic = topic_cls(self.participant, dds_graph.DISCOVERY_TOPIC, topic_type)
        from racecar_hw.net.topics import LATCHED  # noqa: PLC0415

        self._info_writer = writer_cls(self.participant, topic, qos_of(LATCHED))
        node = dds_graph.NodeInfo(self.namespace or "/", self.node_name, readers, writers)
        gid = bytes(16) if self.params.null_participant_gid else self.participant.guid.bytes
        info = dds_graph.ParticipantInfo(gid, [node])
        cdr = dds_graph.encode_participant_info(info, self.params.gid_size)
        log.debug("dds: ros_discovery_info %s", info)
        self._info_writer.write(raw_sample(topic_type, cdr))

    def close(self) -> None:
        """Stop the publisher thread, delete every entity, leave the domain (safe twice)."""
        self._stop_outgoing()
        if self._own_inbox:
            self.inbox.close()
        self.receiver.stop()
        if not self._open:
            return
        self._open = False
        participant, self.participant = self.participant, None
        self._outs.clear()
        self._readers.clear()
        self._info_writer = None
        for entity in (participant, self._domain):
            if entity is None:
                continue
            try:
                entity.__del__()
            except Exception:  # noqa: BLE001 - shutting down: report and go on
                log.debug("dds: deleting %r failed", entity, exc_info=True)
        self._domain = None
        s = self.stats
        log.info("dds interface closed: %d published (%d dropped, queue full), %d skipped (no reader); "
                 "%d received, %d malformed, %d non-finite, %d refused", s.published, self.outbox.dropped,
                 s.skipped, s.received, s.malformed, s.non_finite, s.refused)

    # --- out: the publisher thread -----------------------------------------------------------

    def _write(self, out: _Out, msg: Message, stamp: int) -> None:
        """In the publisher thread: serialize ``msg`` and write it with its source timestamp."""
        out.writer.write(raw_sample(out.topic_type, self._types.serialize(msg)), timestamp=stamp)

    # --- in: Cyclone's receive thread (see DdsReceiver), then the event loop (Bridge._deliver) --

    def _receiver(self, row: Topic) -> Callable[[Any], None]:
        """What takes ``row``'s samples from a reader into the inbox."""
        return self.receiver.receiver(row, self.ros_name(row))
