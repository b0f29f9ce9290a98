"""The Foxglove live view's parameters, apart from the server.

The configuration (and ``check-config``) is read without the Foxglove SDK, which the ``foxglove``
extra installs: :mod:`racecar_hw.net.foxglove_server` is imported only when ``foxglove.enabled`` is
true (docs/install.md, "Extras").
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import urlsplit

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.loopback import is_loopback
from racecar_hw.base.params import param
from racecar_hw.base.topics import FOXGLOVE_TELEOP_TOPIC
from racecar_hw.net.gate import (
    GatedServerParams,
    head_timeout_param,
    idle_timeout_param,
    max_connections_param,
)

#: Foxglove's web app (and its older and embedded addresses): pages that may connect without a token.
DEFAULT_ORIGINS = ("https://app.foxglove.dev", "https://studio.foxglove.dev", "https://embed.foxglove.dev")


@dataclass
class FoxgloveParams(GatedServerParams):
    """The Foxglove live-view server."""

    enabled: bool = param(True, "serve the live view to Foxglove and Lichtblick (WebSocket)")
    host: str = param("127.0.0.1", "address to listen on; anything but loopback needs token",
                      nonempty=True)
    port: int = param(8765, "TCP port (0: any free port, logged at start)", min=0, max=65535)
    token: str = param("", "required in the URL (ws://car:8765/?token=...) when host is not loopback; "
                           "optional on loopback")
    allowed_origins: list[str] = param(list(DEFAULT_ORIGINS),
                                       "web origins whose pages may connect without a token (besides "
                                       "pages served by this machine and desktop apps); 'null' admits "
                                       "every opaque origin, including any site's sandboxed frames")
    teleop: bool = param(True, "let Foxglove's Teleop panel drive through the mux input 'foxglove'")
    teleop_topic: str = param(FOXGLOVE_TELEOP_TOPIC, "geometry_msgs/Twist topic the Teleop panel publishes",
                              topic=True)
    teleop_priority: int = param(85, "priority of the mux input 'foxglove' (below teleop's 90)",
                                 min=0, max=255)
    teleop_timeout_s: float = param(0.3, "the car stops this long after the last Twist (a closed tab, "
                                         "dropped Wi-Fi); the shipped layout publishes at 10 Hz",
                                    unit="s", min=0.05, max=2.0)
    teleop_max_speed_mps: float = param(1.0, "largest speed a Twist may ask for", unit="m/s",
                                        min=0.0, max=10.0)
    scene_rate_hz: float = param(10.0, "rate of /safety/scene and /safety/speeds", unit="Hz",
                                 min=0.5, max=50.0)
    queue_size: int = param(1000, "messages waiting for the sender thread before the oldest are dropped",
                            min=10, max=100_000)
    max_connections: int = max_connections_param()
    head_timeout_s: float = head_timeout_param()
    idle_timeout_s: float = idle_timeout_param("on which nothing moves either way for this long is "
                                               "closed (a viewer with no channel subscribed reconnects)")

    def __post_init__(self) -> None:
        origins = []
        for i, origin in enumerate(self.allowed_origins):
            if not isinstance(origin, str) or not _is_origin(origin):
                raise ConfigError(f"foxglove.allowed_origins[{i}]",
                                  f"{origin!r} is not an origin: scheme://host[:port] with no path "
                                  "(https://lichtblick.example.org), or null")
            origins.append(origin.strip().lower().rstrip("/"))
        self.allowed_origins = origins
        if self.enabled and not is_loopback(self.host) and not self.token:
            # keyed on the host, the value that needs the token: check-config names where it was set
            raise ConfigError("foxglove.host", f"{self.host!r} is not loopback: set foxglove.token "
                                               "(clients add ?token=... to the URL), or keep host "
                                               "127.0.0.1 and reach it over ssh -L")


def _is_origin(text: str) -> bool:
    text = text.strip().rstrip("/")
    if text.lower() == "null":
        return True
    parts = urlsplit(text)
    try:
        parts.port  # noqa: B018 - raises on a bad port
    except ValueError:
        return False
    return bool(parts.scheme and parts.hostname) and not (parts.path or parts.query or parts.fragment
                                                          or parts.username or parts.password)


__all__ = ["DEFAULT_ORIGINS", "FoxgloveParams"]
