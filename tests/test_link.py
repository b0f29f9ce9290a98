"""The serial link over a real pty, including an unplug, and the TCP link."""

from __future__ import annotations

import asyncio

import pytest

from racecar_hw.base.errors import DeviceIOError, DeviceNotFound
from racecar_hw.base.link import SerialLink, TcpLink, open_link, parse_host_port
from racecar_hw.runtime.fakepty import PtyPort


async def _open_pty_link(tmp_path) -> tuple[PtyPort, SerialLink]:
    """A fake serial device on a real pty and an open SerialLink to it."""
    port = PtyPort(str(tmp_path / "dev")).open()
    link = SerialLink(port.path)
    await link.open()
    return port, link


async def _read_exactly(link: SerialLink, n: int) -> bytes:
    data = b""
    while len(data) < n:
        data += await asyncio.wait_for(link.read(), 5)
    return data


def test_serial_link_both_ways_and_unplug(tmp_path):
    async def scenario() -> None:
        port, link = await _open_pty_link(tmp_path)
        link.write(b"hello device")
        got = b""
        for _ in range(500):
            got += port.read()
            if len(got) >= 12:
                break
            await asyncio.sleep(0.01)
        assert got == b"hello device"
        port.write(b"hello host")
        assert await _read_exactly(link, 10) == b"hello host"
        port.unplug()
        with pytest.raises(DeviceIOError):
            await asyncio.wait_for(link.read(), 5)
        link.close()
        link.close()
        with pytest.raises(DeviceNotFound):
            await SerialLink(port.path).open()
        port.replug()
        again = SerialLink(port.path)
        await again.open()
        port.write(b"back")
        assert await _read_exactly(again, 4) == b"back"
        again.close()
        port.close()

    asyncio.run(scenario())


def test_tcp_link_echo_and_drop():
    async def scenario() -> None:
        conns = []

        async def handle(reader, writer):
            conns.append(writer)
            writer.write(await reader.read(100))

        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        host, port = server.sockets[0].getsockname()[:2]
        link = open_link(f"tcp://{host}:{port}")
        assert isinstance(link, TcpLink)
        async with link:
            link.write(b"ping")
            assert await asyncio.wait_for(link.read(), 5) == b"ping"
            conns[0].close()
            with pytest.raises(DeviceIOError):
                await asyncio.wait_for(link.read(), 5)
        server.close()
        await server.wait_closed()
        with pytest.raises(DeviceNotFound):
            await TcpLink(host, port).open()

    asyncio.run(scenario())


def test_tcp_link_receiver_gets_bytes_and_a_drop_or_its_error_fails_the_link():
    async def scenario() -> None:
        conns: list[asyncio.StreamWriter] = []

        async def handle(reader, writer):
            conns.append(writer)
            await reader.read(1)

        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        host, port = server.sockets[0].getsockname()[:2]
        chunks: list[bytes] = []

        def receiver(data: bytes) -> None:
            if b"boom" in data:
                raise ValueError("receiver broke")
            chunks.append(data)

        async def until(condition) -> None:
            for _ in range(500):
                if condition():
                    return
                await asyncio.sleep(0.01)
            raise AssertionError("condition never held")

        link = TcpLink(host, port)
        await link.open()
        await until(lambda: conns)
        conns[0].write(b"early")
        assert await asyncio.wait_for(link.read(), 5) == b"early"
        link.set_receiver(receiver)
        conns[0].write(b"scan frame")
        await until(lambda: b"".join(chunks) == b"scan frame")
        conns[0].write(b"boom")
        with pytest.raises(ValueError, match="receiver broke"):
            await asyncio.wait_for(link.read(), 5)
        assert not link.is_open
        link.close()

        again = TcpLink(host, port)
        await again.open()
        await until(lambda: len(conns) == 2)
        again.set_receiver(receiver)
        conns[1].close()
        with pytest.raises(DeviceIOError, match="closed by the device"):
            await asyncio.wait_for(again.read(), 5)
        again.close()
        again.close()
        server.close()
        await server.wait_closed()

    asyncio.run(scenario())


