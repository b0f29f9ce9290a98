"""The MAVLink ground-station link's parameters, and the address rules they are checked with.

Apart from :mod:`racecar_hw.teleop.mavlink_gcs` so that the configuration (and ``check-config``)
is read without pymavlink, which the ``mavlink`` extra installs: the link itself is imported only
when ``mavlink.enabled`` is true (docs/install.md, "Extras").
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.loopback import is_loopback
from racecar_hw.base.params import param
from racecar_hw.base.topics import TELEOP_TOPIC

#: ArduPilot Rover's custom mode numbers.
MODES: dict[str, int] = {"MANUAL": 0, "HOLD": 4, "GUIDED": 15}
MODE_NAMES: dict[int, str] = {v: k for k, v in MODES.items()}


def parse_address(text: str, key: str) -> tuple[str, int]:
    """``host:port`` to (host, port); ConfigError naming ``key`` otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(key, f"{text!r} is not host:port")
    return host.strip("[]"), int(port)


def station_host(host: str, key: str) -> str:
    """The ground station's host as datagrams from it name their source: an IP address in its
    canonical form (``2001:DB8::1`` is ``2001:db8::1``), or a loopback name kept as given.

    Any other host name is refused (ConfigError naming ``key``): datagrams are matched by source
    address, so an unresolved name would make every datagram foreign, and a name resolved once at
    start would silently go stale when the laptop's DHCP address changes (or fail at a track
    without DNS).
    """
    if is_loopback(host):
        return host
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        raise ConfigError(key, f"{host!r} is a host name: give the ground station's IP address "
                               "(datagrams are matched by their source address, not by name)") from None


NEEDS_SIGNING = ("the ground station {} is not on loopback: MAVLink 2 signing is required; set "
                  "signing_key_file to a key file")
BIND_NEEDS_SIGNING = ("{} is not a loopback address: listening beyond this computer requires MAVLink 2 "
                      "signing; set mavlink.signing_key_file to a key file, or bind_address to auto")


@dataclass
class MavlinkParams:
    """The ground-station link: addresses, identity, signing, timeouts and teleop scales."""

    enabled: bool = param(False, "run the MAVLink ground-station link")
    gcs_address: str = param("127.0.0.1:14550", "ground station IP:port telemetry is sent to "
                                                "([::1]:14550 for IPv6; no host names but localhost); "
                                                "port 0 = the port its first authenticated message "
                                                "came from; any non-loopback host requires signing")
    gcs_system_id: int = param(255, "the ground station's system id (ArduPilot's SYSID_MYGCS): only "
                                    "its messages are heard; it alone may arm, set modes and drive",
                               min=1, max=255)
    bind_address: str = param("auto", "local address to bind; auto = the loopback address of the "
                                      "ground station's family (127.0.0.1 or ::1) for a loopback "
                                      "ground station, all addresses (0.0.0.0 or ::) otherwise")
    bind_port: int = param(14555, "local UDP port (0 = ephemeral, for tests)", min=0, max=65535)
    system_id: int = param(1, "our MAVLink system id", min=1, max=255)
    component_id: int = param(1, "our MAVLink component id (1 = autopilot)", min=1, max=255)
    signing_key_file: str = param("", "MAVLink 2 signing key: 64 hex digits, 32 raw bytes, or a "
                                      "passphrase (hashed with SHA-256 as MAVProxy does)")
    signing_link_id: int = param(0, "link id in our signatures", min=0, max=255)
    future_window_s: float = param(60.0, "a signed frame stamped more than this far ahead of this "
                                         "car's wall clock is refused and its stream's timestamp "
                                         "is not advanced, so a station with a wrong clock cannot "
                                         "lock the operator out (beyond MAVLink's signing rules); "
                                         "0 = no limit (a car whose clock is not set)", unit="s",
                                   min=0.0, max=86400.0)
    heartbeat_timeout_s: float = param(2.0, "ground station lost after this long without its "
                                            "heartbeat: its teleop input is dropped", unit="s",
                                       min=0.2, max=60.0)
    input_timeout_s: float = param(1.0, "a MANUAL_CONTROL / RC override stops driving this long "
                                        "after it arrived", unit="s", min=0.05, max=10.0)
    rc_override_time_s: float = param(3.0, "an RC override channel value expires this long after the "
                                           "message that set it (ArduPilot's RC_OVERRIDE_TIME); "
                                           "65535 keeps a live value but never revives an expired "
                                           "one", unit="s", min=0.1, max=60.0)
    max_speed_mps: float = param(2.0, "speed at full throttle", unit="m/s", min=0.0, max=20.0)
    max_steering_rad: float = param(0.34, "steering at full deflection (+ left)", unit="rad",
                                    min=0.0, max=1.0)
    throttle_axis: str = param("z", "MANUAL_CONTROL axis carrying throttle (ArduPilot Rover: z)",
                               choices=("z", "x"))
    rc_min_us: int = param(1000, "RC override PWM at full reverse / full left", min=500, max=1500)
    rc_trim_us: int = param(1500, "RC override PWM at rest", min=800, max=2200)
    rc_max_us: int = param(2000, "RC override PWM at full forward / full right", min=1500, max=2500)
    start_mode: str = param("MANUAL", "mode at start", choices=tuple(MODES))
    rate_hz: float = param(20.0, "teleop command rate", unit="Hz", min=1.0, max=100.0)
    telemetry_rate_hz: float = param(4.0, "ATTITUDE, LOCAL_POSITION_NED, OBSTACLE_DISTANCE rate",
                                     unit="Hz", min=0.1, max=50.0)
    teleop_topic: str = param(TELEOP_TOPIC, "mux input the ground station drives", topic=True)
    vesc_state_topic: str = param("/vesc/sensors/core", "vesc_msgs/VescStateStamped", topic=True)
    odom_topic: str = param("/odom", "nav_msgs/Odometry", topic=True)
    scan_topic: str = param("/scan", "sensor_msgs/LaserScan", topic=True)
    safety_topic: str = param("/safety/state", "diagnostic_msgs/DiagnosticArray", topic=True)

    def __post_init__(self) -> None:
        host, _ = parse_address(self.gcs_address, "mavlink.gcs_address")
        station_host(host, "mavlink.gcs_address")
        if not self.rc_min_us < self.rc_trim_us < self.rc_max_us:
            raise ConfigError("mavlink.rc_trim_us", "must lie strictly between rc_min_us and rc_max_us")
        if self.enabled and not self.signing_key_file and not is_loopback(host):
            raise ConfigError("mavlink.signing_key_file", NEEDS_SIGNING.format(self.gcs_address))
        bind_host = self.bind[0]
        if self.enabled and not self.signing_key_file and not is_loopback(bind_host):
            raise ConfigError("mavlink.bind_address", BIND_NEEDS_SIGNING.format(bind_host))

    @property
    def gcs(self) -> tuple[str, int]:
        """The ground station's (host, port); the host as :func:`station_host` gives it."""
        host, port = parse_address(self.gcs_address, "mavlink.gcs_address")
        return station_host(host, "mavlink.gcs_address"), port

    @property
    def bind(self) -> tuple[str, int]:
        """The local (host, port) to bind: IPv6 when the ground station's address is IPv6."""
        host = self.bind_address
        if host == "auto":
            v6 = ":" in self.gcs[0]
            if is_loopback(self.gcs[0]):
                host = "::1" if v6 else "127.0.0.1"
            else:
                host = "::" if v6 else "0.0.0.0"
        return host, self.bind_port


__all__ = ["MODES", "MODE_NAMES", "MavlinkParams", "parse_address", "station_host"]
