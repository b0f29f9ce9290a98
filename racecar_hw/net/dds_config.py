"""The ``dds`` config section, and the Cyclone DDS configuration (XML) it makes. Pure: no I/O.

ROS 2's default middleware is DDS (Fast DDS on Humble, Jazzy and Kilted; Cyclone DDS for many
teams). The daemon speaks it with Cyclone DDS (PyPI ``cyclonedds``), confined to this computer by
default, like the Zenoh bridge: Cyclone uses only the loopback interface, sends no multicast, and
finds ROS 2 nodes by unicast discovery on 127.0.0.1 (the participant ports of ``domain_id``). A
ROS 2 node on this computer finds it with its default discovery or with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (see docs/interop.md for what was verified how).

Beyond loopback (``interface`` set to a LAN address or interface name) the project's rule applies:
network input must be authenticated. DDS Security (what an SROS2 keystore configures) needs
Cyclone's security plugins, which the PyPI build of ``cyclonedds`` does not ship (checked:
:func:`security_plugins_available`), so a non-loopback DDS interface *publishes* the car's topics
but refuses every command (mux inputs, locks, e-stop, ``/cmd_vel``), counted as refusals, unless
``accept_unauthenticated_commands`` says otherwise; the daemon says at start what that means.

Every Cyclone config also carries ``Compatibility/IgnoreTypeInformation`` for eProsima's vendor id
(1.15): Cyclone 11 rejects the XTypes type information Fast DDS 3 sends ("invalid type object"),
and its endpoints would never match Fast DDS's otherwise.
"""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.loopback import is_loopback
from racecar_hw.base.params import param
from racecar_hw.net.topics import ros_domain_id

#: ROS 2 distributions as their DDS graph differs: Humble's ``rmw_dds_common/msg/Gid`` has 24 bytes
#: and no type hashes exist; Iron and later use 16-byte GIDs and RIHS01 hashes in USER_DATA.
DISTROS = ("humble", "jazzy", "kilted", "rolling")
#: eProsima's DDS vendor id, whose type information Cyclone is told to ignore.
FAST_DDS_VENDOR = "1.15"
LOOPBACK = "127.0.0.1"
#: How often the participant announces itself to its unicast peers (Cyclone's default is 30 s). A
#: ROS 2 node with default discovery announces itself by multicast, which does not reach a
#: participant on loopback, so it finds the car only when the car's announcement reaches it: every
#: second, to the discovery port of every participant index up to MAX_PARTICIPANT_INDEX on each peer
#: (121 ports of 127.0.0.1), a few hundred bytes each.
SPDP_INTERVAL = "1s"
#: The highest participant index the daemon takes for itself and announces itself to: Fast DDS's own
#: limit (120; ports 7410 + 250 domain + 10 + 2 index stay below 65536 for every domain id). At 32,
#: Cyclone's default, the 33rd ROS 2 process on the computer (the ros2 daemon and every CLI call
#: count) never found the car, and with 32 ports of the range held the daemon could not start.
MAX_PARTICIPANT_INDEX = 120


