"""The MAVLink link's UDP sockets: one shared port, the ground station's own socket, drained under a budget.

One UDP socket, bound to ``bind_address:bind_port``, sends and receives; telemetry goes to the
ground station's address, or, when its port is 0, to the port the first authenticated message of
the station came from (:meth:`MavlinkSocket.learn_station`). It never follows other senders.

Floods: the ground station's address has a socket of its own: a second socket on the same port
(``SO_REUSEPORT``), connected to the station, to which the kernel delivers the station's datagrams
in preference to the shared socket, so a flood from other addresses fills only the shared socket's
buffer and cannot push the station's heartbeats out. Each socket is drained each time it is
readable (the station's first), until empty or for ``DRAIN_BUDGET_NS``, looked at after every
datagram; a socket that still has datagrams waiting after that rests for ``DRAIN_PAUSE_S`` (the
kernel drops what overflows its buffer), so a flood takes about 5 % of the event loop at most and
the control loop keeps its time. Datagrams are read in batches (the station's address first within
one); what a spent budget left of a batch is handled first when the socket reads again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from collections.abc import Callable
from typing import Any

from racecar_hw.teleop.mavlink_rx import MAX_DATAGRAM
from racecar_hw.teleop.mavlink_signing import Tally

log = logging.getLogger(__name__)

#: The longest one wake-up drains a socket (ns) before the event loop's other work runs.
DRAIN_BUDGET_NS = 500_000
#: How long a socket that still had datagrams waiting after its budget rests (s): under a flood
#: a socket takes at most budget / (budget + pause) of the loop, about 5 %.
DRAIN_PAUSE_S = 0.010
#: Datagrams read per batch (the station's address is handled first within a batch). The budget
#: is looked at after every datagram, not per batch: one batch of costly datagrams once took 64
#: times the budget.
DRAIN_BATCH = 64
#: Bytes read of a datagram: one more than the decoder takes (a MAVLink 2 frame is at most 280
#: bytes), so that a longer datagram, cut here by the kernel, is still seen to be too long and is
#: refused whole without copying its 64 KiB.
RECV_SIZE = MAX_DATAGRAM + 1

#: Handles one datagram from an address, summing its refusals in the tally.
DatagramHandler = Callable[[bytes, tuple[Any, ...], Tally], None]
#: Datagrams read and not yet handled, with their source addresses.
Batch = list[tuple[bytes, tuple[Any, ...]]]


class MavlinkSocket:
    """The sockets of the link on the event loop; also pymavlink's file (:meth:`write`).

    ``dest`` is the station's (host, port), or None while its port is to be learnt;
    ``on_datagram`` handles each datagram read; ``note_tally`` notes a wake-up's refusals.
    ``counters`` (the link's): ``tx``, ``send_errors``, ``datagrams``, ``station_datagrams``,
    ``drain_rests``.
    """

    def __init__(self, bind: tuple[str, int], dest: tuple[str, int] | None, counters: dict[str, int],
                 on_datagram: DatagramHandler, note_tally: Callable[[Tally], None]) -> None:
        self._bind = bind
        #: where telemetry goes: the configured address; with port 0, the first authenticated sender
        self.dest = dest
        self.counters = counters
        self._on_datagram = on_datagram
        self._note_tally = note_tally
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sock: socket.socket | None = None  #: everyone's datagrams (and telemetry out, as a fallback)
        self._station_sock: socket.socket | None = None  #: connected to the station: its datagrams
        self._dest_addr: tuple[Any, ...] | None = None  #: dest as a socket address of our family
        self._paused: dict[int, asyncio.TimerHandle] = {}  #: fd: the resumption of a resting socket
        self._unhandled: dict[int, Batch] = {}  #: fd: what a spent budget left of a batch
        self._buf = bytearray(RECV_SIZE)
        self._view = memoryview(self._buf)

    @property
    def bound(self) -> bool:
        """True once :meth:`start` bound the shared socket (until :meth:`close`)."""
        return self._sock is not None

    @property
    def port(self) -> int:
        """The bound local UDP port (after :meth:`start`)."""
        if self._sock is None:
            raise RuntimeError("the MAVLink link is not started")
        return int(self._sock.getsockname()[1])

    @property
    def station_socket(self) -> bool:
        """True while the ground station's address has its own connected socket."""
        return self._station_sock is not None

    async def start(self) -> None:
        """Bind the UDP socket, and the ground station's own socket when its port is known."""
        loop = asyncio.get_running_loop()
        host, port = self._bind
        infos = await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_PASSIVE)
        family, _, _, _, sockaddr = infos[0]
        if sockaddr[1]:
            _check_free(family, sockaddr)
        sock = _udp_socket(family)
        try:
            sock.bind(sockaddr)
            if self.dest is not None:
                dest = await loop.getaddrinfo(*self.dest, family=family, type=socket.SOCK_DGRAM)
                self._dest_addr = dest[0][4]
        except BaseException:
            sock.close()
            raise
        self._loop, self._sock = loop, sock
        loop.add_reader(sock.fileno(), self._on_shared_readable)
        if self._dest_addr is not None:
            self._open_station_socket(self._dest_addr)

    def learn_station(self, addr: tuple[Any, ...]) -> None:
        """The first authenticated message came from ``addr``: telemetry goes there from now on
        (only while the configured port is 0; a known station is never replaced)."""
        if self.dest is not None:
            return
        self.dest = (addr[0], addr[1])
        self._dest_addr = addr
        log.info("MAVLink telemetry to %s port %d", addr[0], addr[1])
        self._open_station_socket(addr)

    def _open_station_socket(self, addr: tuple[Any, ...]) -> None:
        """A second socket on our port, connected to the station: the kernel hands it the
        station's datagrams before the shared socket, so a flood cannot crowd them out. Without
        it (no SO_REUSEPORT, a refused bind) the link works as before on the one socket."""
        if self._sock is None or self._loop is None or self._station_sock is not None:
            return
        sock = _udp_socket(self._sock.family)
        try:
            sock.bind(self._sock.getsockname())
            sock.connect(addr)
        except OSError as err:
            sock.close()
            log.warning("MAVLink: no socket of its own for the ground station (%s); its datagrams "
                        "share the socket with everyone's", err)
            return
        self._station_sock = sock
        self._loop.add_reader(sock.fileno(), self._on_station_readable)

    def write(self, buf: bytes) -> None:
        """pymavlink's file interface: send one packed message to the ground station (dropped and
        counted as a send error when the socket cannot take it now: nothing waits)."""
        try:
            if self._station_sock is not None:
                self._station_sock.send(buf)
            elif self._sock is not None and self._dest_addr is not None:
                self._sock.sendto(buf, self._dest_addr)
            else:
                return
        except OSError:  # a full buffer, or "connection refused" while no station listens
            self.counters["send_errors"] += 1
            return
        self.counters["tx"] += 1

    def close(self) -> None:
        """Close the sockets (safe twice)."""
        for handle in self._paused.values():
            handle.cancel()
        self._paused.clear()
        self._unhandled.clear()
        for sock in (self._station_sock, self._sock):
            if sock is not None:
                if self._loop is not None and not self._loop.is_closed():
                    self._loop.remove_reader(sock.fileno())
                sock.close()
        self._station_sock = self._sock = None

    # --- receiving -----------------------------------------------------------------------------

    def _on_station_readable(self) -> None:
        self._read(self._station_sock)

    def _on_shared_readable(self) -> None:
        self._read(self._station_sock)  # the station's datagrams first, whichever socket woke us
        self._read(self._sock)

    def _read(self, sock: socket.socket | None) -> None:
        """Drain ``sock`` until empty or the budget is spent (then it rests); its refusals are
        noted once per wake-up."""
        if sock is None or sock.fileno() in self._paused:
            return
        tally: Tally = {}
        try:
            emptied = self._drain_socket(sock, time.monotonic_ns() + DRAIN_BUDGET_NS, tally)
        finally:
            self._note_tally(tally)
        if not emptied and self._loop is not None:
            self.counters["drain_rests"] += 1
            fd = sock.fileno()
            self._loop.remove_reader(fd)
            self._paused[fd] = self._loop.call_later(DRAIN_PAUSE_S, self._resume, sock)

    def _resume(self, sock: socket.socket) -> None:
        """A resting socket reads again, at once if a spent budget left datagrams unhandled."""
        fd = sock.fileno()
        if self._paused.pop(fd, None) is None or self._loop is None or fd < 0:
            return
        station = sock is self._station_sock
        self._loop.add_reader(fd, self._on_station_readable if station else self._on_shared_readable)
        if fd in self._unhandled:
            self._read(sock)

    def _drain_socket(self, sock: socket.socket, deadline: int, tally: Tally) -> bool:
        """Handle ``sock``'s datagrams (what a spent budget left first, then batches read) until
        it is empty or ``deadline`` (monotonic ns) passes, looked at after every datagram; False
        when the budget ran out first."""
        fd = sock.fileno()
        while True:
            batch = self._unhandled.pop(fd, None)
            empty = False
            if batch is None:
                batch, empty = self._read_batch(sock)
            for k, (data, addr) in enumerate(batch):
                self._on_datagram(data, addr, tally)
                if time.monotonic_ns() >= deadline:
                    if k + 1 < len(batch):
                        self._unhandled[fd] = batch[k + 1:]
                        return False
                    return empty
            if empty:
                return True

    def _read_batch(self, sock: socket.socket) -> tuple[Batch, bool]:
        """Up to :data:`DRAIN_BATCH` datagrams of ``sock``, the station's address first (stable),
        and whether the socket was emptied."""
        batch: Batch = []
        empty = False
        for _ in range(DRAIN_BATCH):
            try:
                n, addr = sock.recvfrom_into(self._buf)
            except BlockingIOError:
                empty = True
                break
            except ConnectionRefusedError:  # an ICMP error for an earlier send: not a datagram
                self.counters["send_errors"] += 1
                continue
            except OSError:
                empty = True
                break
            batch.append((bytes(self._view[:n]), addr))
        self.counters["datagrams"] += len(batch)
        dest = self._dest_addr[:2] if self._dest_addr is not None else None
        if sock is self._station_sock:
            self.counters["station_datagrams"] += len(batch)
        elif dest is not None and len(batch) > 1:
            batch.sort(key=lambda item: item[1][:2] != dest)
        return batch, empty


def _udp_socket(family: int) -> socket.socket:
    """A non-blocking UDP socket that may share its port with our other one (``SO_REUSEPORT``
    shares only with sockets of the same user)."""
    sock = socket.socket(family, socket.SOCK_DGRAM)
    sock.setblocking(False)
    reuse_port = getattr(socket, "SO_REUSEPORT", None)
    if reuse_port is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, reuse_port, 1)
    return sock


def _check_free(family: int, sockaddr: tuple[Any, ...]) -> None:
    """Raise the OSError (address in use) a plain bind gets when another socket holds the port:
    with ``SO_REUSEPORT`` a second racecar-hw of the same user would otherwise share it silently
    (each probes first, and a probe without ``SO_REUSEPORT`` cannot join a group)."""
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        probe.bind(sockaddr)


__all__ = ["DRAIN_BATCH", "DRAIN_BUDGET_NS", "DRAIN_PAUSE_S", "RECV_SIZE", "MavlinkSocket"]
