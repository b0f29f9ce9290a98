"""Failed Zenoh logins (user/password, TLS), counted by source address from Zenoh's own log.

Zenoh refuses a session that presents a wrong user or password, or fails the TLS handshake, inside
its Rust transport layer: the Python API sees nothing of it (no callback, no event; a
``TransportEventsListener`` only hears of sessions that got in). What does see it is Zenoh's
``tracing`` log. zenoh-python 1.x does not forward that log to Python's ``logging`` (its bridge,
``src/logging.rs``, is commented out in ``src/lib.rs``: "TODO ... pull/235"); ``zenoh.init_log_from_env_or``
installs Rust's ``tracing_subscriber::fmt`` writer instead, which writes every line to the process's
standard output (file descriptor 1), and a process may install it only once.

So :class:`ZenohLoginWatch` (:func:`install`) makes descriptor 1 a pipe read by a thread of its own,
gives Python's ``sys.stdout`` (and the console panel, built after it) a duplicate of the real standard
output, and turns on only the Zenoh log lines it needs, with the directives in :data:`DIRECTIVES`:

* ``zenoh_transport::unicast::establishment::accept`` at TRACE: the accept handshake's steps, each
  naming the link (``Establishment Accept OpenSyn: tcp/<listen> => tcp/<peer>. Received: ...``), and
  at DEBUG the step that failed (``UsrPwd extension - Recv OpenSyn. Invalid password.``, which names
  no address: it is matched to the last link the same thread named, as one handshake step runs on
  one thread from its trace line to its failure, with no await that waits in between);
* ``zenoh_link_tls`` at WARN: a failed TLS handshake (``peer sent no certificates``, ``invalid peer
  certificate: UnknownIssuer``). The error tls-listener hands Zenoh carries no address and Zenoh logs
  none for a connection before its handshake, so these are counted under ``unknown address``.

About four lines of 0.5-1 KB per connection attempt, and nothing while sessions exchange data: the
cost is per login, not per message. Each failed login is counted in the daemon's
:class:`~racecar_hw.runtime.refusals.Refusals` as surface ``zenoh``, source the peer's host (the
port changes with every attempt), reason ``user/password: invalid password`` (or ``invalid user``,
...) or ``tls: <Zenoh's error>``. Every other line (output written through a stale handle of the old
standard output) passes through to the real standard output unchanged. With ``RUST_LOG`` set, Zenoh
uses it instead of :data:`DIRECTIVES` and every line passes through (logins are counted if its
directives include those above).

Installed by the commands that run a daemon (``run``, ``sim``, ``follow``), before the status panel,
when the Zenoh listener authenticates (``zenoh.auth.dictionary_file`` or ``zenoh.tls.enable_mtls``)
and ``zenoh.count_failed_logins`` is on: not in a process that only imports the daemon (tests).
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import re
import sys
import threading

from racecar_hw.net.zenoh_config import ZenohParams
from racecar_hw.runtime.refusals import Refusals

log = logging.getLogger(__name__)

#: The Zenoh log lines read (a ``RUST_LOG``-style filter): see the module docstring.
DIRECTIVES = ("off,zenoh_transport::unicast::establishment::accept=trace,"
              "zenoh_link_tls=warn")

#: The surface failed logins are counted under in :class:`Refusals`.
SURFACE = "zenoh"

#: Bytes of a line read (the time, level, thread, target and the start of the message).
PREFIX = 512
_ANSI = re.compile(rb"\x1b\[[0-9;]*m")
_THREAD = re.compile(rb"ThreadId\((\d+)\)")
_TARGET = re.compile(rb" (zenoh_[a-z_:]+): ")
_ACCEPT_STEP = re.compile(rb"Establishment Accept \w+: \S+ => (\S+?)\. ")
_USRPWD = re.compile(rb"UsrPwd extension - [^.]*\. ([^.]+)\.")
_ADDRESS = re.compile(rb"(\d{1,3}(?:\.\d{1,3}){3}|\[[0-9a-fA-F:.]+\])(?::\d+)?")
_AT_SOURCE = re.compile(rb"\s+at\s+\S+\.rs:\d+\.?")


def peer_host(locator: str) -> str:
    """The host of a Zenoh locator or socket address: ``tcp/127.0.0.1:40112`` -> ``127.0.0.1``,
    ``tls/[::1]:40112`` -> ``::1``."""
    address = locator.split("/", 1)[-1].split("#", 1)[0]
    if address.startswith("["):
        return address[1:].split("]", 1)[0]
    return address.rsplit(":", 1)[0] if address.count(":") == 1 else address


class LoginLineParser:
    """Turns Zenoh's log lines into refusals: ``feed(line)`` returns ``(source, reason)`` for a failed
    login, else None (pure: no I/O, so it is fuzzed and tested alone)."""

    def __init__(self) -> None:
        self._link_by_thread: dict[bytes, str] = {}
        #: whether the last line fed was one of Zenoh's (it is not passed through)
        self.last_was_zenoh = False

    def feed(self, raw: bytes) -> tuple[str, str] | None:
        """One line (ANSI colours allowed). Only its first :data:`PREFIX` bytes are read: the
        handshake lines name the link there, before the message dump that makes them long."""
        line = raw[:PREFIX]
        if b"\x1b" in line:  # colours: :func:`install` turns them off, RUST_LOG users may not
            line = _ANSI.sub(b"", line)
        # plain substring tests first: most lines (the other handshake steps) stop at one of them
        self.last_was_zenoh = b" zenoh_" in line and _TARGET.search(line) is not None
        if not self.last_was_zenoh:
            return None
        if b"Establishment Accept OpenSyn: " in line:  # the step whose check a wrong password fails
            step = _ACCEPT_STEP.search(line)
            if step is not None:
                if len(self._link_by_thread) > 1024:  # bounded, whatever the thread ids
                    self._link_by_thread.clear()
                self._link_by_thread[self._thread(line)] = step.group(1).decode("utf-8", "replace")
            return None
        if b"UsrPwd extension - " in line:
            failure = _USRPWD.search(line)
            if failure is None:
                return None
            peer = self._link_by_thread.pop(self._thread(line), None)
            source = peer_host(peer) if peer else "unknown address"
            return source, "user/password: " + failure.group(1).decode("utf-8", "replace").strip().lower()
        target = _TARGET.search(line)
        if target is not None and target.group(1).startswith(b"zenoh_link_tls") and b" WARN " in line:
            text = line[target.end():].strip()
            lowered = text.lower()
            if not any(word in lowered for word in (b"certificate", b"tls", b"handshake")):
                return None
            address = _ADDRESS.search(text)
            source = address.group(1).decode().strip("[]") if address else "unknown address"
            reason = _AT_SOURCE.sub(b"", _ADDRESS.sub(b"", text)).decode("utf-8", "replace")
            reason = reason.split(". Hint:", 1)[0].strip(" .:")[:80]
            return source, f"tls: {reason}"
        return None

    @staticmethod
    def _thread(line: bytes) -> bytes:
        match = _THREAD.search(line)
        return match.group(1) if match else b""

    def is_zenoh(self, raw: bytes) -> bool:
        """Whether ``raw`` is one of Zenoh's log lines (not passed through)."""
        return _TARGET.search(_ANSI.sub(b"", raw[:PREFIX])) is not None


