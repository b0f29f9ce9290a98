"""The DDS interface's inbound side: samples from Cyclone's readers into the daemon's inbox.

A command row's reader keeps only its newest sample (KEEP_LAST 1, in Cyclone's C code, without the
GIL) and a thread per row (a *pump*) takes it at most once per control period (``period_s``, s),
so a flood of ``/cmd_vel`` costs no Python work per message. The e-stop and its release are never
coalesced: Cyclone calls their readers' listeners for every sample, in order. Every sample's CDR
payload is decoded and checked by the :class:`~racecar_hw.net.inbox.Inbox`; without
``accepts_commands`` (a non-loopback interface) each is refused and counted instead.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from racecar_hw.net.inbox import MALFORMED, NON_FINITE, Inbox
from racecar_hw.net.topics import Topic
from racecar_hw.runtime.refusals import Refusals

if TYPE_CHECKING:
    from racecar_hw.net.dds_bridge import DdsStats

SURFACE = "dds"
#: Samples taken from a reader per call.
TAKE_N = 64
#: How long a command row's thread waits for a sample before it looks whether to stop (ns).
PUMP_WAIT_NS = 200_000_000
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
        self._pumps: list[threading.Thread] = []
        self._stopping = threading.Event()

    def receiver(self, row: Topic, name: str) -> Callable[[Any], None]:
        """What takes ``row``'s samples from a reader (a listener's callback, or a pump's step);
        ``name`` is the row's full ROS name, for the refusals."""
        cls, topic = row.msgtype, row.bus
        stats, lock, inbox = self.stats, self.lock, self.inbox
        accept = self.accepts_commands
        refusals = self.refusals
        outcome = {None: "received", MALFORMED: "malformed", NON_FINITE: "non_finite"}

        def receive(reader: Any) -> None:
            try:
                samples = reader.take(TAKE_N)
            except Exception:  # noqa: BLE001 - a reader being deleted at shutdown
                return
            for sample in samples:
                data = getattr(sample, "data", None)
                if data is None:  # an instance state change (a writer went away), no data
                    continue
                if not accept:
                    with lock:
                        stats.refused += 1
                    refusals.note(SURFACE, name, _UNAUTHENTICATED)
                    continue
                field = outcome.get(inbox.offer_cdr(SURFACE, topic, cls, data), "refused")
                with lock:
                    setattr(stats, field, getattr(stats, field) + 1)

        return receive

    def add_pump(self, participant: Any, row: Topic, name: str, reader: Any) -> None:
        """A thread for a command row's ``reader`` (started by :meth:`start`)."""
        self._pumps.append(threading.Thread(target=self._pump, args=(participant, row, name, reader),
                                            daemon=True, name=f"dds-in {row.ros}"))

    def start(self) -> None:
        self._stopping.clear()
        for pump in self._pumps:
            pump.start()

    def stop(self) -> None:
        """Stop every pump (each wakes within PUMP_WAIT_NS) and forget them."""
        self._stopping.set()
        for pump in self._pumps:
            if pump.is_alive():
                pump.join(5.0)
        self._pumps.clear()

    def _pump(self, participant: Any, row: Topic, name: str, reader: Any) -> None:
        """A command row's thread: wait (in C) for a sample, take the newest, rest one period."""
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet  # noqa: PLC0415

        receive = self.receiver(row, name)
        waitset = WaitSet(participant)
        waitset.attach(ReadCondition(reader, SampleState.NotRead | ViewState.Any | InstanceState.Any))
        while not self._stopping.is_set():
            try:
                if waitset.wait(PUMP_WAIT_NS) <= 0:
                    continue
            except Exception:  # noqa: BLE001 - the participant is gone: the thread ends
                return
            receive(reader)
            self._stopping.wait(self.period_s)


__all__ = ["PUMP_WAIT_NS", "SURFACE", "TAKE_N", "DdsReceiver"]