@dataclass
class DdsParams:
    """ROS 2 topics over DDS (ROS 2's default middleware), with Cyclone DDS (see docs/interop.md).

    The topic names, the namespace, the node name and ``/cmd_vel`` are the ``zenoh`` section's
    (``profile``, ``remap``, ``namespace``, ``node_name``, ``cmd_vel``, ``cmd_vel_topic``): one
    table, two wires.
    """

    enabled: bool = param(True, "run the DDS interface (this computer only unless interface says "
                                "otherwise)")
    domain_id: int | None = param(None, "ROS domain id; none: ROS_DOMAIN_ID, else 0", min=0, max=232)
    interface: str = param(LOOPBACK, "network interface DDS uses (an address or interface name); "
                                     "127.0.0.1 keeps it on this computer. Any other interface "
                                     "publishes but takes no command unless "
                                     "accept_unauthenticated_commands")
    peers: list[str] = param([LOOPBACK], "addresses to look for ROS 2 nodes at by unicast discovery "
                                         "(127.0.0.1: nodes on this computer)")
    multicast: bool = param(False, "also find ROS 2 nodes by multicast on interface (a LAN; needs "
                                   "a non-loopback interface)")
    accept_unauthenticated_commands: bool = param(
        False, "on a non-loopback interface, accept commands (mux inputs, e-stop, /cmd_vel) from "
               "anyone on that network: DDS here has no authentication (the PyPI Cyclone build has "
               "no DDS Security)")
    ros_distro: str = param("jazzy", "the ROS 2 distribution of the nodes (its node graph format): "
                                     "humble (24-byte GIDs, no type hashes), jazzy, or kilted and "
                                     "rolling (Fast DDS 3: the node is named under the null "
                                     "participant GID, see docs/interop.md)",
                            choices=DISTROS)
    queue_size: int = param(64, "outgoing messages waiting for the publisher thread before the "
                                "oldest is dropped", min=1, max=100000)

    def validate(self, key: str = "dds") -> None:
        """Refuse a malformed interface or peer, and multicast on loopback, naming the key."""
        if not self.interface.strip():
            raise ConfigError(f"{key}.interface", "empty; 127.0.0.1 keeps DDS on this computer")
        for i, peer in enumerate(self.peers):
            host = peer.rsplit(":", 1)[0] if peer.count(":") == 1 else peer
            if not host.strip() or any(c in host for c in "<>\"'& "):
                raise ConfigError(f"{key}.peers[{i}]", f"{peer!r} is not an address")
        if any(c in self.interface for c in "<>\"'& "):
            raise ConfigError(f"{key}.interface", f"{self.interface!r} is not an address or interface name")
        if self.multicast and self.local:
            raise ConfigError(f"{key}.multicast", "multicast needs a LAN interface (dds.interface); on "
                                                  "127.0.0.1 nodes are found by unicast")
        self.resolved_domain_id(key)

    @property
    def local(self) -> bool:
        """Whether DDS stays on this computer (the loopback interface)."""
        return self.interface in ("lo", "localhost") or _is_loopback_address(self.interface)

    @property
    def accepts_commands(self) -> bool:
        """Whether commands from DDS are taken: on loopback, or when explicitly allowed."""
        return self.local or self.accept_unauthenticated_commands

    @property
    def null_participant_gid(self) -> bool:
        """Whether ``ros_discovery_info`` names the node under the null participant GID.

        Fast DDS 3 (Kilted and later) gives the endpoints of a Cyclone participant the participant
        GID zero (Cyclone's endpoint discovery data carries no participant GUID, which is optional
        in DDSI-RTPS, and Fast DDS 3 does not derive it from the endpoint's GUID): seen here with
        the PyPI Kilted wheels. Under the real GID ``ros2 node list`` shows the node but ``ros2
        topic info -v`` shows ``_CREATED_BY_BARE_DDS_APP_``; under the null GID both work, but two
        cars on one domain overwrite each other's entry and a Kilted node keeps listing the car
        after it stopped until that node restarts.
        """
        return self.ros_distro in ("kilted", "rolling")

    @property
    def gid_size(self) -> int:
        """Bytes of a GID in ``ros_discovery_info`` (``rmw_dds_common/msg/Gid``) for ``ros_distro``."""
        return 24 if self.ros_distro == "humble" else 16

    def resolved_domain_id(self, key: str = "dds") -> int:
        """``domain_id``, else ``ROS_DOMAIN_ID`` from the environment, else 0."""
        return ros_domain_id(self.domain_id, f"{key}.domain_id")

    def start_notice(self) -> str | None:
        """What start prints for a non-loopback interface (None on loopback)."""
        if self.local:
            return None
        if self.accept_unauthenticated_commands:
            return (f"DDS on {self.interface}: dds.accept_unauthenticated_commands is on: anyone on "
                    "that network can drive the car, engage or release its e-stop and lock the mux, "
                    "with no authentication (DDS Security is not available in this Cyclone build)")
        return (f"DDS on {self.interface}: publishing only. Commands from DDS (mux inputs, e-stop, "
                "/cmd_vel) are refused and counted, because DDS here has no authentication (no DDS "
                "Security in this Cyclone build); drive over Zenoh with auth or TLS, or set "
                "dds.accept_unauthenticated_commands: true on a network you trust")


def _is_loopback_address(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return is_loopback(text)


def cyclone_xml(params: DdsParams) -> str:
    """The Cyclone DDS configuration (``CYCLONEDDS_URI`` XML) for the section."""
    peers = "".join(f"<Peer address={quoteattr(p)}/>" for p in params.peers)
    if params.interface.replace(".", "").isdigit() or ":" in params.interface:
        interface = f"<NetworkInterface address={quoteattr(params.interface)}/>"
    else:
        interface = f"<NetworkInterface name={quoteattr(params.interface)}/>"
    multicast = "spdp" if params.multicast else "false"
    return (
        '<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any">'
        f"<General><Interfaces>{interface}</Interfaces><AllowMulticast>{multicast}</AllowMulticast>"
        "</General>"
        f"<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>"
        f"{MAX_PARTICIPANT_INDEX}</MaxAutoParticipantIndex><Peers>{peers}</Peers>"
        f"<SPDPInterval>{SPDP_INTERVAL}</SPDPInterval></Discovery>"
        f"<Compatibility><IgnoreTypeInformation>{FAST_DDS_VENDOR}</IgnoreTypeInformation>"
        "</Compatibility>"
        "</Domain></CycloneDDS>")


def participant_ports(domain_id: int) -> list[int]:
    """The unicast discovery ports of participant indices 0..MAX_PARTICIPANT_INDEX in the domain
    (RTPS's default port mapping: 7400 + 250 domain + 10 + 2 index)."""
    base = 7400 + 250 * domain_id + 10
    return [base + 2 * index for index in range(MAX_PARTICIPANT_INDEX + 1)]


def cyclone_available() -> bool:
    """Whether the ``cyclonedds`` package is installed (a dependency on x86_64 only)."""
    import importlib.util  # noqa: PLC0415

    return importlib.util.find_spec("cyclonedds") is not None


def security_plugins_available() -> bool:
    """Whether this Cyclone build ships its DDS Security plugins (``libdds_security_*``)."""
    try:
        import cyclonedds  # noqa: PLC0415
    except ImportError:
        return False
    root = os.path.dirname(os.path.dirname(cyclonedds.__file__))
    for folder in (os.path.join(root, "cyclonedds.libs"), os.path.dirname(cyclonedds.__file__)):
        if os.path.isdir(folder) and any(n.startswith("libdds_security") for n in os.listdir(folder)):
            return True
    return False
