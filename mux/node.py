"""The command mux on the bus: subscriptions, e-stop latch, diagnostics and the fixed-rate output.

:class:`CommandMux` keeps the last command of each input and the state of each lock as they
arrive, and on every tick arbitrates (:mod:`mux.arbiter`), runs the optional filters (the daemon
puts the safety controller there), applies the :class:`~mux.limiter.RateLimiter` and publishes an
``AckermannDriveStamped`` (frame ``base_link``) on ``output_topic`` whatever the inputs do.

A latched e-stop outputs zero speed and centred steering from its first tick on, past the limiter:
the VESC gets its brake command at once instead of a ramp at ``max_decel_mps2``. Stop is for anyone,
release is for an operator (:mod:`mux.estop`): every request names its :class:`~mux.estop.Origin`,
the latch remembers who engaged it (:attr:`CommandMux.estop`), and a release from the plain release
topic is refused unless only the e-stop topic engaged the latch. Messages on the e-stop topics that
a network surface hands over with :meth:`CommandMux.publish_from` carry its origin; any other
publisher on the bus counts as ``local``. Refused releases are counted and logged rate-limited
(:class:`~racecar_hw.runtime.refusals.Refusals`, surface ``estop``).

Any unexpected exception inside the mux (a subscriber callback, arbitration, a filter, the
limiter, diagnostics) is logged and moves the mux to FAULT: zero speed, centred steering, limiter
bypassed, until :meth:`CommandMux.reset` (which leaves it e-stopped) and then
:meth:`CommandMux.release_estop`.

Times are monotonic integer nanoseconds from the injected ``clock``; output stamps are wall time.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

from mux.arbiter import (
    FAULT,
    Arbitration,
    MuxEvent,
    MuxState,
    MuxStateMachine,
    MuxTable,
    arbitrate,
    is_fresh,
    lock_engaged,
    stopped,
)
from mux.estop import DAEMON, DAEMON_ORIGIN, EstopRecord, Origin, release_refusal
from mux.limiter import RateLimiter
from mux.params import MuxParams
from racecar_hw.base.bus import Bus, Subscription
from racecar_hw.base.clock import NS_PER_S, monotonic_ns, wall_ns
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    Bool,
    DiagnosticArray,
    DiagnosticStatus,
    KeyValue,
    String,
    stamp_now,
)
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: ``filter(drive, source, now_ns) -> drive``, run between arbitration and the limiter. It must
#: return a command (a new one, or ``drive`` unchanged) and must not mutate ``drive``.
Filter = Callable[[AckermannDrive, str, int], AckermannDrive]

OUTPUT_FRAME = "base_link"
_MAX_SWITCHES = 10_000


class CommandMux:
    """The priority Ackermann command mux bound to ``bus``; see :mod:`mux.arbiter` for the rules.

    Use from the bus's event loop thread only. ``clock`` gives monotonic ns (message arrival,
    ages), ``wall_clock`` the output stamps. The daemon's control loop
    (:class:`~racecar_hw.runtime.ticker.PeriodicTimer`) calls :meth:`step` at ``rate_hz``.
    ``steering_range``: the (right, left) steering angles (rad) the car drives at full lock, and
    ``speed_max_mps`` the fastest it is sent (m/s, either way); the output never asks for more
    (:class:`~mux.limiter.RateLimiter`).
    """

    def __init__(self, bus: Bus, params: MuxParams | None = None, *,
                 clock: Callable[[], int] = monotonic_ns,
                 wall_clock: Callable[[], int] = wall_ns,
                 refusals: Refusals | None = None,
                 steering_range: tuple[float, float] = (-math.inf, math.inf),
                 speed_max_mps: float = math.inf) -> None:
        self.bus = bus
        self.params = params = params if params is not None else MuxParams()
        self.table = MuxTable.from_params(params)
        self.limiter = RateLimiter.from_params(params, steering_range, speed_max_mps)
        self.machine = MuxStateMachine()
        self._clock = clock
        self._wall_clock = wall_clock
        #: refused releases, counted per (``estop``, origin, reason) and logged rate-limited
        self.refusals = refusals if refusals is not None else Refusals()
        #: the current latch (None while running), or the last one after its release
        self.estop: EstopRecord | None = None
        #: e-stop releases refused so far
        self.release_refusals = 0
        #: the last refused release: ``"<origin>: <reason>"`` ("" before the first)
        self.last_refusal = ""
        #: the origin of the message being published on the bus, while :meth:`publish_from` runs
        self._origin: Origin | None = None
        if params.start_estopped:
            self.engage_estop("start_estopped", Origin(DAEMON, "mux.start_estopped"))
        #: the clock (ns) at creation; :attr:`switches` are seconds since it
        self.start_ns = clock()
        n, m = len(self.table.inputs), len(self.table.locks)
        self._drives: list[AckermannDrive | None] = [None] * n
        self._received: list[int | None] = [None] * n
        self._lock_values: list[bool | None] = [None] * m
        self._lock_received: list[int | None] = [None] * m
        self._held_steering = 0.0
        self._estop_asserted = False
        self._unannounced: str | None = None  # a source switched to, not yet on active_topic
        #: (seconds since the mux was created, new source), for reports; the first entry is
        #: the first arbitration's source. Oldest entries are dropped past 10 000.
        self.switches: list[tuple[float, str]] = []
        #: the current source (None before the first arbitration)
        self.source: str | None = None
        self.last_output: AckermannDriveStamped | None = None
        self.outputs = 0
        #: output deadlines skipped because the loop fell behind
        self.overruns = 0
        self.faults = 0
        #: per input name: messages with a non-finite speed or steering (replaced by a stop)
        self.rejected: dict[str, int] = dict.fromkeys(self.table.names, 0)
        self._subs: list[Subscription] = []
        self._subscribe()

    # --- bus wiring ------------------------------------------------------------------------

    def _subscribe(self) -> None:
        p = self.params
        self.bus.declare(p.output_topic, AckermannDriveStamped)
        self.bus.declare(p.active_topic, String)
        self.bus.declare(p.diagnostics_topic, DiagnosticArray)
        for inp in p.inputs:
            self.bus.declare(inp.topic, AckermannDriveStamped)
            index = self.table.index_of[inp.name]
            self._subs.append(self.bus.subscribe(inp.topic, self._input_callback(index)))
        for index, lock in enumerate(p.locks):
            self.bus.declare(lock.topic, Bool)
            self._subs.append(self.bus.subscribe(lock.topic, self._lock_callback(index)))
        self.bus.declare(p.estop_topic, Bool)
        self.bus.declare(p.estop_release_topic, Bool)
        self._subs.append(self.bus.subscribe(p.estop_topic, self._guarded(self._on_estop, "e-stop")))
        self._subs.append(self.bus.subscribe(p.estop_release_topic,
                                             self._guarded(self._on_release, "e-stop release")))

    def close(self) -> None:
        """Unsubscribe from the bus (safe to call twice)."""
        for sub in self._subs:
            sub.close()
        self._subs.clear()

    def __enter__(self) -> CommandMux:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _guarded(self, handler: Callable[[Any], None], what: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            try:
                handler(msg)
            except Exception as err:
                self._fail(f"{what} message", err)
        return callback

    def _input_callback(self, index: int) -> Callable[[Any], None]:
        name = self.table.names[index]

        def take(msg: AckermannDriveStamped) -> None:
            drive = msg.drive
            if not (math.isfinite(drive.speed) and math.isfinite(drive.steering_angle)):
                count = self.rejected[name] = self.rejected[name] + 1
                if count == 1 or count % 100 == 0:
                    log.warning("mux input %s sent a non-finite command (speed %r, steering %r); "
                                "treated as a stop (%d so far)", name, drive.speed,
                                drive.steering_angle, count)
                drive = AckermannDrive()
            self._drives[index] = drive
            self._received[index] = self._clock()
        return self._guarded(take, f"input {name}")

    def _lock_callback(self, index: int) -> Callable[[Any], None]:
        def take(msg: Bool) -> None:
            self._lock_values[index] = bool(msg.data)
            self._lock_received[index] = self._clock()
        return self._guarded(take, f"lock {self.table.locks[index].name}")

    def publish_from(self, origin: Origin, topic: str, msg: Any) -> None:
        """Publish ``msg`` on the bus as coming from ``origin``: the e-stop topics' handlers see it.

        For surfaces that hand over an e-stop or release (the network bridges); recorders and the
        live view see the message as any other.
        """
        self._origin = origin
        try:
            self.bus.publish(topic, msg)
        finally:
            self._origin = None

    def _topic_origin(self, topic: str) -> Origin:
        return self._origin if self._origin is not None else Origin("local", topic)

    def _on_estop(self, msg: Bool) -> None:
        self._estop_asserted = bool(msg.data)
        if self._estop_asserted:
            self.engage_estop(f"{self.params.estop_topic} said true",
                              self._topic_origin(self.params.estop_topic))

    def _on_release(self, msg: Bool) -> None:
        if msg.data:
            self.release_estop(self._topic_origin(self.params.estop_release_topic))

    def last_command(self, name: str | None) -> AckermannDrive | None:
        """The last command input ``name`` sent (None: never, or not an input: idle, estop, fault)."""
        index = self.table.index_of.get(name) if name is not None else None
        return None if index is None else self._drives[index]

    # --- e-stop and fault ------------------------------------------------------------------

    @property
    def state(self) -> MuxState:
        """RUNNING, ESTOP or FAULT."""
        return self.machine.state

    def _latched(self) -> EstopRecord | None:
        """The record of the current latch (None while running)."""
        record = self.estop
        return record if record is not None and record.released_by is None else None

    def engage_estop(self, reason: str = "requested", origin: Origin = DAEMON_ORIGIN) -> bool:
        """Latch the e-stop: zero speed, centred steering until :meth:`release_estop`.

        Anyone may engage it. ``origin`` says who (logged, kept in :attr:`estop`, shown in the
        diagnostics). The next output (:meth:`step`) already brakes: the e-stop bypasses the rate
        limiter. Returns True when this latched it (it was running).
        """
        before = self.machine.state
        self.machine.process(MuxEvent.ENGAGE_ESTOP, reason)
        record = self._latched()
        if record is None:
            self.estop = EstopRecord(origin, self._wall_clock(), reason)
            if before is MuxState.RUNNING:
                log.warning("mux e-stop engaged by %s: %s", origin, reason)
            else:
                log.warning("mux e-stop engaged by %s while in %s: %s", origin, before.value, reason)
            return before is MuxState.RUNNING
        if record.engaged_again(origin):
            log.warning("mux e-stop engaged again by %s while latched: %s", origin, reason)
        return False

    def release_refusal(self, origin: Origin = DAEMON_ORIGIN) -> str | None:
        """Why ``origin`` may not release the e-stop now (:func:`mux.estop.release_refusal`), or None."""
        return release_refusal(origin, self._latched(), self.params.estop_release_sources,
                               in_fault=self.machine.state is MuxState.FAULT,
                               asserted=self._estop_asserted)

    def release_estop(self, origin: Origin = DAEMON_ORIGIN) -> bool:
        """Release a latched e-stop; True when the mux is now RUNNING.

        Refused (False; counted and logged rate-limited, surface ``estop``) in FAULT (call
        :meth:`reset` first), while the last message on ``estop_topic`` said true, for a source
        ``estop_release_sources`` leaves out, and for the release topic when an operator, a
        ``start_estopped`` or the daemon engaged the latch (:mod:`mux.estop`).
        """
        state = self.machine.state
        why = self.release_refusal(origin)
        if why is not None:
            self.release_refusals += 1
            self.last_refusal = f"{origin}: {why}"
            self.refusals.note("estop", str(origin), f"release refused: {why}")
            return False
        self.machine.process(MuxEvent.RELEASE_ESTOP)
        record = self._latched()
        was = record.text() if record is not None else "latched"
        if record is not None:
            record.released_by = origin
            record.released_at_wall_ns = self._wall_clock()
        if state is MuxState.ESTOP:
            log.warning("mux e-stop released by %s (it was %s)", origin, was)
        return True

    def reset(self) -> MuxState:
        """Leave FAULT for ESTOP (a release is still needed to drive); returns the new state.

        The latch is then the daemon's: only an operator releases it.
        """
        before = self.machine.state
        state = self.machine.process(MuxEvent.RESET)
        if before is MuxState.FAULT:
            self.estop = EstopRecord(Origin(DAEMON, "fault reset"), self._wall_clock(), self.machine.reason)
            log.warning("mux fault reset; e-stop stays engaged until an operator releases it")
        return state

    def _fail(self, where: str, err: BaseException) -> None:
        self.faults += 1
        if self.machine.state is not MuxState.FAULT:
            log.error("mux fault in %s: %r; output stopped until reset", where, err, exc_info=err)
        else:
            log.debug("mux fault in %s while in fault: %r", where, err, exc_info=err)
        self.machine.process(MuxEvent.ERROR, f"{where}: {err!r}")

    # --- arbitration and output ------------------------------------------------------------

    def arbitrate(self, now_ns: int | None = None) -> Arbitration:
        """The winning command at ``now_ns`` (default: the clock); records source switches and
        announces them on ``active_topic``."""
        arb = self._arbitrate(self._clock() if now_ns is None else now_ns)
        self._announce_switch()
        return arb

    def _arbitrate(self, now: int) -> Arbitration:
        """The winning command at ``now``; a source switch is recorded and logged, and announced
        on ``active_topic`` by the next :meth:`_announce_switch`."""
        try:
            arb = arbitrate(self.table, self.machine.state, self._drives, self._received,
                            self._lock_values, self._lock_received, now, self._held_steering)
            if arb.source in self.table.index_of:
                self._held_steering = arb.drive.steering_angle
            elif arb.source != "idle":
                self._held_steering = 0.0
            if arb.source != self.source:
                self._switch(arb, now)
            return arb
        except Exception as err:
            self._fail("arbitration", err)
            arb = stopped(self.table)
            if self.source != FAULT:
                self.source = FAULT
                self.switches.append(((now - self.start_ns) / NS_PER_S, FAULT))
            return arb

    def _switch(self, arb: Arbitration, now_ns: int) -> None:
        previous = self.source
        self.source = arb.source
        if len(self.switches) >= _MAX_SWITCHES:
            del self.switches[: _MAX_SWITCHES // 2]
        t = (now_ns - self.start_ns) / NS_PER_S
        self.switches.append((t, arb.source))
        log.info("mux source %s -> %s at %.3f s; %s", previous, arb.source, t, self.summary(arb))
        self._unannounced = arb.source

    def _announce_switch(self) -> None:
        """Publish the source switched to since the last announcement on ``active_topic``."""
        source = self._unannounced
        if source is not None:
            self._unannounced = None
            self.bus.publish(self.params.active_topic, String(source))

    def step(self, now_ns: int | None = None, filters: Sequence[Filter] = (),
             periods: int = 1) -> AckermannDriveStamped:
        """One output tick: arbitrate, filter, limit, publish on ``output_topic``; returns it.

        ``periods`` is how many output periods passed since the previous tick (more than 1 only
        when the control loop skipped deadlines, counted in :attr:`overruns`); the limiter advances
        by that many fixed periods. :meth:`decide` and :meth:`publish_output` are its two halves,
        for a caller that writes the command to the motor in between.
        """
        msg = self.decide(now_ns, filters, periods)
        self.publish_output(msg)
        return msg

    def decide(self, now_ns: int | None = None, filters: Sequence[Filter] = (),
               periods: int = 1) -> AckermannDriveStamped:
        """The output :meth:`step` publishes, taken (the limiter steps, :attr:`last_output` is set)
        but not yet published: no bus publication happens until :meth:`publish_output`."""
        now = self._clock() if now_ns is None else now_ns
        self.overruns += periods - 1
        arb = self._arbitrate(now)
        return self._output(now, arb.drive, arb.source, filters, periods, commit=True)

    def step_early(self, source: str, now_ns: int | None = None,
                   filters: Sequence[Filter] = ()) -> AckermannDriveStamped | None:
        """Publish now what the next tick would publish, if ``source`` wins arbitration; else None.

        For a command that just arrived from a remote client: it reaches the output (and the VESC)
        without waiting up to a period for the tick. The limiter previews its next step without
        taking it, so the next tick takes the same step and the limits hold; the output is at most
        one step ahead of the limiter, as if that tick had come early.
        """
        msg = self.decide_early(source, now_ns, filters)
        if msg is not None:
            self.publish_output(msg)
        return msg

    def decide_early(self, source: str, now_ns: int | None = None,
                     filters: Sequence[Filter] = ()) -> AckermannDriveStamped | None:
        """What :meth:`step_early` publishes (or None), not yet published (:meth:`publish_output`)."""
        now = self._clock() if now_ns is None else now_ns
        arb = self._arbitrate(now)
        if arb.source != source or self.machine.state is not MuxState.RUNNING:
            return None
        return self._output(now, arb.drive, arb.source, filters, 1, commit=False)

    def cut(self, drive: AckermannDrive, now_ns: int | None = None) -> AckermannDriveStamped:
        """A safety cut between ticks: ``drive``, slower than :attr:`last_output`, as the output now.

        Past arbitration and the filters (the safety controller decided ``drive`` from the last
        output); the limiter is clamped to its speed (:meth:`RateLimiter.clamp`), so the next ticks
        cannot raise it again faster than the acceleration limit. Not yet published
        (:meth:`publish_output`). In e-stop or fault the output is the brake, as on every tick.
        """
        now = self._clock() if now_ns is None else now_ns
        self.limiter.clamp(drive.speed)
        return self._output(now, drive, self.source or "idle", (), 1, commit=True)

    def publish_output(self, msg: AckermannDriveStamped) -> None:
        """Publish a source switch on ``active_topic`` and then ``msg`` on ``output_topic``."""
        try:
            self._announce_switch()
            self.bus.publish(self.params.output_topic, msg)
        except Exception as err:
            self._fail("output publish", err)

    def _output(self, now: int, drive: AckermannDrive, source: str, filters: Sequence[Filter],
                periods: int, commit: bool) -> AckermannDriveStamped:
        out: AckermannDrive | None = None
        if self.machine.state is not MuxState.FAULT:
            try:
                for f in filters:
                    drive = f(drive, source, now)
                if self.machine.state is MuxState.RUNNING:
                    limit = self.limiter.limit if commit else self.limiter.preview
                    out = limit(drive, periods)
            except Exception as err:
                self._fail("output filter or limiter", err)
        if out is None:
            # e-stop or fault: brake and centre at once, past the limiter, which starts again from
            # standstill after a release or reset
            self.limiter.reset()
            out = AckermannDrive()
        msg = AckermannDriveStamped(stamp_now(OUTPUT_FRAME, self._wall_clock()), out)
        self.last_output = msg
        self.outputs += 1
        return msg

    # --- diagnostics -----------------------------------------------------------------------

    def summary(self, arb: Arbitration) -> str:
        """One line: each input's age and mask, lock states, e-stop; for logs."""
        parts = []
        for name, age in zip(arb.names, arb.ages_ns, strict=True):
            text = "never" if age is None else f"{age / NS_PER_S:.2f}s"
            parts.append(f"{name} {text}{' masked' if name in arb.masked else ''}")
        locks = ", ".join(arb.engaged_locks) or "none"
        estop = self.machine.reason if self.machine.state is not MuxState.RUNNING else "off"
        return f"inputs: {', '.join(parts)}; engaged locks: {locks}; {self.machine.state.value}: {estop}"

    def diagnostics(self, now_ns: int | None = None) -> DiagnosticArray:
        """The mux's diagnostic status at ``now_ns``: state, source, inputs, locks, counters."""
        now = self._clock() if now_ns is None else now_ns
        state = self.machine.state
        arb = arbitrate(self.table, state, self._drives, self._received, self._lock_values,
                        self._lock_received, now, self._held_steering)
        values = [KeyValue("state", state.value), KeyValue("active", self.source or arb.source)]
        if state is not MuxState.RUNNING:
            values.append(KeyValue("reason", self.machine.reason))
        values.append(KeyValue("estop_topic_asserted", str(self._estop_asserted).lower()))
        values.append(KeyValue("estop", self.estop_text()))
        values.append(KeyValue("estop_release_refusals", str(self.release_refusals)))
        if self.last_refusal:
            values.append(KeyValue("estop_last_refusal", self.last_refusal))
        for i, spec in enumerate(self.table.inputs):
            age = arb.ages_ns[i]
            if age is None:
                text = "never received"
            else:
                fresh = is_fresh(spec.timeout_ns, self._received[i], now)
                text = f"{'fresh' if fresh else 'expired'}, age {age / NS_PER_S:.3f} s"
            if spec.name in arb.masked:
                text += ", masked"
            rejected = self.rejected[spec.name]
            if rejected:
                text += f", {rejected} non-finite"
            values.append(KeyValue(f"input {spec.name} (priority {spec.priority})", text))
        for i, lock in enumerate(self.table.locks):
            received = self._lock_received[i]
            if not lock_engaged(lock, self._lock_values[i], received, now):
                text = "released"
            elif received is None:
                text = "engaged (never heard: deadman)"
            elif lock.timeout_ns and not is_fresh(lock.timeout_ns, received, now):
                text = f"engaged (silent {(now - received) / NS_PER_S:.3f} s: deadman)"
            else:
                text = "engaged"
            values.append(KeyValue(f"lock {lock.name} (priority {lock.priority})", text))
        values += [KeyValue("switches", str(len(self.switches))), KeyValue("outputs", str(self.outputs)),
                   KeyValue("overruns", str(self.overruns)), KeyValue("faults", str(self.faults))]
        level = {MuxState.RUNNING: DiagnosticStatus.OK, MuxState.ESTOP: DiagnosticStatus.WARN,
                 MuxState.FAULT: DiagnosticStatus.ERROR}[state]
        message = (f"active: {arb.source}" if state is MuxState.RUNNING
                   else f"{state.value}: {self.machine.reason}")
        status = DiagnosticStatus(level, "racecar_hw: command mux", message, "", values)
        return DiagnosticArray(stamp_now("", self._wall_clock()), [status])

    def estop_text(self) -> str:
        """``latched by web page (127.0.0.1) at 18:50:01.123``; how the last one ended; or ``never``."""
        return self.estop.text() if self.estop is not None else "never engaged"

    def publish_diagnostics(self, now_ns: int | None = None) -> None:
        """Publish :meth:`diagnostics` on ``diagnostics_topic``."""
        try:
            self.bus.publish(self.params.diagnostics_topic, self.diagnostics(now_ns))
        except Exception as err:
            self._fail("diagnostics", err)


#: The name the daemon wiring uses for the mux node; the same class.
MuxNode = CommandMux
