"""The Zenoh bridge's incoming side: subscribers of the input rows, checks, hand-over to the inbox.

Each input row has one subscriber, on its topic whatever the type (``<domain>/<topic>/*/*``),
whose callback runs in Zenoh's receiving thread (not ``indirect``: no Python thread of its own to
wake per sample). A sample on another key than the row's (another type or type hash) is counted in
``wrong_type`` and in the daemon's :class:`~racecar_hw.runtime.refusals.Refusals`. On the row's key
its rmw_zenoh attachment is checked and the payload given to the network
:class:`~racecar_hw.net.inbox.Inbox` (shared with every network surface), which decodes it,
checks every number is finite and keeps the latest message per input for the event loop. A command
row's samples pass a :class:`~racecar_hw.net.command_gate.CommandGate` first: at most one offer
per control period, the newest, at once when none was offered within the period (a client
answering every scan costs no wake-up of a thread of ours). E-stop rows take every message, in
order, never coalesced. A row closed to the network (a mux input with ``network: false``,
:attr:`~racecar_hw.net.topics.Topic.refused`) is subscribed too, so that every sample on it is
refused and counted (``closed``, and per input by the inbox, whose refusals log the key to change),
never decoded. See :mod:`racecar_hw.net.zenoh_bridge`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

from racecar_hw.net import rmw
from racecar_hw.net.command_gate import CommandGate
from racecar_hw.net.inbox import NON_FINITE, Inbox
from racecar_hw.net.topics import Topic
from racecar_hw.net.zenoh_node import ZenohNode
from racecar_hw.runtime.foreign_threads import hold_thread_state
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: How the bridge names itself as the origin of the messages it hands to the inbox.
ORIGIN = "zenoh"
#: What a sample from a Jazzy node on rmw_zenoh 0.2.0-0.2.3 gets in the log.
OLD_ATTACHMENT_HINT = ("the sender's rmw_zenoh uses the old string-keyed attachment of Jazzy's 0.2.0-0.2.3 "
                       "releases: update rmw_zenoh on that machine "
                       "(sudo apt upgrade ros-jazzy-rmw-zenoh-cpp)")
#: Publishers per command row whose sequence numbers are followed (to count what Zenoh dropped).
MAX_PUBLISHERS = 64
#: The largest gap in one publisher's sequence numbers counted as superseded samples (a forged
#: sequence number must not make the counts absurd).
MAX_GAP = 1_000_000


class ZenohInputs:
    """The input rows of one bridge. ``stats`` (a :class:`~racecar_hw.net.zenoh_bridge.BridgeStats`)
    is written under ``lock``; ``ros_name(row)`` gives a row's full ROS name."""

    def __init__(self, inbox: Inbox, stats: Any, lock: threading.Lock, refusals: Refusals,
                 ros_name: Callable[[Topic], str]) -> None:
        self.inbox = inbox
        self.stats = stats
        self.lock = lock
        self.refusals = refusals
        self.ros_name = ros_name
        #: the command rows' rate gate (its thread offers the samples that came within a period)
        self.gate = CommandGate("zenoh-in", inbox.period_ns / 1e9)

    def declare(self, row: Topic, node: ZenohNode, zenoh: Any) -> None:
        """Subscribe to ``row``'s topic (whatever the type) on ``node``'s session, and announce it."""
        topic = self.ros_name(row)
        key = node.names.key(topic, row.msgtype.ROS_TYPE)
        guard = self._type_guard(row, key)
        if row.qos.latched:
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=row.qos.depth)
            node.track(zenoh.ext.declare_advanced_subscriber(node.session, key, self.receiver(row),
                                                             history=history, subscriber_detection=True))
            node.track(node.session.declare_subscriber(rmw.topic_key_pattern(node.names.domain_id, topic),
                                                       zenoh.handlers.Callback(guard, indirect=False)))
        else:
            if row.refused:
                take = self.refuser(row)  # a mux input closed to the network: every sample refused
            elif row.bus in self.inbox.stop_topics:
                take = self.receiver(row)  # every e-stop message, in order: never coalesced
            else:
                take = self.gate.row(self.receiver(row, gaps={}))

            def on_sample(sample: Any) -> None:  # in Zenoh's receiving thread
                hold_thread_state()
                if str(sample.key_expr) == key:
                    take(sample)
                else:
                    guard(sample)

            node.track(node.session.declare_subscriber(rmw.topic_key_pattern(node.names.domain_id, topic),
                                                       zenoh.handlers.Callback(on_sample, indirect=False)))
        node.announce(node.names.endpoint(rmw.SUBSCRIPTION, topic, row.msgtype.ROS_TYPE, row.qos))

    def start(self) -> None:
        """Start the command rows' gate."""
        self.gate.start()

    def stop(self) -> None:
        """Stop the command rows' gate (samples still pending are dropped)."""
        self.gate.stop()

    def _type_guard(self, row: Topic, key: str) -> Callable[[Any], None]:
        """Counts a sample on the row's topic with another key than ``key`` (another type or type
        hash), which the row never takes."""
        expected = row.msgtype.ROS_TYPE
        topic = self.ros_name(row)
        stats, lock = self.stats, self.lock

        def guard(sample: Any) -> None:
            hold_thread_state()
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

    def refuser(self, row: Topic) -> Callable[[Any], None]:
        """Refuse every sample of ``row``, a mux input closed to the network (:attr:`Topic.refused`):
        counted in ``closed`` and by the inbox (per input, and in the refusals' log lines)."""
        topic, reason = row.bus, row.refused
        stats, lock, inbox = self.stats, self.lock, self.inbox

        def refuse(sample: Any) -> None:
            with lock:
                stats.closed += 1
            inbox.refuse(ORIGIN, topic, reason)

        return refuse

    def receiver(self, row: Topic, gaps: dict[bytes, int] | None = None) -> Callable[[Any], None]:
        """Check one sample of ``row`` and offer it to the inbox (in Zenoh's or the row's thread).

        With ``gaps`` (a command row, whose older samples Zenoh drops for the newest), the gap in
        each publisher's sequence numbers is counted as superseded.
        """
        cls, topic = row.msgtype, row.bus
        stats, lock, inbox = self.stats, self.lock, self.inbox

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
