"""The Foxglove relay on its own: what it lets through, byte for byte, and what it turns away.

A real relay (its own thread and event loop, as in the daemon) in front of a TLS server on loopback
that stands in for the SDK's: it answers an upgrade with 101 and then echoes every byte, and records
what reached it. The daemon-level checks (tokens, origins, a real browser) are in test_net_foxglove.py
and test_net_web.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import ssl
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.net import relay as relay_module
from racecar_hw.net.loopback_tls import make_loopback_cert
from racecar_hw.net.relay import Relay

UPGRADE = (b"GET /?token=%s HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
           b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n")
DEADLINE_S = 20.0


class EchoUpstream:
    """A TLS server standing in for the SDK's: 101 to any request, then every byte back."""

    def __init__(self, context: ssl.SSLContext) -> None:
        self.context = context
        self.heads: list[bytes] = []
        self.port = 0
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> EchoUpstream:
        self._server = await asyncio.start_server(self._client, "127.0.0.1", 0, ssl=self.context)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        with contextlib.suppress(OSError, asyncio.IncompleteReadError, asyncio.CancelledError):
            self.heads.append(await reader.readuntil(b"\r\n\r\n"))
            writer.write(b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\n"
                         b"Connection: Upgrade\r\n\r\n")
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        writer.close()


@pytest.fixture
def tls(tmp_path: Path) -> Iterator[tuple[bytes, ssl.SSLContext]]:
    """The loopback certificate (PEM) and a server context using it."""
    cert = make_loopback_cert()
    (tmp_path / "cert.pem").write_bytes(cert.cert_pem)
    (tmp_path / "key.pem").write_bytes(cert.key_pem)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(tmp_path / "cert.pem", tmp_path / "key.pem")
    yield cert.cert_pem, context


@contextlib.contextmanager
def running(relay: Relay) -> Iterator[Relay]:
    relay.start()
    try:
        yield relay
    finally:
        relay.stop()


