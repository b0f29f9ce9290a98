"""Open files: the daemon raises its soft limit to the hard one (and puts it back), and an accept()
that finds no descriptor left is a counted log line, not a traceback a second.

Real limits of this process (restored after each test) and a real listening socket on loopback.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import resource
import socket

import pytest

from racecar_hw.net.gate import quiet_accept_errors
from racecar_hw.runtime.fdlimit import raise_open_file_limit
from racecar_hw.runtime.refusals import Refusals


@pytest.fixture
def file_limit():
    """This process's limits, put back after the test."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    yield soft, hard
    resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_the_soft_limit_is_raised_to_the_hard_one_and_put_back(file_limit, caplog):
    _, hard = file_limit
    low = 512 if hard == resource.RLIM_INFINITY or hard > 512 else hard
    if low == hard:
        pytest.skip(f"the hard limit ({hard}) leaves nothing to raise")
    resource.setrlimit(resource.RLIMIT_NOFILE, (low, hard))
    with caplog.at_level(logging.INFO, logger="racecar_hw.runtime.fdlimit"):
        limit = raise_open_file_limit()
    assert limit is not None and (limit.before, limit.soft, limit.hard) == (low, hard, hard)
    assert resource.getrlimit(resource.RLIMIT_NOFILE) == (hard, hard)
    assert f"raised the soft limit from {low} to the hard limit" in caplog.text
    limit.restore()
    assert resource.getrlimit(resource.RLIMIT_NOFILE) == (low, hard)
    # soft = hard (a lowered hard limit cannot be raised again here): see test_net_flood.py, whose sim
    # runs with 1,024 for both and logs "open files: limit 1024 (soft = hard; nothing to raise)"


def test_accept_without_a_free_descriptor_is_counted_once_and_retried(file_limit, caplog):
    refusals = Refusals(interval_s=600.0)
    accepted: list[asyncio.BaseTransport] = []

    class Keep(asyncio.Protocol):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            accepted.append(transport)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        put_back = quiet_accept_errors(loop, refusals)
        server = await loop.create_server(Keep, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        client = socket.socket()
        client.setblocking(False)
        fillers: list[int] = []
        soft, hard = file_limit
        try:
            # no descriptor left in this process: the kernel still completes the client's handshake
            resource.setrlimit(resource.RLIMIT_NOFILE, (len(os.listdir("/proc/self/fd")) + 8, hard))
            with contextlib.suppress(OSError):
                while True:
                    fillers.append(os.open(os.devnull, os.O_RDONLY))
            with contextlib.suppress(BlockingIOError):
                client.connect(("127.0.0.1", port))
            async with asyncio.timeout(30):
                while refusals.total("accept") < 2:  # asyncio tries again every second
                    await asyncio.sleep(0.05)
        finally:
            for fd in fillers:
                os.close(fd)
            resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        async with asyncio.timeout(30):  # descriptors again: the waiting connection is accepted
            while not accepted:
                await asyncio.sleep(0.05)
        client.close()
        server.close()
        put_back()
        assert loop.get_exception_handler() is None

    with caplog.at_level(logging.INFO):
        asyncio.run(main())
    lines = [r for r in caplog.records if "accept" in r.getMessage()]
    assert len(lines) == 1 and lines[0].exc_info is None, [r.getMessage() for r in lines]
    assert "127.0.0.1" in lines[0].getMessage() and "Too many open files" in lines[0].getMessage()
