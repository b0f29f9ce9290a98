"""The DDS interface's inbound side: samples from Cyclone's readers into the daemon's inbox.

A command row's reader keeps only its newest sample (KEEP_LAST 1, in Cyclone's C code, without the
GIL) and one thread for all command rows (the *pump*) takes it at most once per control period
(``period_s``, s) per row, so a flood of ``/cmd_vel`` costs no Python work per message. The pump
waits (in C) on one WaitSet holding every command reader's ReadCondition and a guard condition
that :meth:`DdsReceiver.stop` sets. A sample that comes a period or more after the row's last take
is taken at once; one that comes sooner has its row detached from the WaitSet until the period
is over (its rest), then the newest is taken. So the other rows are still taken as soon as a
sample arrives, an idle interface costs nothing, a client answering every scan (40 Hz) costs the
pump one wake-up per command, and a flood at most two per period. The e-stop and its release are never
coalesced: Cyclone calls their readers' listeners for every sample, in order. Every sample's CDR
payload is decoded and checked by the :class:`~racecar_hw.net.inbox.Inbox`; without
``accepts_commands`` (a non-loopback interface) each is refused and counted instead.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from racecar_hw.base.clock import monotonic
from racecar_hw.net.inbox import MALFORMED, NON_FINITE, Inbox
from racecar_hw.net.topics import Topic
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.runtime.threadname import name_this_thread

if TYPE_CHECKING:
    from racecar_hw.net.dds_bridge import DdsStats

SURFACE = "dds"
#: Samples taken from a reader per call.
TAKE_N = 64
#: The longest the pump waits for a sample before it looks whether to stop (ns; stop also wakes it).
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
        self._participant: Any = None
        self._rows: list[tuple[Topic, str, Any]] = []
        self._pump_thread: threading.Thread | None = None
        self._wake: Any = None  # the pump's GuardCondition, once it runs
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
        """Have the pump (started by :meth:`start`) take a command row's ``reader``."""
        self._participant = participant
        self._rows.append((row, name, reader))

    def start(self) -> None:
        self._stopping.clear()
        if self._rows and self._pump_thread is None:
            rows = list(self._rows)
            self._pump_thread = threading.Thread(target=self._pump, args=(self._participant, rows),
                                                 daemon=True, name="dds-in")
            self._pump_thread.start()

    def stop(self) -> None:
        """Stop the pump (woken at once by its guard condition) and forget the rows."""
        self._stopping.set()
        wake = self._wake
        if wake is not None:
            try:
                wake.set(True)
            except Exception:  # noqa: BLE001 - the participant is gone already: the pump has ended
                pass
        if self._pump_thread is not None and self._pump_thread.is_alive():
            self._pump_thread.join(5.0)
        self._pump_thread = None
        self._wake = None
        self._rows.clear()

    def _pump(self, participant: Any, rows: list[tuple[Topic, str, Any]]) -> None:
        """The command rows' thread: wait (in C) for a sample on any row, take the newest of each
        row that has one and was last taken a period ago or more, and rest the others until then."""
        from cyclonedds.core import (  # noqa: PLC0415
            GuardCondition,
            InstanceState,
            ReadCondition,
            SampleState,
            ViewState,
            WaitSet,
        )

        name_this_thread()
        mask = SampleState.NotRead | ViewState.Any | InstanceState.Any
        try:
            waitset = WaitSet(participant)
            self._wake = GuardCondition(participant)
            waitset.attach(self._wake)
            pumps = [(ReadCondition(reader, mask), self.receiver(row, name), reader)
                     for row, name, reader in rows]
            for condition, _, _ in pumps:
                waitset.attach(condition)
        except Exception:  # noqa: BLE001 - closed before the pump started
            return
        resting: dict[int, float] = {}  # row index -> monotonic time (s) it may be taken again
        taken: dict[int, float] = {}    # row index -> monotonic time (s) of its last take
        period_s = self.period_s
        while not self._stopping.is_set():
            try:
                timeout_ns = PUMP_WAIT_NS
                if resting:
                    now = monotonic()
                    for i, due in list(resting.items()):
                        if due <= now:
                            waitset.attach(pumps[i][0])
                            del resting[i]
                    if resting:
                        timeout_ns = min(timeout_ns, max(0, int((min(resting.values()) - now) * 1e9)))
                if waitset.wait(timeout_ns) <= 0 or self._stopping.is_set():
                    continue
                now = monotonic()
                for i, (condition, receive, reader) in enumerate(pumps):
                    if i not in resting and condition.triggered:
                        due = taken.get(i, -period_s) + period_s
                        if now >= due:
                            receive(reader)
                            taken[i] = now
                        else:  # sooner than a period after the last: the newest goes at its end
                            waitset.detach(condition)
                            resting[i] = due
            except Exception:  # noqa: BLE001 - the participant is gone: the thread ends
                return


__all__ = ["PUMP_WAIT_NS", "SURFACE", "TAKE_N", "DdsReceiver"]
