"""The one loopback rule behind every "non-loopback needs authentication" check."""

from __future__ import annotations

import pytest

from racecar_hw.base.loopback import is_loopback

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)


@pytest.mark.parametrize("host", ["127.0.0.1", "127.1.2.3", "::1", "[::1]", "localhost", "LOCALHOST",
                                  "localhost.localdomain", "ip6-localhost", " 127.0.0.1 "])
def test_loopback_hosts(host: str) -> None:
    assert is_loopback(host)


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "[::]", "192.168.1.10", "10.0.0.1", "car.local",
                                  "localhost.evil.example", "", "fe80::1"])
def test_hosts_that_reach_beyond_this_machine(host: str) -> None:
    assert not is_loopback(host)
