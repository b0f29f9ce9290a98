"""Who may engage and who may release the latched e-stop: origins, the latch's record, the rule.

**Stop is for anyone, release is for an operator.** Every stop source may engage the e-stop: the
status page, Foxglove, the e-stop topic from a network session (Zenoh; the DDS interface next) or
from code in the daemon, a scenario. Releasing it needs an operator surface (:data:`OPERATORS`: the
status page's hold, Foxglove's release, and the names kept for the gamepad, the ground station and
the keyboard). The plain release topic (``mux.estop_release_topic``) is not an operator: whoever
can reach the network can publish on it, so it releases only an e-stop that was engaged by the
e-stop topic alone (:data:`TOPICS`), and only when ``mux.estop_release_sources`` names its surface.
An e-stop a person pressed is released by a person.

An :class:`Origin` names where a request came from: its ``surface`` (one of :data:`SURFACES`, which
decides what it may do) and ``who`` (an address, a client id, a session; for the log). The mux
keeps an :class:`EstopRecord` per latch: who engaged it first, when (wall ns), every other surface
that engaged it again while it was latched, whether only topics engaged it, and the last release
or refusal. :func:`release_refusal` is the rule as a pure function.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

#: Operator surfaces: a person in front of a control that needs a deliberate act.
OPERATORS: tuple[str, ...] = ("web", "foxglove", "gamepad", "mavlink", "keyboard")
#: The e-stop topics: ``network`` from a network session (Zenoh, DDS), ``local`` from code in the
#: daemon's own process that publishes on the bus (a built-in source, a test).
TOPICS: tuple[str, ...] = ("network", "local")
#: What ``mux.estop_release_sources`` may name.
RELEASE_SOURCES: tuple[str, ...] = OPERATORS + TOPICS
#: The daemon itself (``start_estopped``, a scenario's action, a fault, a direct call in Python):
#: it may always engage and release; it is not reachable from outside the process.
DAEMON = "daemon"
#: Every surface an origin may name.
SURFACES: tuple[str, ...] = (*RELEASE_SOURCES, DAEMON)

#: The reasons a release is refused (stable texts: the refusal counts are kept per reason).
REFUSED_FAULT = "the mux is in fault; reset it first"
REFUSED_ASSERTED = "the e-stop topic still says true"
REFUSED_NOT_ALLOWED = "this source may not release (mux.estop_release_sources)"
REFUSED_OPERATOR_LATCH = "an operator or the daemon latched it; only an operator releases it"

#: Engaging surfaces remembered per latch beyond the first (a flood cannot grow the record).
_MAX_ALSO = 8


@dataclass(frozen=True, slots=True)
class Origin:
    """Where an e-stop or release came from: ``surface`` (:data:`SURFACES`) and ``who`` (free text)."""

    surface: str
    who: str = ""

    def __post_init__(self) -> None:
        if self.surface not in SURFACES:
            raise ValueError(f"unknown e-stop surface {self.surface!r}; surfaces: {', '.join(SURFACES)}")

    @property
    def is_topic(self) -> bool:
        """Whether this is the plain e-stop topic (network or local), not an operator or the daemon."""
        return self.surface in TOPICS

    def __str__(self) -> str:
        if self.is_topic:
            return f"{self.surface} topic ({self.who})" if self.who else f"{self.surface} topic"
        return self.who or self.surface


#: The origin of a call in Python with no other origin named (tests, the simulator's scenarios).
DAEMON_ORIGIN = Origin(DAEMON, "the daemon")


def clock_text(wall_ns: int) -> str:
    """``HH:MM:SS.mmm`` in local time, as the log shows it."""
    seconds, ns = divmod(wall_ns, 1_000_000_000)
    return time.strftime("%H:%M:%S", time.localtime(seconds)) + f".{ns // 1_000_000:03d}"


@dataclass
class EstopRecord:
    """One latch: who engaged it (first, and others while latched), when, and how it ended."""

    by: Origin
    at_wall_ns: int
    reason: str
    #: other origins that engaged it again while it was latched (at most a few, first come)
    also: list[Origin] = field(default_factory=list)
    #: True while every engagement came from an e-stop topic (only then may a topic release it)
    topics_only: bool = True
    engagements: int = 1
    released_by: Origin | None = None
    released_at_wall_ns: int | None = None

    def __post_init__(self) -> None:
        self.topics_only = self.by.is_topic

    def engaged_again(self, origin: Origin) -> bool:
        """Note another engagement; True when ``origin`` is new to this latch (worth a log line)."""
        self.engagements += 1
        self.topics_only = self.topics_only and origin.is_topic
        if origin == self.by or origin in self.also:
            return False
        if len(self.also) < _MAX_ALSO:
            self.also.append(origin)
        return True

    def text(self) -> str:
        """``latched by web page (127.0.0.1) at 18:50:01.123`` (+ others) while latched; after the
        release ``released by ... at ... (latched by ... at ...)``."""
        out = f"latched by {self.by} at {clock_text(self.at_wall_ns)}"
        if self.also:
            out += " (also by " + ", ".join(str(o) for o in self.also) + ")"
        if self.released_by is not None and self.released_at_wall_ns is not None:
            out = f"released by {self.released_by} at {clock_text(self.released_at_wall_ns)} ({out})"
        return out


def release_refusal(origin: Origin, record: EstopRecord | None, allowed: tuple[str, ...] | list[str],
                    *, in_fault: bool = False, asserted: bool = False) -> str | None:
    """Why ``origin`` may not release the latch ``record`` now, or None when it may.

    ``allowed`` is ``mux.estop_release_sources``; ``in_fault`` and ``asserted`` (the e-stop topic's
    last message said true) refuse every origin, the daemon's too.
    """
    if in_fault:
        return REFUSED_FAULT
    if asserted:
        return REFUSED_ASSERTED
    if origin.surface == DAEMON:
        return None
    if origin.surface not in allowed:
        return REFUSED_NOT_ALLOWED
    if origin.is_topic and record is not None and not record.topics_only:
        return REFUSED_OPERATOR_LATCH
    return None
