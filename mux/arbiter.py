"""Arbitration of the command mux as data: a state table and a pure choice function.

The mux is in one of three states::

    state      output                      leaves on
    RUNNING    the winning input, or idle  ENGAGE_ESTOP -> ESTOP, ERROR -> FAULT
    ESTOP      zero speed, centred         RELEASE_ESTOP -> RUNNING, ERROR -> FAULT
    FAULT      zero speed, centred         RESET -> ESTOP (then an explicit release drives)

Every (state, event) pair is in :data:`TRANSITIONS`; pairs that do not move stay where they
are, so an e-stop or release cannot get the mux out of FAULT, and nothing but RESET can. The
node refuses RELEASE_ESTOP while the e-stop topic still says true (see ``docs/mux.md``).

In RUNNING, :func:`arbitrate` picks the input that wins at ``now_ns``:

* an input is *fresh* when it has a message and (its timeout is 0, or the message is no older
  than the timeout); age equal to the timeout is still fresh, as in twist_mux;
* a lock is *engaged* when its last message said true, or when its timeout is > 0 and it has been
  silent longer than that, including never having spoken (deadman: a lock that must be held
  open starts closed);
* an engaged lock masks every input of strictly lower priority than its own;
* the highest-priority fresh unmasked input wins; with none, the output is the *idle* command:
  zero speed and centred steering (or the last winner's steering when
  ``hold_steering_when_idle``), never the last command.

Everything here is a pure function of its arguments; times are integer monotonic nanoseconds.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from mux.params import MuxParams
from racecar_hw.base.clock import NS_PER_S, nanoseconds
from racecar_hw.base.messages import AckermannDrive

IDLE = "idle"
ESTOP = "estop"
FAULT = "fault"


class MuxState(enum.Enum):
    """What the mux is doing with its inputs."""

    RUNNING = "running"  #: forwarding the winning input (or idle)
    ESTOP = "estop"  #: latched stop until an explicit release
    FAULT = "fault"  #: an unexpected error happened; stopped until reset


class MuxEvent(enum.Enum):
    """Things that move the mux between states."""

    ENGAGE_ESTOP = "engage_estop"
    RELEASE_ESTOP = "release_estop"
    ERROR = "error"
    RESET = "reset"


_R, _E, _F = MuxState.RUNNING, MuxState.ESTOP, MuxState.FAULT

#: The complete state table: TRANSITIONS[state][event] is the next state.
TRANSITIONS: Mapping[MuxState, Mapping[MuxEvent, MuxState]] = {
    _R: {MuxEvent.ENGAGE_ESTOP: _E, MuxEvent.RELEASE_ESTOP: _R, MuxEvent.ERROR: _F,
         MuxEvent.RESET: _R},
    _E: {MuxEvent.ENGAGE_ESTOP: _E, MuxEvent.RELEASE_ESTOP: _R, MuxEvent.ERROR: _F,
         MuxEvent.RESET: _E},
    _F: {MuxEvent.ENGAGE_ESTOP: _F, MuxEvent.RELEASE_ESTOP: _F, MuxEvent.ERROR: _F,
         MuxEvent.RESET: _E},
}


class MuxStateMachine:
    """The current :class:`MuxState` and why the mux is stopped, driven by :data:`TRANSITIONS`."""

    def __init__(self, state: MuxState = MuxState.RUNNING, reason: str = "") -> None:
        self.state = state
        #: why the mux entered ESTOP or FAULT ("" while RUNNING)
        self.reason = reason

    def process(self, event: MuxEvent, reason: str = "") -> MuxState:
        """Apply ``event``; a move into ESTOP or FAULT records ``reason``. Returns the new state."""
        new = TRANSITIONS[self.state][event]
        if new is not self.state:
            if new is MuxState.RUNNING:
                self.reason = ""
            elif new is MuxState.ESTOP and self.state is MuxState.FAULT:
                self.reason = f"reset after fault ({self.reason})"
            else:
                self.reason = reason
            self.state = new
        return new


@dataclass(frozen=True, slots=True)
class InputSpec:
    """One input as arbitration sees it (``timeout_ns`` is never 0 for an input: every input expires,
    :class:`~mux.params.InputParams`)."""

    name: str
    priority: int
    timeout_ns: int


@dataclass(frozen=True, slots=True)
class LockSpec:
    """One lock as arbitration sees it; ``timeout_ns`` > 0 makes it a deadman."""

    name: str
    priority: int
    timeout_ns: int


class MuxTable:
    """Inputs sorted by priority, highest first, and locks, compiled once from :class:`MuxParams`.

    The node keeps its per-input and per-lock samples in this order (``index_of``).
    """

    def __init__(self, inputs: Sequence[InputSpec], locks: Sequence[LockSpec] = (),
                 hold_steering_when_idle: bool = False) -> None:
        self.inputs: tuple[InputSpec, ...] = tuple(sorted(inputs, key=lambda s: -s.priority))
        self.locks: tuple[LockSpec, ...] = tuple(locks)
        self.names: tuple[str, ...] = tuple(s.name for s in self.inputs)
        self.lock_names: tuple[str, ...] = tuple(s.name for s in self.locks)
        self.index_of: dict[str, int] = {name: i for i, name in enumerate(self.names)}
        self.hold_steering_when_idle = hold_steering_when_idle

    @classmethod
    def from_params(cls, params: MuxParams) -> MuxTable:
        """The table for ``params`` (inputs re-ordered by priority; locks as listed)."""
        inputs = [InputSpec(p.name, p.priority, nanoseconds(p.timeout_s)) for p in params.inputs]
        locks = [LockSpec(p.name, p.priority, nanoseconds(p.timeout_s)) for p in params.locks]
        return cls(inputs, locks, params.hold_steering_when_idle)


@dataclass(frozen=True, slots=True)
class Arbitration:
    """The outcome of one arbitration.

    ``drive`` is the chosen command (shared with the input's message: do not mutate it).
    ``source`` is an input name, ``"idle"``, ``"estop"`` or ``"fault"``. ``masked`` lists inputs
    masked by an engaged lock, ``engaged_locks`` the engaged locks. ``ages_ns`` holds each input's
    message age in ``names`` order (None: never received).
    """

    drive: AckermannDrive
    source: str
    state: MuxState
    masked: tuple[str, ...]
    engaged_locks: tuple[str, ...]
    names: tuple[str, ...]
    ages_ns: tuple[int | None, ...]

    def ages_s(self) -> dict[str, float | None]:
        """Each input's message age in seconds (None: never received)."""
        return {n: None if a is None else a / NS_PER_S for n, a in zip(self.names, self.ages_ns, strict=True)}


def is_fresh(timeout_ns: int, received_ns: int | None, now_ns: int) -> bool:
    """Whether a message received at ``received_ns`` still counts at ``now_ns``."""
    if received_ns is None:
        return False
    return timeout_ns == 0 or now_ns - received_ns <= timeout_ns


def lock_engaged(spec: LockSpec, value: bool | None, received_ns: int | None, now_ns: int) -> bool:
    """Whether a lock is engaged: it said true, or (deadman) it is silent past its timeout."""
    if spec.timeout_ns > 0 and not is_fresh(spec.timeout_ns, received_ns, now_ns):
        return True
    return bool(value)


def arbitrate(
    table: MuxTable,
    state: MuxState,
    drives: Sequence[AckermannDrive | None],
    received_ns: Sequence[int | None],
    lock_values: Sequence[bool | None],
    lock_received_ns: Sequence[int | None],
    now_ns: int,
    held_steering: float = 0.0,
) -> Arbitration:
    """The command that wins at ``now_ns``.

    ``drives`` and ``received_ns`` hold each input's last command and its arrival time, in
    ``table.inputs`` order (None: nothing received); ``lock_values`` and ``lock_received_ns`` the
    same for ``table.locks``. ``held_steering`` is the steering used when idle with
    ``hold_steering_when_idle``.
    """
    mask_priority = -1
    engaged: tuple[str, ...] = ()
    for i, lock in enumerate(table.locks):
        if lock_engaged(lock, lock_values[i], lock_received_ns[i], now_ns):
            engaged += (lock.name,)
            if lock.priority > mask_priority:
                mask_priority = lock.priority
    first_masked = len(table.inputs)
    winner = -1
    for i, spec in enumerate(table.inputs):
        if spec.priority < mask_priority:
            first_masked = i
            break
        if winner < 0 and drives[i] is not None and is_fresh(spec.timeout_ns, received_ns[i], now_ns):
            winner = i
    ages = tuple(None if r is None else now_ns - r for r in received_ns)
    masked = table.names[first_masked:]
    if state is not MuxState.RUNNING:
        source = ESTOP if state is MuxState.ESTOP else FAULT
        return Arbitration(AckermannDrive(), source, state, masked, engaged, table.names, ages)
    if winner >= 0:
        drive = drives[winner]
        assert drive is not None
        return Arbitration(drive, table.names[winner], state, masked, engaged, table.names, ages)
    steering = held_steering if table.hold_steering_when_idle else 0.0
    return Arbitration(AckermannDrive(steering_angle=steering), IDLE, state, masked, engaged,
                       table.names, ages)


def stopped(table: MuxTable, state: MuxState = MuxState.FAULT) -> Arbitration:
    """A zero, centred arbitration for ``state`` that needs no samples (the fault path)."""
    source = FAULT if state is MuxState.FAULT else ESTOP
    return Arbitration(AckermannDrive(), source, state, (), (), table.names,
                       (None,) * len(table.names))
