"""The Zenoh bridge's incoming side: subscribers of the input rows, checks, hand-over to the inbox.

Zenoh calls back in its own threads; there the sample's rmw_zenoh attachment is checked and the
payload given to the network :class:`~racecar_hw.net.inbox.Inbox` (shared with every network
surface), which decodes it, checks every number is finite and keeps the latest message per input
for the event loop. A command row's subscriber keeps only the newest sample (a Zenoh ring channel,
in Rust, without the GIL) until the row's own thread takes it, at most once per control tick;
e-stop rows take every message, in order, never coalesced. A second subscriber per input topic
matches the topic whatever its type and counts the samples of another type (or type hash) in
``wrong_type`` and in the daemon's :class:`~racecar_hw.runtime.refusals.Refusals`.
See :mod:`racecar_hw.net.zenoh_bridge`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from racecar_hw.net import rmw
from racecar_hw.net.inbox import NON_FINITE, Inbox
from racecar_hw.net.topics import Topic
from racecar_hw.net.zenoh_node import ZenohNode
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.threadname import name_this_thread

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
        self._pumps: list[threading.Thread] = []
        self._stopping = threading.Event()

    def declare(self, row: Topic, node: ZenohNode, zenoh: Any) -> None:
        """Subscribe to ``row`` (and to its topic whatever the type) on ``node``'s session."""
        topic = self.ros_name(row)
        key = node.names.key(topic, row.msgtype.ROS_TYPE)
        if row.qos.latched:
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=row.qos.depth)
            node.track(zenoh.ext.declare_advanced_subscriber(node.session, key, self.receiver(row),
                                                             history=history, subscriber_detection=True))
            node.announce(node.names.endpoint(rmw.SUBSCRIPTION, topic, row.msgtype.ROS_TYPE, row.qos))
        elif row.bus in self.inbox.stop_topics:
            # every e-stop message, in order, through a callback in Zenoh's thread: never coalesced
            node.subscriber(topic, row.msgtype, row.qos, self.receiver(row))
        else:
            # a command: Zenoh keeps only the newest sample until this row's thread takes it, at
            # most once per control tick (the inbox's period)
            sub = node.subscriber(topic, row.msgtype, row.qos, zenoh.handlers.RingChannel(1))
            self._pumps.append(threading.Thread(target=self._pump, args=(row, sub), daemon=True,
                                                name=f"zenoh-in {row.ros}"))
        node.track(node.session.declare_subscriber(rmw.topic_key_pattern(node.names.domain_id, topic),
                                                   self._type_guard(row, key)))

    def start(self) -> None:
        """Start the command rows' threads."""
        for pump in self._pumps:
            pump.start()

    def stop(self) -> None:
        """Tell the command rows' threads to end (they wait for a sample until the session closes)."""
        self._stopping.set()

    def join(self, timeout_s: float = 5.0) -> None:
        """Wait for the command rows' threads (after the session's close ended their wait)."""
        for pump in self._pumps:
            if pump.is_alive() or pump.ident is not None:
                pump.join(timeout_s)
        self._pumps.clear()

    def _type_guard(self, row: Topic, key: str) -> Callable[[Any], None]:
        """A callback for every sample on the row's topic, whatever its type: counts the samples of
        another type (or type hash), which the row's own subscriber never sees."""
        expected = row.msgtype.ROS_TYPE
        topic = self.ros_name(row)
        stats, lock = self.stats, self.lock

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
        """A command row's thread: take the newest sample, check it, offer it; at most one per period.

        A sample that comes a period or more after the last one offered is offered at once, with
        no rest after it (a client answering every scan at 40 Hz costs one wake-up of this thread
        per command, not two). One that comes sooner waits out the rest of the period, and then
        the newest sample (Zenoh's ring channel kept it, dropping the ones before) is offered
        instead: a flood still costs this thread at most two wake-ups per period.
        """
        name_this_thread(f"zenoh-in{row.ros}")
        receive = self.receiver(row, gaps={})
        period_s = self.inbox.period_ns / 1e9
        clock = time.monotonic
        last = -math.inf
        while not self._stopping.is_set():
            try:
                sample = sub.recv()  # blocks without the GIL; raises once the session closes
            except Exception:  # noqa: BLE001 - closed: the thread ends
                return
            rest = last + period_s - clock()
            if rest > 0.0:
                if self._stopping.wait(rest):
                    return
                try:
                    newer = sub.try_recv()  # the newest sample, if one came meanwhile
                except Exception:  # noqa: BLE001 - closed: the thread ends
                    return
                if newer is not None:
                    sample = newer
            last = clock()
            receive(sample)

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
