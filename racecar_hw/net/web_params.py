"""The status page's parameters (the ``web`` config section), apart from the server: the config
reads them without importing aiohttp, which :mod:`racecar_hw.net.web` loads only when the page is on."""

from __future__ import annotations

from dataclasses import dataclass

from racecar_hw.base.params import param
from racecar_hw.net.gate import (
    GatedServerParams,
    head_timeout_param,
    idle_timeout_param,
    max_connections_param,
)


@dataclass
class WebParams(GatedServerParams):
    """The status page with the e-stop."""

    enabled: bool = param(True, "serve the status page with the e-stop")
    host: str = param("127.0.0.1", "address to listen on; anything but loopback needs a token",
                      nonempty=True)
    port: int = param(8080, "TCP port (0: any free port, logged at start)", min=0, max=65535)
    token: str = param("", "the page's token (open http://car:8080/?token=...); empty on a "
                           "non-loopback host: one is generated and printed at start")
    push_rate_hz: float = param(10.0, "state updates per second to each open page", unit="Hz",
                                min=1.0, max=30.0)
    scan_points: int = param(360, "scan points per update at most (every n-th beam)", min=10, max=2000)
    max_range_m: float = param(8.0, "scan points farther than this are left out", unit="m",
                               min=1.0, max=60.0)
    max_connections: int = max_connections_param()
    head_timeout_s: float = head_timeout_param()
    idle_timeout_s: float = idle_timeout_param("that sends nothing for this long is closed (an open "
                                               "page answers the server's ping every 5 s)")


__all__ = ["WebParams"]
