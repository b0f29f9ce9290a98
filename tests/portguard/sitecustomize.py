"""The test suite never listens on a default port (7447 Zenoh, 8765 Foxglove, 8080 web, 14550
MAVLink): a user's sim beside the tests would clash with them. tests/conftest.py puts this folder on
PYTHONPATH, so every Python process a test starts imports this and a bind to a default port fails
loudly (a RuntimeError, which no server catches as "port busy") instead of quietly taking it.
Only Python-level binds are seen; Zenoh binds in Rust (tests turn it off or give it a free port).
"""

from __future__ import annotations

import socket

DEFAULT_PORTS = frozenset({7447, 8765, 8080, 14550})
_bind = socket.socket.bind


def _guarded_bind(self: socket.socket, address, /):  # noqa: ANN001, ANN202 - socket.bind's own signature
    if isinstance(address, tuple) and len(address) >= 2 and address[1] in DEFAULT_PORTS:
        raise RuntimeError(f"a test bound the default port {address[1]} ({address[0]}); tests must "
                           "use free ports (tests/conftest.py QUIET_NET, docs/live-view.md)")
    return _bind(self, address)


def install() -> None:
    """Guard ``socket.socket.bind`` in this process."""
    socket.socket.bind = _guarded_bind  # type: ignore[method-assign]


install()