async def _status(port: int, request: bytes) -> tuple[int, bytes]:
    """The status code of the relay's answer to ``request``, and the answer (the head only for 101)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request)
    answer = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), DEADLINE_S)
    status = int(answer.split(b" ", 2)[1])
    if status != 101:
        answer += await asyncio.wait_for(reader.read(), DEADLINE_S)  # then the relay closes
    writer.close()
    return status, answer


def test_an_admitted_client_reaches_the_server_byte_for_byte_both_ways(tls):
    cert_pem, context = tls
    payload = os.urandom(3 * 1024 * 1024)  # larger than any read: chunks and back-pressure

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            with running(Relay("127.0.0.1", 0, upstream.port, cert_pem, token="t0k")) as relay:
                reader, writer = await asyncio.open_connection("127.0.0.1", relay.port)
                writer.write(UPGRADE % b"t0k")
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), DEADLINE_S)
                assert head.startswith(b"HTTP/1.1 101 ")

                async def send() -> None:
                    writer.write(payload)
                    await writer.drain()

                sending = asyncio.ensure_future(send())
                echoed = await asyncio.wait_for(reader.readexactly(len(payload)), DEADLINE_S)
                await sending
                assert echoed == payload
                assert upstream.heads == [UPGRADE % b"t0k"]
                writer.close()

    asyncio.run(main())


def test_requests_that_may_not_pass_never_reach_the_server(tls):
    cert_pem, context = tls

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            with running(Relay("127.0.0.1", 0, upstream.port, cert_pem, token="t0k")) as relay:
                assert (await _status(relay.port, UPGRADE % b"wrong"))[0] == 401
                no_token = UPGRADE.replace(b"?token=%s", b"")
                assert (await _status(relay.port, no_token))[0] == 401
                bearer = no_token.replace(b"Upgrade: websocket",
                                          b"Authorization: Bearer t0k\r\nUpgrade: websocket")
                assert (await _status(relay.port, bearer))[0] == 101
                plain_get = b"GET /?token=t0k HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
                assert (await _status(relay.port, plain_get))[0] == 400
                assert (await _status(relay.port, b"\x16\x03\x01garbage\r\n\r\n"))[0] == 400
                # a head that never ends is cut off at MAX_HEAD, without an answer
                reader, writer = await asyncio.open_connection("127.0.0.1", relay.port)
                writer.write(b"GET / HTTP/1.1\r\nX-Long: " + b"a" * (2 * relay_module.MAX_HEAD))
                assert await asyncio.wait_for(reader.read(), DEADLINE_S) == b""
                writer.close()
                assert relay.refused == 4
                assert upstream.heads == [bearer]

    asyncio.run(main())


def test_an_open_loopback_relay_turns_away_pages_of_other_sites(tls):
    cert_pem, context = tls
    chrome = b"User-Agent: Mozilla/5.0 (X11; Linux x86_64) Chrome/156.0.0.0 Safari/537.36\r\n"

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            with running(Relay("127.0.0.1", 0, upstream.port, cert_pem)) as relay:
                origin = b"Origin: https://evil.example\r\n" + chrome
                evil = (UPGRADE % b"").replace(b"Host:", origin + b"Host:")
                status, body = await _status(relay.port, evil)
                assert status == 403 and b"foxglove.allowed_origins" in body
                assert (await _status(relay.port, UPGRADE % b""))[0] == 101  # not a browser
                assert upstream.heads == [UPGRADE % b""]

    asyncio.run(main())


def test_a_server_that_does_not_answer_is_a_502(tls):
    cert_pem, _ = tls
    with contextlib.closing(socket.socket()) as sock:
        sock.bind(("127.0.0.1", 0))
        closed_port = sock.getsockname()[1]  # nobody listens there once closed

    async def main() -> None:
        with running(Relay("127.0.0.1", 0, closed_port, cert_pem)) as relay:
            assert (await _status(relay.port, UPGRADE % b""))[0] == 502

    asyncio.run(main())


def test_stopping_the_relay_closes_relayed_connections(tls):
    cert_pem, context = tls

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            relay = Relay("127.0.0.1", 0, upstream.port, cert_pem)
            relay.start()
            reader, writer = await asyncio.open_connection("127.0.0.1", relay.port)
            writer.write(UPGRADE % b"")
            await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), DEADLINE_S)
            await asyncio.to_thread(relay.stop)
            assert await asyncio.wait_for(reader.read(), DEADLINE_S) == b""
            writer.close()
            with pytest.raises(OSError):
                await asyncio.open_connection("127.0.0.1", relay.port)

    asyncio.run(main())


@settings(max_examples=500, deadline=None)
@given(st.one_of(st.binary(max_size=300),
                 st.builds(lambda line, rest: line + b"\r\n" + rest + b"\r\n\r\n",
                           st.sampled_from([b"GET / HTTP/1.1", b"GET /?token=x HTTP/1.0", b"GET  HTTP/1.1",
                                            b"POST / HTTP/2", b"GET / HTTP/1.1 extra"]),
                           st.binary(max_size=200))))
def test_any_request_head_parses_or_is_refused_without_an_exception(head):
    request = relay_module._parse(head)
    if request is not None:
        assert isinstance(request.is_websocket_upgrade, bool)
        assert request.token is None or isinstance(request.token, str)


# --- the connection gate: a cap, a head timeout, an idle timeout (racecar_hw.net.gate) -----------

PARTIAL = b"GET /?token=t0k HTTP/1.1\r\nHost: 127.0.0.1\r\n"  # a head that is never finished


async def _closed_by_server(reader: asyncio.StreamReader, timeout_s: float = DEADLINE_S) -> bool:
    """Whether the server closes (or resets) the connection within ``timeout_s``, reading what comes."""
    try:
        async with asyncio.timeout(timeout_s):
            while await reader.read(65536):
                pass
    except TimeoutError:
        return False
    except OSError:
        pass  # reset: closed at once
    return True


async def _upgraded(port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(UPGRADE % b"t0k")
    head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), DEADLINE_S)
    assert head.startswith(b"HTTP/1.1 101 ")
    return reader, writer


def test_beyond_the_cap_half_open_connections_make_room_and_then_new_ones_are_closed_at_once(tls):
    from racecar_hw.net.gate import EVICTED, TOO_MANY, ConnectionLimits

    cert_pem, context = tls
    limits = ConnectionLimits(max_connections=4, head_timeout_s=60.0, idle_timeout_s=600.0)

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            with running(Relay("127.0.0.1", 0, upstream.port, cert_pem, token="t0k", limits=limits)) as relay:
                half_open = []
                for _ in range(4):
                    reader, writer = await asyncio.open_connection("127.0.0.1", relay.port)
                    writer.write(PARTIAL)
                    await writer.drain()
                    half_open.append((reader, writer))
                # the cap is reached with unfinished requests: each viewer closes the oldest of them
                viewers = []
                for i in range(4):
                    viewers.append(await _upgraded(relay.port))
                    assert await _closed_by_server(half_open[i][0])
                # four viewers in use: a fifth connection is closed at once, before it says anything
                reader, writer = await asyncio.open_connection("127.0.0.1", relay.port)
                assert await _closed_by_server(reader)
                writer.close()
                for reader, writer in viewers:  # and the viewers are untouched
                    writer.write(b"ping")
                    assert await asyncio.wait_for(reader.readexactly(4), DEADLINE_S) == b"ping"
                    writer.close()
                for _, writer in half_open:
                    writer.close()
                assert relay.refusals.total("relay", EVICTED) == 4
                assert relay.refusals.total("relay", TOO_MANY) == 1
                assert len(upstream.heads) == 4

    asyncio.run(main())


def test_an_unfinished_request_head_is_closed_after_the_head_timeout_and_a_silent_one_when_idle(tls):
    from racecar_hw.net.gate import HEAD_LATE, IDLE, ConnectionLimits

    cert_pem, context = tls
    limits = ConnectionLimits(max_connections=8, head_timeout_s=0.5, idle_timeout_s=3.0)

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            with running(Relay("127.0.0.1", 0, upstream.port, cert_pem, token="t0k", limits=limits)) as relay:
                slow, slow_writer = await asyncio.open_connection("127.0.0.1", relay.port)
                slow_writer.write(PARTIAL)
                talking = await _upgraded(relay.port)
                silent = await _upgraded(relay.port)
                assert await _closed_by_server(slow)
                assert relay.refusals.total("relay", HEAD_LATE) == 1
                # a viewer whose bytes keep moving stays past the head timeout and the idle timeout;
                # the silent one is closed once idle
                loop = asyncio.get_running_loop()
                deadline = loop.time() + DEADLINE_S
                reader, writer = talking
                while relay.refusals.total("relay", IDLE) == 0:
                    assert loop.time() < deadline, "the silent viewer was never closed"
                    writer.write(b"x")
                    assert await asyncio.wait_for(reader.readexactly(1), DEADLINE_S) == b"x"
                    await asyncio.sleep(0.1)
                assert await _closed_by_server(silent[0])
                writer.write(b"still here")
                assert await asyncio.wait_for(reader.readexactly(10), DEADLINE_S) == b"still here"
                for _, w in (talking, silent):
                    w.close()
                slow_writer.close()
                assert relay.refusals.total("relay", IDLE) == 1

    asyncio.run(main())


def test_refused_requests_log_one_summary_line_per_source_and_reason_per_interval(tls, caplog):
    from racecar_hw.runtime.refusals import Refusals

    cert_pem, context = tls
    refusals = Refusals(interval_s=600.0)  # longer than the test: exactly the first line

    async def main() -> None:
        async with EchoUpstream(context) as upstream:
            with running(Relay("127.0.0.1", 0, upstream.port, cert_pem, token="t0k",
                               refusals=refusals)) as relay:
                for _ in range(300):
                    assert (await _status(relay.port, UPGRADE % b"wrong"))[0] == 401
                assert (await _status(relay.port, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"))[0] == 400
                assert relay.refusals.by_source() == {
                    ("relay", "127.0.0.1", "not a WebSocket upgrade (400)"): 1,
                    ("relay", "127.0.0.1", "upgrade without the token (401)"): 300}

    with caplog.at_level("INFO"):
        asyncio.run(main())
    lines = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(lines) == 2 and all(line.startswith("relay: refused 127.0.0.1: ") for line in lines), lines
    refusals.flush()  # at shutdown: the rest, counted
    assert "299 times" in caplog.records[-1].getMessage()


@settings(max_examples=500, deadline=None)
@given(st.lists(st.sampled_from([b"\r", b"\n", b"\r\n", b"a", b"GET / HTTP/1.1", b"\r\n\r\n", b"\x00"]),
                max_size=40),
       st.lists(st.integers(min_value=0, max_value=200), max_size=10))
def test_the_gate_sees_a_head_end_however_the_reads_split_it(pieces, cuts):
    from racecar_hw.net.gate import HEAD_END, head_end

    stream = b"".join(pieces)
    points = sorted({min(c, len(stream)) for c in cuts} | {0, len(stream)})
    ended, tail = False, b""
    for start, stop in zip(points, points[1:], strict=False):
        ended, tail = head_end(tail, stream[start:stop])
        assert len(tail) < len(HEAD_END)
        if ended:
            assert HEAD_END in stream[:stop].lstrip(b"\r\n")
            break
    # blank lines before the request line are skipped (they are not a head)
    assert ended == (HEAD_END in stream.lstrip(b"\r\n"))


def test_a_certificate_child_that_answers_nothing_is_one_clear_error(tmp_path, monkeypatch):
    """The child process runs whatever ``racecar_hw`` comes first on its path: an older tree there
    (seen with PYTHONPATH set to another checkout) prints nothing. That is a CertificateError
    naming the certificate, not a JSON traceback."""
    from racecar_hw.net.loopback_tls import CertificateError  # noqa: PLC0415

    package = tmp_path / "racecar_hw" / "net"
    package.mkdir(parents=True)
    for empty in ("__init__.py", "net/__init__.py", "net/loopback_tls.py"):
        (tmp_path / "racecar_hw" / empty).write_text("")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    with pytest.raises(CertificateError, match="loopback certificate: the child process answered b''"):
        make_loopback_cert()


def test_servers_of_one_process_share_its_certificate_and_a_plain_request_gets_a_new_one(monkeypatch):
    """``PendingCert(reuse=True)`` (the Foxglove server's) makes the process's certificate once; later
    ones start no child process. Without ``reuse`` every certificate is new."""
    from racecar_hw.net import loopback_tls  # noqa: PLC0415

    monkeypatch.setattr(loopback_tls, "_made", {})
    first = loopback_tls.PendingCert(reuse=True).result()
    fresh = make_loopback_cert()
    assert fresh.key_pem != first.key_pem

    def no_child(*args, **kwargs):
        raise AssertionError(f"a child process was started: {args}")

    monkeypatch.setattr(loopback_tls.subprocess, "Popen", no_child)
    again = loopback_tls.PendingCert(reuse=True)
    assert again.result() is first
    assert again.result() is first
