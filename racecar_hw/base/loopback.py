"""Which hosts keep a socket on this machine: the one rule behind every "non-loopback needs
authentication" check (MAVLink signing, Zenoh TLS or user/password, the web and Foxglove token)."""

from __future__ import annotations

import ipaddress

#: Host names that always mean this machine.
LOCAL_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost")


def is_loopback(host: str) -> bool:
    """Whether ``host`` only reaches this machine: a loopback address (127.0.0.0/8, ::1, with or
    without brackets) or one of :data:`LOCAL_NAMES`. Other host names and the wildcard addresses
    (``0.0.0.0``, ``::``: every interface) are not."""
    name = host.strip().strip("[]").lower()
    if name in LOCAL_NAMES:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False
