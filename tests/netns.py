"""A private network namespace for the DDS tests, and the ROS 2 environment they run rclpy from.

DDS finds peers by UDP discovery on well-known ports of a domain; a test on the host's network would
meet other jobs' participants (and theirs ours). Each test runs its processes in a namespace of its
own with only loopback (``unshare -n``, root), so nothing leaves it and nothing from outside reaches
it. ``multicast=True`` gives ``lo`` the MULTICAST flag and a 224.0.0.0/4 route, so ROS 2's default
discovery (multicast) works in it; without it, ``lo`` is as on a normal host (no multicast) and only
unicast discovery on 127.0.0.1 can work. ``lan`` adds an interface with that address
(``10.77.0.1/24``, say): an interface beyond loopback, for the tests of what DDS accepts there.

The ROS 2 environment is a virtual environment with the PyPI Kilted wheels (``ros-rclpy[fastrtps]``
and the message packages), made by ``.ci/run`` at ``.ros-venv`` (or ``$RACECAR_ROS_VENV``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROS_VENV = Path(os.environ.get("RACECAR_ROS_VENV", ROOT / ".ros-venv"))


def ros_python() -> str:
    """The ROS 2 environment's python; skips the test, saying why, where it is missing."""
    python = ROS_VENV / "bin" / "python"
    if not python.exists():
        pytest.skip(f"no ROS 2 environment at {ROS_VENV}: .ci/run installs the PyPI Kilted wheels "
                    "(ros-rclpy[fastrtps], ros-*-msgs) there; they exist for x86_64 Linux, CPython 3.11/3.12")
    probe = subprocess.run([str(python), "-c", "import rclpy, sensor_msgs.msg, nav_msgs.msg"],
                           capture_output=True, text=True, timeout=120)
    if probe.returncode != 0:
        pytest.skip(f"the ROS 2 environment at {ROS_VENV} cannot import rclpy: {probe.stderr.strip()[-300:]}")
    return str(python)


class NetNs:
    """A network namespace held open by a sleeping process; :meth:`popen` runs commands inside it."""

    def __init__(self, holder: subprocess.Popen[bytes]) -> None:
        self.holder = holder
        self.prefix = ["nsenter", "-t", str(holder.pid), "-n", "--"]

    def ip(self, *args: str) -> None:
        subprocess.run([*self.prefix, "ip", *args], check=True, capture_output=True, timeout=30)

    def popen(self, command: Sequence[str], **kwargs: Any) -> subprocess.Popen[Any]:
        return subprocess.Popen([*self.prefix, *command], **kwargs)

    def run(self, command: Sequence[str], **kwargs: Any) -> subprocess.CompletedProcess[Any]:
        return subprocess.run([*self.prefix, *command], **kwargs)


def _netns_of(pid: int) -> str | None:
    try:
        return os.readlink(f"/proc/{pid}/ns/net")
    except OSError:
        return None


@contextmanager
def netns(*, multicast: bool = True, lan: str | None = None) -> Iterator[NetNs]:
    """A fresh network namespace with loopback up; skips where namespaces cannot be made (not root)."""
    for tool in ("unshare", "nsenter", "ip"):
        if shutil.which(tool) is None:
            pytest.skip(f"{tool} (util-linux / iproute2) is not installed: the DDS tests run in a "
                        "private network namespace")
    if os.geteuid() != 0:
        pytest.skip("the DDS tests make a private network namespace (unshare -n), which needs root")
    holder = subprocess.Popen(["unshare", "-n", "--", "sleep", "3600"])
    ns = NetNs(holder)
    try:
        # unshare(1) makes the namespace after it started: until then nsenter would enter ours
        own = os.readlink("/proc/self/ns/net")
        deadline = time.monotonic() + 30
        while _netns_of(holder.pid) in (own, None):
            if holder.poll() is not None or time.monotonic() > deadline:
                pytest.skip("unshare -n did not make a network namespace here")
            time.sleep(0.01)
        try:
            ns.ip("link", "set", "lo", "up")
        except subprocess.CalledProcessError as err:
            pytest.skip(f"cannot configure a private network namespace here: {err.stderr!r}")
        if multicast:
            ns.ip("link", "set", "lo", "multicast", "on")
            ns.ip("route", "add", "224.0.0.0/4", "dev", "lo")
        if lan:
            # a veth pair (the dummy module is not always there): lan0 has the address
            ns.ip("link", "add", "lan0", "type", "veth", "peer", "name", "lan1")
            ns.ip("addr", "add", lan, "dev", "lan0")
            ns.ip("link", "set", "lan1", "up")
            ns.ip("link", "set", "lan0", "up", "multicast", "on")
            if not multicast:  # as on a host: multicast goes out on the LAN
                ns.ip("route", "add", "224.0.0.0/4", "dev", "lan0")
        yield ns
    finally:
        holder.kill()
        holder.wait(10)
