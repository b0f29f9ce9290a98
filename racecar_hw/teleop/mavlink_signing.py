"""Who may talk to the car over MAVLink: signing keys, the station's host and system id.

:class:`LinkSecurity` turns one datagram into the messages the ground station may be obeyed in:
datagrams from any other host than the station's are dropped, forgeries are turned away by
:meth:`~racecar_hw.teleop.mavlink_rx.MavlinkRx.refuse_cheaply` before any parsing, the rest is
decoded by :class:`~racecar_hw.teleop.mavlink_rx.MavlinkRx` (signatures verified before any
timestamp is recorded), and messages from other system ids are heard but never obeyed. Every
refusal is counted in the link's counters and in a :class:`~racecar_hw.runtime.refusals.Refusals`
(surface ``"mavlink"``, source ``host:port``). Signing time is in MAVLink units of 10 µs since
2015-01-01 UTC; our outgoing timestamps follow the wall clock and every accepted timestamp.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from racecar_hw.base.clock import NS_PER_S
from racecar_hw.base.errors import ConfigError
from racecar_hw.base.loopback import is_loopback
from racecar_hw.runtime.refusals import Refusals
from racecar_hw.teleop.mavlink_params import BIND_NEEDS_SIGNING, NEEDS_SIGNING
from racecar_hw.teleop.mavlink_rx import MAX_DATAGRAM, MavlinkRx

log = logging.getLogger(__name__)

#: Seconds from the Unix epoch to the MAVLink signing epoch (2015-01-01 00:00:00 UTC).
SIGNING_EPOCH_S = 1_420_070_400
#: MAVLink signing time units per second (10 µs each).
SIGNING_UNITS_PER_S = 100_000
#: Refusals of one wake-up of the reader: (sender address, counter name) -> count.
Tally = dict[tuple[tuple[Any, ...], str], int]
#: The log and diagnostics' words for each refusal counter (Refusals reason).
REFUSAL_REASONS = {
    "foreign": "not the ground station's host",
    "bad_data": "malformed datagram",
    "unknown_ids": "unknown message id",
    "mavlink1_refused": "MAVLink 1 frame",
    "unsigned_refused": "unsigned frame",
    "bad_signature": "bad signature",
    "old_timestamp": "replayed or old signing timestamp",
    "future_timestamp": "signing timestamp too far ahead of our clock",
    "other_sender": "not the ground station's system id",
    "oversized": f"datagram longer than {MAX_DATAGRAM} bytes",
    "overfull": "more frames in one datagram than a ground station sends",
}


def load_signing_key(path: str, key: str = "mavlink.signing_key_file") -> bytes:
    """The 32-byte secret from a key file (64 hex digits, 32 raw bytes, or a passphrase)."""
    try:
        raw = Path(path).read_bytes()
    except OSError as err:
        raise ConfigError(key, f"cannot read the signing key {path}: {err.strerror}") from err
    text = raw.strip()
    if len(text) == 64:
        with contextlib.suppress(ValueError):
            return bytes.fromhex(text.decode("ascii"))
    if len(raw) == 32:
        return raw
    if not text:
        raise ConfigError(key, f"the signing key file {path} is empty")
    return hashlib.sha256(text).digest()


def write_signing_key(path: str | Path) -> bytes:
    """Create a new random key file (64 hex digits, mode 0600); returns the key."""
    secret = os.urandom(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(secret.hex() + "\n")
    return secret


def signing_timestamp(unix_ns: int) -> int:
    """MAVLink signing time: units of 10 µs since 2015-01-01 UTC."""
    return max(0, (unix_ns - SIGNING_EPOCH_S * NS_PER_S) // 10_000)


class LinkSecurity:
    """The gate between the socket and the link: only the ground station's verified messages pass.

    ``mav`` is the pymavlink packer whose outgoing signing this keeps in step with what was
    received; ``counters`` the link's counters (the refusal names of :data:`REFUSAL_REASONS`);
    ``gcs_host`` the station's host as :func:`~racecar_hw.teleop.mavlink_gcs.station_host` gives it.
    A station outside loopback without ``signing_key_file`` is a ConfigError, and so is a socket
    bound outside loopback (``bind_host``) without it.
    """

    def __init__(self, mav: Any, gcs_host: str, gcs_address: str, gcs_system_id: int, *,
                 signing_key_file: str, signing_link_id: int, future_window_s: float,
                 counters: dict[str, int], refusals: Refusals, wall_clock: Callable[[], int],
                 bind_host: str = "127.0.0.1") -> None:
        self.mav = mav
        self.counters = counters
        self.refusals = refusals
        self.gcs_system_id = gcs_system_id
        self._gcs_host = gcs_host
        self._wall_clock = wall_clock
        self.secret_key: bytes | None = None
        if signing_key_file:
            self.secret_key = load_signing_key(signing_key_file)
        elif not is_loopback(gcs_host):
            raise ConfigError("mavlink.signing_key_file", NEEDS_SIGNING.format(gcs_address))
        elif not is_loopback(bind_host):
            raise ConfigError("mavlink.bind_address", BIND_NEEDS_SIGNING.format(bind_host))
        self.rx = MavlinkRx(self.secret_key, signing_timestamp(wall_clock()),
                            future_window=round(future_window_s * SIGNING_UNITS_PER_S))
        if self.secret_key is not None:
            mav.signing.secret_key = self.secret_key
            mav.signing.link_id = signing_link_id
            mav.signing.timestamp = self.rx.timestamp
            mav.signing.sign_outgoing = True

    def station_messages(self, data: bytes, addr: tuple[Any, ...], tally: Tally | None) -> list[Any]:
        """The messages of the ground station in one datagram from ``addr``, each counted as
        ``rx``; everything else in it is refused and counted (``tally``: summed there for the
        caller to note; None: noted at once)."""
        host = addr[0]
        if host != self._gcs_host and not (is_loopback(host) and is_loopback(self._gcs_host)):
            self.refused(addr, "foreign", tally)
            return []
        rx = self.rx
        refusal = rx.refuse_cheaply(data)  # an unsigned or forged frame: one hash, nothing parsed
        if refusal is not None:
            self.refused(addr, refusal, tally)
            return []
        # our signing time follows the wall clock and every accepted timestamp, and never goes back
        wall = signing_timestamp(self._wall_clock())
        rx.timestamp = max(rx.timestamp, self.mav.signing.timestamp, wall)
        messages = rx.decode(data, wall)
        self.mav.signing.timestamp = max(self.mav.signing.timestamp, rx.timestamp)
        for counter in rx.refused:
            self.refused(addr, counter, tally)
        heard = []
        for msg in messages:
            if msg.get_srcSystem() != self.gcs_system_id:
                self.refused(addr, "other_sender", tally)  # another system: heard, never obeyed
                continue
            self.counters["rx"] += 1
            heard.append(msg)
        return heard

    def restart(self) -> int:
        """Forget every signing stream's timestamp and take our signing time from the wall clock
        again, as a restart of the daemon does. Returns how many streams were forgotten."""
        now = signing_timestamp(self._wall_clock())
        forgotten = self.rx.restart(now)
        self.mav.signing.timestamp = now
        self.counters["signing_restarts"] += 1
        log.warning("MAVLink: signing state restarted (%d stream(s) forgotten, our time from the "
                    "wall clock again)", forgotten)
        return forgotten

    def refused(self, addr: tuple[Any, ...], counter: str, tally: Tally | None) -> None:
        """Count a refusal from ``addr`` in the counters and the refusals (``tally``: summed
        per wake-up and noted at its end; None: noted at once)."""
        self.counters[counter] += 1
        if tally is None:
            self.note(addr, counter, 1)
        else:
            key = (addr, counter)
            tally[key] = tally.get(key, 0) + 1

    def note_tally(self, tally: Tally) -> None:
        """Note a wake-up's summed refusals."""
        for (addr, counter), count in tally.items():
            self.note(addr, counter, count)

    def note(self, addr: tuple[Any, ...], counter: str, count: int) -> None:
        host, port = addr[0], addr[1]
        source = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        self.refusals.note("mavlink", source, REFUSAL_REASONS[counter], count)


__all__ = ["REFUSAL_REASONS", "SIGNING_EPOCH_S", "SIGNING_UNITS_PER_S", "LinkSecurity", "Tally",
           "load_signing_key", "signing_timestamp", "write_signing_key"]