class ZenohLoginWatch:
    """Reads descriptor 1 (Zenoh's log) on a thread, counting failed logins; see the module docstring."""

    def __init__(self, read_fd: int, out_fd: int, *, pass_zenoh: bool) -> None:
        self.read_fd = read_fd
        self.out_fd = out_fd
        self.pass_zenoh = pass_zenoh
        self.parser = LoginLineParser()
        self.refusals: Refusals | None = None
        self.failed = 0   #: failed logins seen (with or without refusals attached)
        self._thread = threading.Thread(target=self._run, name="zenoh-log", daemon=True)

    def attach(self, refusals: Refusals) -> None:
        """Count from now on in ``refusals`` (the daemon's)."""
        self.refusals = refusals

    def _run(self) -> None:
        pending = b""
        while True:
            try:
                chunk = os.read(self.read_fd, 65536)
            except OSError:
                return
            if not chunk:
                return
            pending += chunk
            *lines, pending = pending.split(b"\n")
            if len(pending) > 1 << 16:  # no line end in sight: pass it on as it is
                lines.append(pending)
                pending = b""
            for line in lines:
                self._line(line)

    def _line(self, line: bytes) -> None:
        try:
            found = self.parser.feed(line)
        except Exception as err:  # noqa: BLE001 - a line we cannot read must not end the watch
            log.debug("zenoh log line not understood: %r", err)
            found = None
            self.parser.last_was_zenoh = False
        if found is not None:
            self.failed += 1
            if self.refusals is not None:
                self.refusals.note(SURFACE, found[0], found[1])
        if self.pass_zenoh or not self.parser.last_was_zenoh:
            with contextlib.suppress(OSError):
                os.write(self.out_fd, line + b"\n")


_installed: ZenohLoginWatch | None = None
_lock = threading.Lock()


def installed() -> ZenohLoginWatch | None:
    """The process's watch, if :func:`install` ran."""
    return _installed


def install_for(params: ZenohParams) -> ZenohLoginWatch | None:
    """:func:`install`, when ``params`` runs a Zenoh listener that authenticates and counts failed
    logins (``zenoh.count_failed_logins``); else None."""
    if not (params.enabled and params.count_failed_logins and params.authenticates()):
        return None
    return install()


def install() -> ZenohLoginWatch | None:
    """Route Zenoh's log (descriptor 1) to a :class:`ZenohLoginWatch` and Python's standard output to
    a duplicate of the real one; once per process (later calls return the same watch). None, with a
    warning, when standard output cannot be moved (no descriptor 1)."""
    global _installed
    with _lock:
        if _installed is not None:
            return _installed
        import zenoh

        try:
            sys.stdout.flush()
            real = os.dup(1)
            read_fd, write_fd = os.pipe()
        except (OSError, ValueError, AttributeError) as err:
            log.warning("failed Zenoh logins are not counted: standard output cannot be moved (%s)", err)
            return None
        os.set_inheritable(real, False)
        os.dup2(write_fd, 1)
        os.close(write_fd)
        old = sys.stdout
        sys.stdout = io.TextIOWrapper(io.FileIO(real, "w", closefd=True),
                                      encoding=getattr(old, "encoding", None) or "utf-8",
                                      errors=getattr(old, "errors", None) or "strict",
                                      line_buffering=True, write_through=True)
        watch = ZenohLoginWatch(read_fd, real, pass_zenoh="RUST_LOG" in os.environ)
        watch._thread.start()
        # no ANSI colours (tracing-subscriber reads NO_COLOR when the writer is built): cheaper to
        # read; set only for that call, so the status panel keeps its colours
        no_color = os.environ.get("NO_COLOR")
        os.environ["NO_COLOR"] = "1"
        try:
            zenoh.init_log_from_env_or(DIRECTIVES)
        finally:
            if no_color is None:
                del os.environ["NO_COLOR"]
            else:
                os.environ["NO_COLOR"] = no_color
        _installed = watch
        log.debug("counting failed Zenoh logins from Zenoh's log (%s)", DIRECTIVES)
        return watch
