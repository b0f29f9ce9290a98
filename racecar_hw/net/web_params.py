"""The status page's parameters (the ``web`` config section), apart from the server: the config
reads them without importing aiohttp, which :mod:`racecar_hw.net.web` loads only when the page is on."""

from __future__ import annotations

from dataclasses import dataclass

from racecar_hw.base.params import param
from racecar_hw.net.gate import ConnectionLimits


@dataclass
class WebParams:
    """The status page with the e-stop."""

    enabled: bool = param(True, "serve the status page with the e-stop")
    host: str = param("127.0.0.1", "address to listen on; anything but loopback needs a token")
    port: int = param(8080, "TCP port (0: any free port, logged at start)", min=0, max=65535)
    token: str = param("", "the page's token (open http://car:8080/?token=...); empty on a "
                           "non-loopback host: one is generated and printed at start")
    push_rate_hz: float = param(10.0, "state updates per second to each open page", unit="Hz",
                                min=1.0, max=30.0)
    scan_points: int = param(360, "scan points per update at most (every n-th beam)", min=10, max=2000)
    max_range_m: float = param(8.0, "scan points farther than this are left out", unit="m",
                               min=1.0, max=60.0)
    max_connections: int = param(32, "connections open at once at most; beyond it the oldest one that has "
                                     "not finished its request is closed, else the new one",
                                 min=1, max=1000)
    head_timeout_s: float = param(5.0, "a connection must send its request head within this",
                                  unit="s", min=0.5, max=60.0)
    idle_timeout_s: float = param(60.0, "a connection that sends nothing for this long is closed (an open "
                                        "page answers the server's ping every 5 s)",
                                  unit="s", min=10.0, max=3600.0)

    def limits(self) -> ConnectionLimits:
        """The connection cap and timeouts."""
        return ConnectionLimits(self.max_connections, self.head_timeout_s, self.idle_timeout_s)


__all__ = ["WebParams"]