def test_parse_host_port():
    assert parse_host_port("192.168.0.10:10940") == ("192.168.0.10", 10940)
    assert parse_host_port("tcp://localhost:1") == ("localhost", 1)
    assert parse_host_port("host", 10940) == ("host", 10940)
    with pytest.raises(ValueError):
        parse_host_port("host:abc")


def test_serial_link_receiver_gets_bytes_and_its_error_fails_the_link(tmp_path):
    async def scenario() -> None:
        port, link = await _open_pty_link(tmp_path)
        port.write(b"early")
        assert await _read_exactly(link, 5) == b"early"
        chunks: list[bytes] = []

        def receiver(data: bytes) -> None:
            if b"boom" in data:
                raise ValueError("receiver broke")
            chunks.append(data)

        link.set_receiver(receiver)
        port.write(b"telemetry")
        for _ in range(500):
            if b"".join(chunks) == b"telemetry":
                break
            await asyncio.sleep(0.01)
        assert b"".join(chunks) == b"telemetry"
        port.write(b"boom")
        with pytest.raises(ValueError, match="receiver broke"):
            await asyncio.wait_for(link.read(), 5)
        assert not link.is_open
        link.close()
        port.close()

    asyncio.run(scenario())


def test_a_device_that_takes_no_data_fails_the_link_at_a_bounded_backlog(tmp_path):
    """Writes to a device that stopped reading queue up to MAX_TX_PENDING bytes, then the link
    fails (a reconnect starts afresh); they never grow without bound."""
    from racecar_hw.base.link import MAX_TX_PENDING

    async def scenario() -> None:
        port, link = await _open_pty_link(tmp_path)  # the device side never reads
        chunk = bytes(100)
        with pytest.raises(DeviceIOError, match="takes no data"):
            for _ in range(100_000):  # the OS's buffer fills first, then the link's
                link.write(chunk)
                assert link.tx_pending <= MAX_TX_PENDING
        assert not link.is_open
        with pytest.raises(DeviceIOError, match="takes no data"):
            await asyncio.wait_for(link.read(), 5)
        link.close()
        assert link.tx_pending == 0
        port.close()

    asyncio.run(scenario())


def test_a_serial_port_in_use_is_refused_not_shared(tmp_path):
    """Two daemons on one VESC once both opened its port and fought over it (each losing the link
    two dozen times in seconds); the second is now refused, saying why, and gets it once free."""
    async def scenario() -> None:
        port, first = await _open_pty_link(tmp_path)
        second = SerialLink(port.path)
        with pytest.raises(DeviceIOError, match="is in use by another program"):
            await second.open()
        first.close()
        await second.open()
        second.close()
        port.close()

    asyncio.run(scenario())


def test_read_within_times_out_and_returns_bytes(tmp_path):
    async def scenario() -> None:
        port, link = await _open_pty_link(tmp_path)
        with pytest.raises(asyncio.TimeoutError):
            await link.read_within(0.05)
        port.write(b"x")
        assert await link.read_within(5) == b"x"
        link.close()
        port.close()

    asyncio.run(scenario())


@pytest.mark.skipif(not hasattr(asyncio, "timeout"), reason="Python < 3.11: within() is wait_for")
def test_within_never_swallows_a_cancellation_that_meets_the_result() -> None:
    """asyncio.wait_for (Python < 3.12) returns the result when the cancellation arrives as it
    completes: a lidar driver cancelled while connecting streamed on, and the sim's shutdown on
    an early Ctrl-C never ended."""
    from racecar_hw.base.link import within

    async def main() -> None:
        done = asyncio.get_running_loop().create_future()
        task = asyncio.create_task(within(done, 10.0))
        await asyncio.sleep(0)  # the task waits
        done.set_result("connected")
        task.cancel()  # in the same loop iteration
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())
