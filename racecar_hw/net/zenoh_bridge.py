"""The Zenoh bridge: the daemon's topics as ROS 2 topics in rmw_zenoh's format (:mod:`racecar_hw.net.rmw`).

A thin I/O shell around the codec, with one Zenoh session:

* **Out** (``/scan``, ``/odom``, ...). The bus callback only queues ``(row, message, wall ns)`` in
  an :class:`~racecar_hw.net.outbox.Outbox` (bounded, the oldest entry goes when it is full,
  counted), whose sender thread serializes with the recorder's serializers and puts the CDR
  bytes with the 33-byte attachment. Like the Foxglove server's, it runs in batches in the gap
  after a scan's motor command (:meth:`ZenohBridge.control_idle`), so its GIL time does not land
  on the next scan's way to the motor; the messages remote navigation code waits for (the scan,
  queued in that gap, odometry and ``/tf``) wake it at once. A row nobody subscribes to (Zenoh's matching
  status, kept up to date by a listener) is not even queued: no serialization while nobody
  listens. Latched rows (``/tf_static``: ROS 2 TRANSIENT_LOCAL) use Zenoh's advanced publisher
  with a cache of ``depth`` samples, so a subscriber that starts later still gets them; they are
  always queued.
* **In** (mux inputs, locks, e-stop, ``/cmd_vel``). Zenoh calls back in its own threads; there the
  sample's rmw_zenoh attachment is checked and the payload given to the network
  :class:`~racecar_hw.net.inbox.Inbox` (shared with every network surface), which decodes it,
  checks every number is finite and keeps the latest message per input for the event loop: at
  most one hand-over per input per control tick whatever the arrival rate, e-stops at once and
  first (with their origin, so the mux knows they came from a network session: only an operator
  releases what an operator latched, :mod:`mux.estop`). In the loop it is published on the bus
  like any local input: the mux applies its timeouts. Anything else is dropped and counted.
  A second subscriber per input topic matches the topic whatever its type: a sample of another
  type (``AckermannDrive`` where ``AckermannDriveStamped`` is taken, which rmw_zenoh puts on a
  different key, so the input never sees it) is counted in ``wrong_type`` and in the daemon's
  :class:`~racecar_hw.runtime.refusals.Refusals` (rate-limited log lines naming the type taken).
* **Services** (the read-only parameter services, :mod:`racecar_hw.net.parameters`). One Zenoh
  queryable per service, on rmw_zenoh's service key (``<domain>/<node>/<service>/<srv DDS type>/
  <hash>``) and declared complete, as ``rmw_service_data.cpp`` does. A query carries the CDR request
  and the client's 33-byte attachment; the answer, computed in Zenoh's thread (a pure function of
  an immutable configuration, cached per request bytes) goes back as a reply on the same key with an
  attachment of the request's sequence number, a fresh timestamp and the client's GID, which is
  how rmw_zenoh's client matches it to its request.
* **Graph.** A liveliness token for the node and one per publisher, subscriber and service server
  (``SS``), so ``ros2 node list``, ``ros2 topic list`` and ``ros2 node info`` on a machine running
  rmw_zenoh show the car. ``zenoh.ros_distro: humble`` writes ``TypeHashNotSupported`` where
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

from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import wall_ns
from racecar_hw.base.messages import Message
from racecar_hw.net import rmw
from racecar_hw.net.inbox import NON_FINITE, Inbox, all_finite
from racecar_hw.net.outbox import Outbox
from racecar_hw.net.parameters import (
    PARAMETER_SERVICES,
    SERVICE_QOS,
    CdrAnswers,
    ParameterService,
    ServiceSpec,
    service_name,
)
from racecar_hw.net.topics import Direction, Reliability, Topic
from racecar_hw.net.zenoh_config import ZenohParams, config_for
from racecar_hw.net.zenoh_security import open_error
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: What a sample from a Jazzy node on rmw_zenoh 0.2.0-0.2.3 gets in the log.
OLD_ATTACHMENT_HINT = ("the sender's rmw_zenoh uses the old string-keyed attachment of Jazzy's 0.2.0-0.2.3 "
                       "releases: update rmw_zenoh on that machine "
                       "(sudo apt upgrade ros-jazzy-rmw-zenoh-cpp)")

__all__ = ["ORIGIN", "BridgeStats", "ZenohBridge", "all_finite"]

#: How the bridge names itself as the origin of the messages it hands to the inbox.
ORIGIN = "zenoh"

#: Publishers per command row whose sequence numbers are followed (to count what Zenoh dropped).
MAX_PUBLISHERS = 64
#: The largest gap in one publisher's sequence numbers counted as superseded samples (a forged
#: sequence number must not make the counts absurd).
MAX_GAP = 1_000_000

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
    service_errors: int = 0  #: service requests refused (no attachment, malformed) or failed replies
    wrong_type: int = 0      #: incoming samples on an input topic with another type or type hash


class _Out:
    """One outgoing row: its Zenoh publisher, sequence number and GID, and whether anyone listens."""

    def __init__(self, row: Topic, publisher: Any, gid: bytes, latched: bool) -> None:
        self.row = row
        self.publisher = publisher
        self.gid = gid
        self.latched = latched
        self.sequence = 0
        self.matching = latched
        self.listener: Any = None


class ZenohBridge:
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
        self.stats = BridgeStats()
        self.refusals = refusals if refusals is not None else Refusals()
        self.session: Any = None
        self.zid = ""
        self._lock = threading.Lock()
        self.early = frozenset(early)
        self.urgent = frozenset(urgent) | self.early
        self._early: dict[str, list[Callable[[Message], None]]] = {}
        # not niced: remote navigation code waits for the scan it sends (the Foxglove sender is)
        self.outbox = Outbox("zenoh-publisher", params.queue_size, nice=0)
        self._types = ros2_types()
        self._outs: list[_Out] = []
        self._subscribers: list[Any] = []
        self._pumps: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._tokens: list[Any] = []
        self._bus_subs: list[Subscription] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._next_entity = 1
        #: answers the parameter services (None: no services)
        self.parameters = parameters
        self._answers = CdrAnswers(parameters) if parameters is not None else None
        self._queryables: list[Any] = []

    # --- names --------------------------------------------------------------------------------

    def ros_name(self, row: Topic) -> str:
        """The topic's full ROS name: the namespace (unless the row is absolute), then the row's ROS name."""
        return row.ros if row.absolute else self.namespace + row.ros

    def key(self, row: Topic) -> str:
        """The Zenoh key of a row's samples."""
        ros_type = row.msgtype.ROS_TYPE
        return rmw.topic_key(self.domain_id, self.ros_name(row), ros_type, self.type_hash(ros_type))

    def type_hash(self, ros_type: str) -> str:
        """The type hash field of keys and tokens for the peers' distribution (``zenoh.ros_distro``)."""
        return rmw.wire_type_hash(ros_type, self.params.ros_distro)

    def service_key(self, spec: ServiceSpec) -> str:
        """The Zenoh key of one of the node's services (rmw_zenoh: as a topic, of the service type)."""
        return rmw.topic_key(self.domain_id, self.service_name(spec), spec.srv_type,
                             self.type_hash(spec.srv_type))

    def service_name(self, spec: ServiceSpec) -> str:
        """The full ROS name of one of the node's services (``/<ns>/<node>/<service>``)."""
        return service_name(self.namespace, self.params.node_name, spec.name)

    def _entity(self, kind: str, row: Topic | None = None) -> rmw.Entity:
        common = (self.domain_id, self.zid, 0)
        node = (self.namespace, self.params.node_name)
        if row is None:
            return rmw.Entity(*common, 0, rmw.NODE, "", *node)
        entity_id, self._next_entity = self._next_entity, self._next_entity + 1
        ros_type = row.msgtype.ROS_TYPE
        return rmw.Entity(*common, entity_id, kind, "", *node, self.ros_name(row), rmw.dds_type(ros_type),
                          self.type_hash(ros_type), rmw.RmwQos.from_qos(row.qos))

    # --- life cycle ---------------------------------------------------------------------------

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
        self.zid = str(self.session.zid())
        liveliness = self.session.liveliness()
        self._tokens.append(liveliness.declare_token(self._entity(rmw.NODE).token()))
        for row in self.rows:
            if row.direction is Direction.OUT:
                self._declare_out(row, zenoh)
            else:
                self._declare_in(row, zenoh)
        if self._answers is not None:
            self._answers.warm()
            for spec in PARAMETER_SERVICES:
                self._declare_service(spec)
        self.outbox.start()
        for pump in self._pumps:
            pump.start()
        for out in self._outs:
            enqueue = self._enqueuer(out)
            if out.row.bus in self.early and not out.latched:
                self._early.setdefault(out.row.bus, []).append(enqueue)
            else:
                self._bus_subs.append(self.bus.subscribe(out.row.bus, enqueue))
            latest = self.bus.latest(out.row.bus)
            if out.latched and latest is not None:
                self._enqueuer(out)(latest)
        log.info("zenoh bridge up: %s mode, session %s, domain %d, namespace %r, listen %s, "
                 "connect %s; %d topics out, %d in, %d services; peers: rmw_zenoh %s", p.mode, self.zid,
                 self.domain_id, self.namespace or "/", p.listen, p.connect, len(self._outs),
                 sum(row.direction is not Direction.OUT for row in self.rows), len(self._queryables),
                 "Humble (TypeHashNotSupported)" if p.ros_distro == "humble" else "Jazzy and later")

    def _declare_out(self, row: Topic, zenoh: Any) -> None:
        reliable = row.qos.reliability is Reliability.RELIABLE
        options = dict(congestion_control=zenoh.CongestionControl.DROP,
                       reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT)
        entity = self._entity(rmw.PUBLISHER, row)
        key = self.key(row)
        if row.qos.latched:
            miss = zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S) \
                if reliable else None
            publisher = zenoh.ext.declare_advanced_publisher(
                self.session, key, cache=zenoh.ext.CacheConfig(row.qos.depth),
                publisher_detection=True, sample_miss_detection=miss, **options)
            out = _Out(row, publisher, entity.gid(), latched=True)
        else:
            publisher = self.session.declare_publisher(key, **options)
            out = _Out(row, publisher, entity.gid(), latched=False)
            out.matching = bool(publisher.matching_status.matching)

            def on_matching(status: Any, out: _Out = out) -> None:
                out.matching = bool(status.matching)

            out.listener = publisher.declare_matching_listener(on_matching)
        self._outs.append(out)
        self._tokens.append(self.session.liveliness().declare_token(entity.token()))

    def _declare_in(self, row: Topic, zenoh: Any) -> None:
        key = self.key(row)
        if row.qos.latched:
            callback = self._receiver(row)
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=row.qos.depth)
            sub = zenoh.ext.declare_advanced_subscriber(self.session, key, callback, history=history,
                                                        subscriber_detection=True)
        elif row.bus in self.inbox.stop_topics:
            # every e-stop message, in order, through a callback in Zenoh's thread: never coalesced
            sub = self.session.declare_subscriber(key, self._receiver(row))
        else:
            # a command: Zenoh keeps only the newest sample (in Rust, without the GIL) until this
            # row's thread takes it, at most once per control tick (the inbox's period)
            sub = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
            self._pumps.append(threading.Thread(target=self._pump, args=(row, sub), daemon=True,
                                                name=f"zenoh-in {row.ros}"))
        self._subscribers.append(sub)
        self._subscribers.append(self.session.declare_subscriber(
            rmw.topic_key_pattern(self.domain_id, self.ros_name(row)), self._type_guard(row, key)))
        token = self._entity(rmw.SUBSCRIPTION, row).token()
        self._tokens.append(self.session.liveliness().declare_token(token))

    def _declare_service(self, spec: ServiceSpec) -> None:
        key = self.service_key(spec)
        self._queryables.append(self.session.declare_queryable(key, self._answerer(spec, key),
                                                               complete=True))
        entity_id, self._next_entity = self._next_entity, self._next_entity + 1
        entity = rmw.Entity(self.domain_id, self.zid, 0, entity_id, rmw.SERVICE, "", self.namespace,
                            self.params.node_name, self.service_name(spec), rmw.dds_type(spec.srv_type),
                            self.type_hash(spec.srv_type), rmw.RmwQos.from_qos(SERVICE_QOS))
        self._tokens.append(self.session.liveliness().declare_token(entity.token()))

    def _type_guard(self, row: Topic, key: str) -> Callable[[Any], None]:
        """A callback for every sample on the row's topic, whatever its type: counts the samples of
        another type (or type hash), which the row's own subscriber never sees."""
        expected = row.msgtype.ROS_TYPE
        topic = self.ros_name(row)
        stats, lock = self.stats, self._lock

        def guard(sample: Any) -> None:
            got = str(sample.key_expr)
            if got == key:
                return
            with lock:
                stats.wrong_type += 1
            head, _, hash_ = got.rpartition("/")  # .../<dds type>/<type hash>
            dds = head.rpartition("/")[2]
            try:
                sent = rmw.ros_type(dds)
            except rmw.WireError:
                sent = dds
            reason = (f"type hash {hash_} of {sent} differs from racecar-hw's" if sent == expected
                      else f"wrong type {sent} (it takes {expected})")
            self.refusals.note("zenoh", topic, reason)

        return guard

    def _pump(self, row: Topic, sub: Any) -> None:
        """A command row's thread: take the newest sample, check it, offer it, rest one period."""
        receive = self._receiver(row, gaps={})
        period_s = self.inbox.period_ns / 1e9
        while not self._stopping.is_set():
            try:
                sample = sub.recv()  # blocks without the GIL; raises once the session closes
            except Exception:  # noqa: BLE001 - closed: the thread ends
                return
            receive(sample)
            self._stopping.wait(period_s)

    def close(self) -> None:
        """Undeclare everything, stop the publisher thread, close the session (safe twice)."""
        self._early = {}
        self._stopping.set()
        if self._own_inbox:
            self.inbox.close()
        for sub in self._bus_subs:
            sub.close()
        self._bus_subs.clear()
        self.outbox.stop(5.0)
        session, self.session = self.session, None
        if session is None:
            return
        for entity in [*self._tokens, *self._queryables, *self._subscribers,
                       *(o.listener for o in self._outs if o.listener), *(o.publisher for o in self._outs)]:
            try:
                entity.undeclare()
            except Exception:  # noqa: BLE001 - closing the session below undeclares the rest
                pass
        self._tokens.clear()
        self._queryables.clear()
        self._subscribers.clear()
        self._outs.clear()
        try:
            session.close()
        except Exception as err:  # noqa: BLE001 - shutting down: report and go on
            log.warning("zenoh session close failed: %r", err)
        for pump in self._pumps:  # the session's close ended their wait for a sample
            pump.join(5.0)
        self._pumps.clear()
        s = self.stats
        log.info("zenoh bridge closed: %d published (%d dropped, queue full), %d skipped (no subscriber); "
                 "%d received, %d without attachment, %d malformed, %d with an old rmw_zenoh's attachment, "
                 "%d non-finite, %d of a wrong type; %d service calls answered, %d refused", s.published,
                 self.outbox.dropped, s.skipped, s.received, s.no_attachment, s.malformed, s.old_attachment,
                 s.non_finite, s.wrong_type, s.service_calls, s.service_errors)

    # --- out: bus thread, then the publisher thread -------------------------------------------

    @property
    def dropped(self) -> int:
        """Outgoing messages dropped because the queue was full (the oldest go first)."""
        return self.outbox.dropped

    def control_idle(self) -> None:
        """The control path is idle until its next event (a scan's command is out): send now."""
        self.outbox.control_idle()

    def send_early(self, topic: str, msg: Message) -> None:
        """Queue ``msg`` of an ``early`` topic now (the event loop, after the scan's motor write)."""
        for enqueue in self._early.get(topic, ()):
            enqueue(msg)

    def _enqueuer(self, out: _Out) -> Callable[[Message], None]:
        return self.outbox.enqueuer(self._publish, out, self.stats, urgent=out.row.bus in self.urgent)

    def _publish(self, out: _Out, msg: Message, stamp: int) -> None:
        """In the publisher thread: serialize ``msg`` and put it with rmw_zenoh's attachment."""
        try:
            payload = self._types.serialize(msg)
            out.sequence += 1
            out.publisher.put(payload, attachment=rmw.encode_attachment(out.sequence, stamp, out.gid))
            self.stats.published += 1
        except Exception as err:  # noqa: BLE001 - one bad message never stops the thread
            self.stats.publish_errors += 1
            if self.stats.publish_errors in (1, 10, 100) or self.stats.publish_errors % 1000 == 0:
                log.warning("zenoh: could not publish %s (%d so far): %r", out.row.ros,
                            self.stats.publish_errors, err)

    # --- in: Zenoh's threads, then the event loop ---------------------------------------------

    def _receiver(self, row: Topic, gaps: dict[bytes, int] | None = None) -> Callable[[Any], None]:
        """Check one sample of ``row`` and offer it to the inbox (in Zenoh's or the row's thread).

        With ``gaps`` (a command row, whose older samples Zenoh drops for the newest), the gap in
        each publisher's sequence numbers is counted as superseded.
        """
        cls, topic = row.msgtype, row.bus
        stats, lock, inbox = self.stats, self._lock, self.inbox

        def count(name: str) -> None:
            with lock:
                setattr(stats, name, getattr(stats, name) + 1)
                n = getattr(stats, name)
            if name == "old_attachment" and (n in (1, 10, 100) or n % 1000 == 0):
                log.warning("zenoh: dropped a message for %s: %s (%d so far)", row.ros,
                            OLD_ATTACHMENT_HINT, n)

        def receive(sample: Any) -> None:
            attachment = sample.attachment
            if attachment is None:
                count("no_attachment")
                inbox.refuse(ORIGIN, topic, "no attachment")
                return
            raw = attachment.to_bytes()
            try:
                meta = rmw.Attachment.decode(raw)
                payload = sample.payload.to_bytes()
            except Exception:  # noqa: BLE001 - hostile bytes: whatever the decoder raises
                old = rmw.is_old_attachment(raw)
                count("old_attachment" if old else "malformed")
                inbox.refuse(ORIGIN, topic,
                             "an old rmw_zenoh's attachment" if old else "malformed attachment")
                return
            skipped = 0
            if gaps is not None:
                last = gaps.get(meta.gid)
                if last is not None and meta.sequence_number > last:
                    skipped = min(meta.sequence_number - last - 1, MAX_GAP)
                if last is None and len(gaps) >= MAX_PUBLISHERS:
                    gaps.clear()  # forged GIDs must not grow memory
                gaps[meta.gid] = meta.sequence_number
            refused = inbox.offer_cdr(ORIGIN, topic, cls, payload, superseded=skipped)
            count("received" if refused is None else "non_finite" if refused == NON_FINITE else "malformed")

        return receive

    # --- services: Zenoh's threads ------------------------------------------------------------

    def _answerer(self, spec: ServiceSpec, key: str) -> Callable[[Any], None]:
        stats, lock, answers = self.stats, self._lock, self._answers
        assert answers is not None

        def refuse(why: str) -> None:
            with lock:
                stats.service_errors += 1
                n = stats.service_errors
            if n in (1, 10, 100) or n % 1000 == 0:
                log.warning("zenoh: refused a call of %s: %s (%d so far)", self.service_name(spec), why, n)

        def answer(query: Any) -> None:
            attachment, payload = query.attachment, query.payload
            if spec.name.startswith("set_"):
                log.info("zenoh: a client called %s: refused, the parameters are read-only",
                         self.service_name(spec))
            if attachment is None or payload is None:
                refuse("no rmw_zenoh attachment" if attachment is None else "no request")
                return
            try:
                request = rmw.Attachment.decode(attachment.to_bytes())
                reply = answers.answer(spec.name, payload.to_bytes())
            except Exception as err:  # noqa: BLE001 - hostile bytes: whatever the decoder raises
                refuse(f"malformed request ({type(err).__name__})")
                return
            try:
                query.reply(key, reply, attachment=rmw.encode_attachment(
                    request.sequence_number, wall_ns(), request.gid))
            except Exception as err:  # noqa: BLE001 - the client went away: nothing to answer
                refuse(f"reply failed ({err!r})")
                return
            with lock:
                stats.service_calls += 1

        return answer

    def _deliver(self, topic: str, msg: Message, origin: str) -> None:
        """The own inbox's hand-over, in the event loop: on the bus, then ``on_input``."""
        if self.session is None:
            return
        self.bus.publish(topic, msg)
        if self.on_input is not None:
            self.on_input(topic)
