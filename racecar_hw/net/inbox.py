"""The network inbox: inbound commands from every network surface, coalesced before the event loop.

Network surfaces (the Zenoh bridge, the DDS interface) receive in their own threads, at whatever
rate a client sends. Handing each message to the event loop (one ``call_soon_threadsafe``, one
bus publish, one early mux step and VESC write per message) lets a flood of ``/cmd_vel`` starve
the control loop: 5,000 messages/s made 147 of 900 ticks miss, and at 60,000/s an e-stop from
another client latched only after about 0.1 s. So every surface gives its messages to one
:class:`Inbox` instead:

* **Checked on the receiving thread.** The surface checks what is its own (rmw_zenoh's
  attachment); the inbox decodes the CDR payload (:meth:`Inbox.offer_cdr`) and checks that every
  number is finite (:meth:`Inbox.offer`: the one finiteness check of network input). What fails is
  counted as refused, per input, and noted in :class:`~racecar_hw.runtime.refusals.Refusals`.
* **Latest value per input.** Each inbound bus topic (a mux input, a lock, ``/cmd_vel``) keeps only
  its newest message until the loop takes it; an older one still waiting is *superseded*
  (counted). The loop takes at most one message per input per period (the control tick,
  ``1 / mux.rate_hz``): the first message after a quiet period goes at once (no added latency for a
  well-behaved client), a faster stream is handed over once per period, its latest value.
* **Cheapest where the surface offers at most one sample per input per period** (a
  :class:`~racecar_hw.net.command_gate.CommandGate`: Zenoh's rows, and DDS readers with KEEP_LAST 1):
  it offers the newest with the number dropped before it (``superseded``, from the publishers'
  sequence numbers), and a flood costs no decoding beyond one message per input per period.
* **One wake-up, not one per message.** The loop is woken (``call_soon_threadsafe``) only when the
  inbox has something it can hand over now and no wake-up is pending; otherwise a single timer in
  the loop waits for the earliest input that may be handed over next. A flood costs the loop about
  two wake-ups per period, whatever its rate.
* **E-stops are never coalesced away and jump the queue.** The e-stop topic and its release keep
  their order in a short FIFO of their own. A message that engages the e-stop (``data`` true on the
  e-stop topic) wakes the loop at once, even within the period, and the whole FIFO is handed over
  before any command. Only what cannot engage is ever dropped: a release or a ``false`` replaced by
  a newer one on the same topic, or the oldest of them when the FIFO is full; a repeated engaging
  message right behind an identical one is merged into it. Dropping those can only keep the car
  stopped, never let it go.

The hand-over calls ``deliver(topic, msg, origin)`` for commands and ``on_estop(topic, msg,
origin)`` for the e-stop topics (``origin`` names the surface: ``"zenoh"``, ``"dds"``), both in the
event loop: e-stops first, then commands. Counts per input (received, superseded, refused, handed
over) are in :meth:`Inbox.counts` and :meth:`Inbox.diagnostics`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from racecar_hw.base.clock import NS_PER_S, monotonic_ns
from racecar_hw.base.messages import DiagnosticStatus, KeyValue, Message
from racecar_hw.net.inbox_stops import StopQueue
from racecar_hw.rosmsg.typestore import ros2_types
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: ``deliver(topic, msg, origin)`` / ``on_estop(topic, msg, origin)``, called in the event loop.
Handover = Callable[[str, Message, str], None]

#: Superseded messages of one input that make one "flood" note in the refusals (a line at most
#: once per the refusals' interval) when they come within :data:`FLOOD_WINDOW_NS`: below it a
#: client a little faster than the tick is no news. Counted over all time, a client at the tick
#: rate whose messages sometimes meet in one period (jitter) was called a flood after 10-20 s.
FLOOD_NOTE = 100
#: The window (monotonic ns) in which :data:`FLOOD_NOTE` superseded messages are a flood: at least
#: 50 a second beyond what the loop takes.
FLOOD_WINDOW_NS = 2_000_000_000
#: Why a message is refused (the reasons the inbox itself checks; surfaces add their own).
MALFORMED = "malformed"
NON_FINITE = "non-finite"


#: each message class's field names, in order (``dataclasses.fields`` builds a tuple per call)
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}
#: types that hold no float, whatever their value
_NO_FLOATS = (int, str, bool, bytes)


def all_finite(msg: Any) -> bool:
    """Whether every float (and float array) in a message is finite."""
    cls = type(msg)
    if cls is float:
        return math.isfinite(msg)
    names = _FIELD_NAMES.get(cls)
    if names is not None:  # a message class seen before: its fields, without dataclasses' walk
        for name in names:
            value = getattr(msg, name)
            kind = type(value)
            if kind is float:
                if not math.isfinite(value):
                    return False
            elif kind not in _NO_FLOATS and not all_finite(value):
                return False
        return True
    if isinstance(msg, float):
        return math.isfinite(msg)
    if isinstance(msg, np.ndarray):
        return msg.dtype.kind != "f" or bool(np.isfinite(msg).all())
    if isinstance(msg, list):
        return all(all_finite(item) for item in msg)
    if dataclasses.is_dataclass(msg) and not isinstance(msg, type):
        _FIELD_NAMES[cls] = tuple(f.name for f in dataclasses.fields(msg))
        return all_finite(msg)
    return True


@dataclass
class InputCounts:
    """What one input's messages became (written under the inbox's lock)."""

    received: int = 0     #: well-formed messages taken in
    superseded: int = 0   #: replaced by a newer one before the loop took them (or merged)
    refused: int = 0      #: malformed: no attachment, bad CDR, a NaN or infinite number
    handed_over: int = 0  #: given to the event loop
    #: refused, by reason
    reasons: dict[str, int] = field(default_factory=dict)


class _Slot:
    """One input: its pending message (the latest) and when it may be handed over next."""

    __slots__ = ("counts", "flooded", "msg", "next_ns", "origin", "topic", "unreported", "window_ns")

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self.msg: Message | None = None
        self.origin = ""
        self.next_ns = 0
        self.counts = InputCounts()
        self.unreported = 0  #: superseded since the last flood note, within the window
        self.window_ns: int | None = None  #: when the flood window began (monotonic ns)
        self.flooded = False  #: a flood was noted (what is left of it is noted at shutdown)


class Inbox:
    """Inbound network messages for ``topics``, coalesced into the event loop (module docstring).

    ``period_s`` is the least time between two hand-overs of one input (the control tick).
    ``estop_topic`` and ``release_topic`` are the e-stop topics (handed to ``on_estop``, or to
    ``deliver`` without it); ``refusals`` counts refused messages and floods for the log.
    :meth:`offer`, :meth:`offer_cdr` and :meth:`refuse` may be called from any thread; the rest
    from the event loop's thread (or before :meth:`bind`).
    """

    def __init__(self, topics: Iterable[str], deliver: Handover, *, period_s: float = 0.02,
                 estop_topic: str | None = None, release_topic: str | None = None,
                 on_estop: Handover | None = None, refusals: Refusals | None = None,
                 clock: Callable[[], int] = monotonic_ns) -> None:
        self.period_ns = max(1, round(period_s * NS_PER_S))
        self.estop_topic = estop_topic
        self.stop_topics = frozenset(t for t in (estop_topic, release_topic) if t)
        self.deliver = deliver
        self.on_estop = on_estop if on_estop is not None else deliver
        self.refusals = refusals
        self._clock = clock
        self._lock = threading.Lock()
        self._slots: dict[str, _Slot] = {t: _Slot(t) for t in {*topics, *self.stop_topics}}
        self._dirty: list[_Slot] = []            #: slots holding a message
        self._stops = StopQueue(estop_topic, self.period_ns, self._superseded)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._soon = False                       #: a call_soon_threadsafe(drain) is pending
        self._timer: asyncio.TimerHandle | None = None
        self._timer_ns: int | None = None        #: when the pending timer fires (monotonic ns)
        self._types = ros2_types()
        #: wake-ups of the loop: call_soon and timers (a flood must not make one per message)
        self.wakeups = 0

    # --- life cycle (event loop thread) --------------------------------------------------------

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Hand over into ``loop`` from now on (idempotent for the same loop)."""
        with self._lock:
            self._loop = loop

    def close(self) -> None:
        """Stop handing over: pending messages are dropped, later offers ignored (safe twice)."""
        with self._lock:
            self._loop = None
            timer, self._timer, self._timer_ns = self._timer, None, None
        if timer is not None:
            timer.cancel()
        self.flush_floods()

    # --- in: any thread -------------------------------------------------------------------------

    def offer_cdr(self, origin: str, topic: str, cls: type[Message], payload: bytes,
                  superseded: int = 0) -> str | None:
        """Decode a CDR ``payload`` of ``cls`` for ``topic`` and :meth:`offer` it.

        Returns None when taken in, else the reason it was refused (``malformed``, ``non-finite``).
        """
        try:
            msg = self._types.deserialize(payload, cls)
        except Exception:  # noqa: BLE001 - hostile bytes: whatever the decoder raises
            self.refuse(origin, topic, MALFORMED)
            return MALFORMED
        return self.offer(origin, topic, msg, superseded)

    def offer(self, origin: str, topic: str, msg: Message, superseded: int = 0) -> str | None:
        """Take in ``msg`` for ``topic`` from surface ``origin``, if every number in it is finite.

        ``superseded``: newer messages of this input the surface's middleware already dropped
        before this one (a surface that keeps only the newest sample, counting the gaps in the
        publishers' sequence numbers), counted as received and superseded. Returns None when
        taken in, else the reason it was refused. Never blocks for longer than a dictionary update
        under the inbox's lock.
        """
        if not all_finite(msg):
            self.refuse(origin, topic, NON_FINITE)
            return NON_FINITE
        slot = self._slots.get(topic)
        if slot is None:
            self.refuse(origin, topic, "not an input")
            return "not an input"
        flood = 0
        now = self._clock()
        with self._lock:
            loop = self._loop
            if loop is None:
                return None  # not running (yet, or any more): nothing to hand over to
            slot.counts.received += 1 + superseded
            slot.counts.superseded += superseded
            if slot.window_ns is None or now - slot.window_ns >= FLOOD_WINDOW_NS:
                slot.window_ns, slot.unreported = now, 0
            slot.unreported += superseded
            if topic in self.stop_topics:
                wake, replaced = self._stops.queue(topic, msg, origin, now, self._timer_ns)
                slot.origin = origin
            else:
                replaced = slot.msg is not None
                if replaced:
                    slot.counts.superseded += 1
                else:
                    self._dirty.append(slot)
                slot.msg, slot.origin = msg, origin
                wake = (now >= slot.next_ns or self._timer_ns is None or self._timer_ns > slot.next_ns)
            if replaced:
                slot.unreported += 1
            if slot.unreported >= FLOOD_NOTE:
                flood, slot.unreported, slot.flooded = slot.unreported, 0, True
            if wake and not self._soon:
                self._soon = True
                self.wakeups += 1
            else:
                wake = False
        if wake:
            try:
                loop.call_soon_threadsafe(self.drain)
            except RuntimeError:  # the loop closed meanwhile
                pass
        if flood and self.refusals is not None:
            self.refusals.note(origin, topic, "flood: superseded before the loop took them", flood)
        return None

    def _superseded(self, topic: str) -> None:
        """A message for ``topic`` was merged or dropped (lock held)."""
        self._slots[topic].counts.superseded += 1

    def refuse(self, origin: str, topic: str, reason: str) -> None:
        """Count a message for ``topic`` from ``origin`` refused for ``reason`` (any thread)."""
        slot = self._slots.get(topic)
        if slot is not None:
            with self._lock:
                slot.counts.refused += 1
                slot.counts.reasons[reason] = slot.counts.reasons.get(reason, 0) + 1
        if self.refusals is not None:
            self.refusals.note(origin, topic, reason)

    # --- out: the event loop --------------------------------------------------------------------

    def drain(self) -> None:
        """Hand over what may go now: the e-stop FIFO first, then each due input's latest message.

        Called by the inbox's own wake-ups; safe to call any time from the loop's thread.
        """
        now = self._clock()
        with self._lock:
            loop = self._loop
            self._soon = False
            timer, self._timer, self._timer_ns = self._timer, None, None
            stops = self._stops.take(now)
            wait_ns = self._stops.next_ns if self._stops else None
            ready: list[tuple[str, Message, str]] = []
            waiting: list[_Slot] = []
            for slot in self._dirty:
                if now >= slot.next_ns:
                    assert slot.msg is not None
                    ready.append((slot.topic, slot.msg, slot.origin))
                    slot.msg = None
                    slot.next_ns = now + self.period_ns
                    slot.counts.handed_over += 1
                else:
                    waiting.append(slot)
                    wait_ns = slot.next_ns if wait_ns is None else min(wait_ns, slot.next_ns)
            self._dirty = waiting
            for topic, _, _ in stops:
                self._slots[topic].counts.handed_over += 1
            if loop is not None:
                self._timer_ns = wait_ns
        if timer is not None:
            timer.cancel()
        if loop is None:
            return  # closed: nothing goes to the loop any more
        if wait_ns is not None:
            self._timer = loop.call_later(max(0, wait_ns - now) / NS_PER_S, self._on_timer)
        for topic, msg, origin in stops:
            self._hand_over(self.on_estop, topic, msg, origin)
        for topic, msg, origin in ready:
            self._hand_over(self.deliver, topic, msg, origin)

    def _on_timer(self) -> None:
        with self._lock:
            self.wakeups += 1
        self.drain()

    def _hand_over(self, handover: Handover, topic: str, msg: Message, origin: str) -> None:
        try:
            handover(topic, msg, origin)
        except Exception:  # one failing hand-over must not lose the e-stop or commands behind it
            log.exception("inbox: handing over a message for %s from %s failed", topic, origin)

    # --- counts ---------------------------------------------------------------------------------

    def counts(self) -> dict[str, InputCounts]:
        """A copy of the counts, per input topic."""
        with self._lock:
            return {t: dataclasses.replace(s.counts, reasons=dict(s.counts.reasons))
                    for t, s in sorted(self._slots.items())}

    def flush_floods(self) -> None:
        """Note what is left of a flood not yet noted in the refusals (at shutdown); a client that
        never flooded has none."""
        if self.refusals is None:
            return
        with self._lock:
            pending = [(s.origin, s.topic, s.unreported) for s in self._slots.values()
                       if s.unreported and s.flooded]
            for s in self._slots.values():
                s.unreported = 0
        for origin, topic, n in pending:
            self.refusals.note(origin or "network", topic, "flood: superseded before the loop took them", n)

    def diagnostics(self, name: str = "racecar_hw: network inbox") -> DiagnosticStatus:
        """The counts as a ``diagnostic_msgs/DiagnosticStatus`` for ``/diagnostics``.

        WARN once any message was refused or superseded (a client sending faster than the car
        takes commands, or sending garbage), with the totals in the message; one value per input
        that has seen traffic: ``received N, superseded N, refused N, handed over N``.
        """
        counts = self.counts()
        values: list[KeyValue] = []
        for topic, c in counts.items():
            if not (c.received or c.refused):
                continue
            text = (f"received {c.received}, superseded {c.superseded}, refused {c.refused}, "
                    f"handed over {c.handed_over}")
            if c.reasons:
                text += " (" + ", ".join(f"{r} {n}" for r, n in sorted(c.reasons.items())) + ")"
            values.append(KeyValue(topic, text))
        received = sum(c.received for c in counts.values())
        superseded = sum(c.superseded for c in counts.values())
        refused = sum(c.refused for c in counts.values())
        values.append(KeyValue("wakeups", str(self.wakeups)))
        level = DiagnosticStatus.WARN if superseded or refused else DiagnosticStatus.OK
        message = f"{received} received, {superseded} superseded, {refused} refused"
        return DiagnosticStatus(level, name, message, "", values)
