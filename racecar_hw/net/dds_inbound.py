"""The DDS interface's inbound side: samples from Cyclone's readers into the daemon's inbox.

Every input row's reader has a listener, which Cyclone calls in its own receiving thread when data
is available (the thread keeps its Python state between calls:
:func:`~racecar_hw.runtime.foreign_threads.hold_thread_state`). A command row's reader keeps only
its newest sample (KEEP_LAST 1, in Cyclone's C code) and its listener passes the reader to a
:class:`~racecar_hw.net.command_gate.CommandGate`: when nothing was taken from the row within the
control period (``period_s``, s) the newest sample is taken at once, in that thread; otherwise the
gate's one thread (``dds-in``, for every row) takes it when the period is over. So a client
answering every scan (40 Hz) wakes no thread of ours, an idle interface costs nothing, and a flood
costs a short callback per sample and at most one take per row and period. The e-stop and its
release are never coalesced: their listeners take every sample, in order. So are the samples of a
row closed to the network (a mux input with ``network: false``, :attr:`Topic.refused`): each is
refused and counted by the inbox (:meth:`Inbox.refuse`), never decoded. Every other sample's CDR
payload is decoded and checked by the :class:`~racecar_hw.net.inbox.Inbox`; without
``accepts_commands`` (a non-loopback interface) each is refused and counted instead.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from racecar_hw.net.command_gate import CommandGate
from racecar_hw.net.inbox import MALFORMED, NON_FINITE, Inbox
from racecar_hw.net.topics import Topic
from racecar_hw.runtime.foreign_threads import hold_thread_state
from racecar_hw.runtime.refusals import Refusals

if TYPE_CHECKING:
    from racecar_hw.net.dds_bridge import DdsStats

SURFACE = "dds"
#: Samples taken from a reader per call.
TAKE_N = 64
_UNAUTHENTICATED = ("unauthenticated interface (dds.interface is not loopback; see "
                    "dds.accept_unauthenticated_commands)")


class DdsReceiver:
    """Takes samples from readers into ``inbox``, counting them in ``stats`` (under :attr:`lock`)."""

    def __init__(self, inbox: Inbox, stats: DdsStats, refusals: Refusals, *, accepts_commands: bool,
                 period_s: float) -> None:
        self.inbox = inbox
        self.stats = stats
        self.refusals = refusals
        self.accepts_commands = accepts_commands
        self.period_s = period_s
        self.lock = threading.Lock()
        #: the command rows' rate gate (its thread takes the samples that came within a period)
        self.gate = CommandGate("dds-in", period_s)

    def receiver(self, row: Topic, name: str,
                 arrivals: Callable[[], int] | None = None) -> Callable[[Any], None]:
        """What takes ``row``'s samples from a reader (a listener's callback, or the gate's offer);
        ``name`` is the row's full ROS name, for the refusals. ``arrivals()``, for a reader that
        keeps only its newest sample, says how many samples came since the last take (and starts
        the count again): those beyond the taken ones were superseded in Cyclone's C code."""
        cls, topic = row.msgtype, row.bus
        stats, lock, inbox = self.stats, self.lock, self.inbox
        accept = self.accepts_commands
        refusals = self.refusals
        closed = row.refused
        outcome = {None: "received", MALFORMED: "malformed", NON_FINITE: "non_finite"}

        def receive(reader: Any) -> None:
            came = arrivals() if arrivals is not None else 0
            try:
                samples = reader.take(TAKE_N)
            except Exception:  # noqa: BLE001 - a reader being deleted at shutdown
                return
            superseded = max(came - len(samples), 0)
            for sample in samples:
                data = getattr(sample, "data", None)
                if data is None:  # an instance state change (a writer went away), no data
                    continue
                if closed:  # a mux input closed to the network: counted per input, never decoded
                    with lock:
                        stats.refused += 1
                    inbox.refuse(SURFACE, topic, closed)
                    continue
                if not accept:
                    with lock:
                        stats.refused += 1
                    refusals.note(SURFACE, name, _UNAUTHENTICATED)
                    continue
                field = outcome.get(inbox.offer_cdr(SURFACE, topic, cls, data, superseded), "refused")
                superseded = 0
                with lock:
                    setattr(stats, field, getattr(stats, field) + 1)

        return receive

    def gated(self, row: Topic, name: str) -> Callable[[Any], None]:
        """A command row reader's ``on_data_available``: the newest sample, at most once per period.

        Cyclone calls it once per sample that arrives; the reader keeps the newest only, so the
        calls since the last take, less the samples taken, are the flood's superseded samples
        (counted as the inbox counts Zenoh's from the gaps in its sequence numbers)."""
        count = [0]
        lock = self.lock

        def arrivals() -> int:
            with lock:
                came, count[0] = count[0], 0
            return came

        arrive = self.gate.row(self.receiver(row, name, arrivals))

        def on_data_available(reader: Any) -> None:  # in Cyclone's receiving thread
            hold_thread_state()
            with lock:
                count[0] += 1
            arrive(reader)

        return on_data_available

    def start(self) -> None:
        """Start the command rows' gate."""
        self.gate.start()

    def stop(self) -> None:
        """Stop the command rows' gate (a sample still waiting for its period stays in its reader)."""
        self.gate.stop()


__all__ = ["SURFACE", "TAKE_N", "DdsReceiver"]
