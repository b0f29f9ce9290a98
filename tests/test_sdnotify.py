"""sd_notify over a real unix datagram socket, as systemd provides it."""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from racecar_hw.runtime.sdnotify import Notifier, watchdog_loop


@pytest.fixture
def notify_socket(tmp_path: Path) -> Iterator[tuple[str, socket.socket]]:
    """A bound datagram socket standing in for systemd's, and its path."""
    path = str(tmp_path / "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(10.0)
    yield path, sock
    sock.close()


def receive(sock: socket.socket) -> str:
    return sock.recv(4096).decode()


def test_from_env_sends_each_state(notify_socket: tuple[str, socket.socket]) -> None:
    path, sock = notify_socket
    with Notifier.from_env({"NOTIFY_SOCKET": path}) as n:
        assert n.enabled
        assert n.ready()
        assert receive(sock) == "READY=1"
        assert n.ready("car ready")
        assert receive(sock) == "READY=1\nSTATUS=car ready"
        assert n.watchdog()
        assert receive(sock) == "WATCHDOG=1"
        assert n.status("vesc: ok\nlidar: reconnecting")
        assert receive(sock) == "STATUS=vesc: ok lidar: reconnecting"
        assert n.stopping()
        assert receive(sock) == "STOPPING=1"
        assert (n.sent, n.send_errors) == (5, 0)


def test_abstract_namespace_socket() -> None:
    name = f"racecar-hw-test-{os.getpid()}-{id(object())}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(10.0)
    try:
        n = Notifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert receive(sock) == "READY=1"
        n.close()
        n.close()
    finally:
        sock.close()


def test_no_socket_is_a_no_op() -> None:
    n = Notifier.from_env({})
    assert not n.enabled
    assert not n.ready() and not n.watchdog() and not n.stopping() and not n.status("x")
    assert (n.sent, n.send_errors) == (0, 0)
    assert n.watchdog_interval_s() is None
    assert not Notifier.from_env({"NOTIFY_SOCKET": ""}).enabled


def test_missing_peer_is_counted_not_raised(tmp_path: Path) -> None:
    n = Notifier.from_env({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert not n.ready()
    assert not n.watchdog()
    assert n.send_errors == 2
    assert n.last_error is not None and "FileNotFoundError" in n.last_error


def test_full_socket_does_not_block(notify_socket: tuple[str, socket.socket]) -> None:
    path, sock = notify_socket
    n = Notifier(path)
    # nobody reads: the receive queue fills and a blocking send would hang the control loop
    results = [n.status("x" * 1000) for _ in range(5000)]
    assert results[0]
    assert not all(results)
    assert n.send_errors == results.count(False)
    assert n.sent == results.count(True)
    n.close()


@pytest.mark.parametrize(("env", "interval"), [
    ({"WATCHDOG_USEC": "2000000"}, 2.0),
    ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "4242"}, 0.5),
    ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, None),
    ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "me"}, None),
    ({"WATCHDOG_USEC": "soon"}, None),
    ({"WATCHDOG_USEC": "0"}, None),
    ({}, None),
])
def test_watchdog_interval(env: dict[str, str], interval: float | None) -> None:
    n = Notifier.from_env({"NOTIFY_SOCKET": "/run/nowhere", **env}, pid=4242)
    assert n.watchdog_interval_s() == interval


def test_watchdog_pid_defaults_to_this_process() -> None:
    env = {"NOTIFY_SOCKET": "/run/nowhere", "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(os.getpid())}
    assert Notifier.from_env(env).watchdog_interval_s() == 1.0


def test_watchdog_loop_pings_only_while_healthy(notify_socket: tuple[str, socket.socket]) -> None:
    path, sock = notify_socket
    sock.setblocking(False)
    n = Notifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "40000"})
    state = {"healthy": True, "checks": 0}

    def healthy() -> bool:
        state["checks"] += 1
        return bool(state["healthy"])

    async def scenario() -> tuple[int, int]:
        task = asyncio.create_task(watchdog_loop(n, healthy))
        deadline = asyncio.get_running_loop().time() + 10.0
        while n.sent < 3:
            assert asyncio.get_running_loop().time() < deadline, "no watchdog pings"
            await asyncio.sleep(0.005)
        state["healthy"] = False
        sent_when_sick = n.sent
        checks = state["checks"]
        while state["checks"] < checks + 3:
            assert asyncio.get_running_loop().time() < deadline, "health no longer checked"
            await asyncio.sleep(0.005)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return sent_when_sick, n.sent

    before, after = asyncio.run(scenario())
    # one event loop: once the flag flips, no further ping passes the health check
    assert after == before
    pings = []
    while True:
        try:
            pings.append(receive(sock))
        except BlockingIOError:
            break
    assert len(pings) == after and set(pings) == {"WATCHDOG=1"}


def test_watchdog_loop_returns_without_watchdog() -> None:
    asyncio.run(asyncio.wait_for(watchdog_loop(Notifier(None)), timeout=10))
    asyncio.run(asyncio.wait_for(watchdog_loop(Notifier("/run/x")), timeout=10))
