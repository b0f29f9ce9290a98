"""The ``zenoh`` config section, and the Zenoh session configuration it makes.

Safe by default: the daemon listens on loopback only (``tcp/127.0.0.1:7447``) with multicast
scouting off, so nothing on the LAN reaches it or is reached by it. Listening on any other address
needs authentication: user/password (``auth.dictionary_file``) or mutual TLS (a ``tls/`` or
``quic/`` endpoint with ``tls.listen_certificate``, ``listen_private_key``, ``root_ca_certificate``
and ``enable_mtls``); otherwise the daemon refuses to start, naming the key (the same rule as
MAVLink signing). The files are read when the config loads (:mod:`racecar_hw.net.zenoh_security`):
a dictionary with no ``user:password`` line would make Zenoh drop authentication without a word.

Every mode takes rmw_zenoh's settings from ``DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5`` and
``DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5`` where they matter here (:data:`RMW_ZENOH_SETTINGS`;
docs/interop.md lists what differs and why).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.loopback import is_loopback
from racecar_hw.base.params import param
from racecar_hw.net.topics import ros_domain_id
from racecar_hw.net.zenoh_security import check_credentials, check_pem, dictionary_users

MODES = ("peer", "router", "client")
#: ``zenoh.ros_distro``: the ROS 2 distribution family of the rmw_zenoh peers (rmw.ROS_DISTROS)
ROS_DISTROS = ("jazzy", "humble")
PROFILES = ("racecar", "f1tenth")
DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream")
_ENCRYPTED = ("tls", "quic")


@dataclass
class ZenohAuthParams:
    """Zenoh user/password authentication."""

    dictionary_file: str = param("", "file of user:password lines (at least one; read when the config "
                                     "loads); a session that connects to this daemon must present one")
    user: str = param("", "user name this daemon presents when it connects out (client/peer connect)")
    password: str = param("", "password this daemon presents with user")


@dataclass
class ZenohTlsParams:
    """Zenoh TLS (for ``tls/`` and ``quic/`` endpoints)."""

    listen_certificate: str = param("", "PEM certificate this daemon presents on tls/ and quic/ listens")
    listen_private_key: str = param("", "PEM private key of listen_certificate")
    root_ca_certificate: str = param("", "PEM CA certificate that signed the peers' certificates "
                                         "(needed by enable_mtls)")
    enable_mtls: bool = param(False, "require connecting sessions to present a certificate signed by "
                                     "root_ca_certificate (mutual TLS)")


#: Why ``multicast_scouting: true`` is refused.
MULTICAST_REFUSED = (
    "multicast scouting listens on every interface and connects the car to any Zenoh peer on the LAN "
    "that answers; Zenoh's user/password and TLS check only the sessions others open to the car, so "
    "such a peer could read and drive it. Name the routers or peers in connect (and listen with auth "
    "or TLS beyond loopback) instead")


@dataclass
class ZenohParams:
    """ROS 2 topics over Zenoh in rmw_zenoh's format (see docs/interop.md)."""

    enabled: bool = param(True, "run the Zenoh bridge (loopback only unless listen says otherwise)")
    mode: str = param("peer", "peer (talk to peers directly), router (be the Zenoh router that ROS 2 "
                              "nodes and laptops connect to, like rmw_zenohd) or client (go through "
                              "the router in connect)", choices=MODES)
    listen: list[str] = param([DEFAULT_ENDPOINT], "Zenoh endpoints to listen on; a non-loopback "
                                                  "address needs tls or auth")
    connect: list[str] = param([], "Zenoh endpoints to connect to (a router such as rmw_zenohd, or "
                                   "another car)")
    domain_id: int | None = param(None, "ROS domain id; none: ROS_DOMAIN_ID, else 0", min=0, max=232)
    namespace: str = param("", "ROS namespace of every topic and of the node, e.g. /car1")
    node_name: str = param("racecar_hw", "the ROS node name the car shows in ros2 node list")
    ros_distro: str = param("jazzy", "the ROS 2 distribution of the rmw_zenoh nodes: jazzy (Jazzy, "
                                      "Kilted, Lyrical, Rolling: RIHS01 type hashes in keys) or humble "
                                      "(rmw_zenoh 0.1.x: TypeHashNotSupported); the two never meet on a "
                                      "key. Jazzy's rmw_zenoh 0.2.0-0.2.3 cannot talk to the car: update it",
                            choices=ROS_DISTROS)
    profile: str = param("racecar", "topic names: racecar (MIT/MuSHR ROS 1 names, as on the bus) or "
                                    "f1tenth (F1TENTH ROS 2 names: /drive, /teleop, /sensors/core)",
                         choices=PROFILES)
    remap: dict[str, str] = param({}, "bus topic -> ROS name, after the profile; two topics may not "
                                      "share a name")
    cmd_vel: bool = param(True, "accept geometry_msgs/Twist on cmd_vel_topic as the mux input "
                                "cmd_vel (priority 18), converted with vesc.wheelbase_m")
    cmd_vel_topic: str = param("/cmd_vel", "the Twist topic")
    queue_size: int = param(64, "outgoing messages waiting for the publisher thread before the "
                                "oldest is dropped", min=1, max=100000)
    multicast_scouting: bool = param(False, "find peers by UDP multicast: refused (true is a "
                                            "ConfigError), since it listens on every interface and "
                                            "connects to any LAN peer that answers, unauthenticated; "
                                            "name peers and routers in connect")
    count_failed_logins: bool = param(True, "count failed logins (user/password, TLS) by source address "
                                            "in /diagnostics, the status page and the log, read from "
                                            "Zenoh's own log on standard output (racecar-hw run, sim "
                                            "and follow, when a listen authenticates)")
    auth: ZenohAuthParams = field(default_factory=ZenohAuthParams, metadata={"doc": "user/password"})
    tls: ZenohTlsParams = field(default_factory=ZenohTlsParams, metadata={"doc": "TLS"})

    def authenticates(self) -> bool:
        """Whether a session must log in to reach this daemon's listeners (user/password, TLS)."""
        return bool(self.auth.dictionary_file or self.tls.enable_mtls
                    or any(e.startswith(("tls/", "quic/")) for e in self.listen))

    def validate(self, key: str = "zenoh") -> None:
        """Refuse bad endpoints, names and an unauthenticated non-loopback listen, naming the key."""
        from racecar_hw.net import rmw  # noqa: PLC0415 - rmw imports the typestore; keep config light

        for name in ("listen", "connect"):
            for i, endpoint in enumerate(getattr(self, name)):
                parse_endpoint(endpoint, f"{key}.{name}[{i}]")
        checks = (("namespace", lambda: rmw.check_namespace(self.namespace)),
                  ("node_name", lambda: rmw.check_topic_name("/" + self.node_name)),
                  ("cmd_vel_topic", lambda: rmw.check_topic_name(self.cmd_vel_topic)))
        for name, check in checks:
            try:
                check()
            except rmw.WireError as err:
                raise ConfigError(f"{key}.{name}", str(err)) from None
        if "/" in self.node_name:
            raise ConfigError(f"{key}.node_name", "a node name has no '/'")
        for bus, ros in self.remap.items():
            try:
                rmw.check_topic_name(ros)
            except rmw.WireError as err:
                raise ConfigError(f"{key}.remap.{bus}", str(err)) from None
        if self.multicast_scouting:
            raise ConfigError(f"{key}.multicast_scouting", MULTICAST_REFUSED)
        a, t = self.auth, self.tls
        check_credentials(a.user, a.password, f"{key}.auth.user", f"{key}.auth.password")
        if a.dictionary_file:
            dictionary_users(a.dictionary_file, f"{key}.auth.dictionary_file")
        for i, endpoint in enumerate(self.listen):
            proto, host, _ = parse_endpoint(endpoint, f"{key}.listen[{i}]")
            if proto == "unixsock-stream" or is_loopback(host):
                continue
            if a.dictionary_file:
                continue
            if proto in _ENCRYPTED and t.enable_mtls:
                continue
            raise ConfigError(f"{key}.listen[{i}]", f"{endpoint} listens beyond this machine without "
                              "authentication: anyone on the network could read the car and drive it. "
                              f"Set {key}.auth.dictionary_file (user/password), or use a tls/ endpoint "
                              f"with {key}.tls.listen_certificate, listen_private_key, "
                              "root_ca_certificate and enable_mtls: true; or listen on 127.0.0.1")
        self._validate_tls(key)

    def _validate_tls(self, key: str) -> None:
        """Refuse TLS settings Zenoh would refuse at start, or that would not protect what they say."""
        t = self.tls
        if bool(t.listen_certificate) != bool(t.listen_private_key):
            raise ConfigError(f"{key}.tls.listen_private_key" if t.listen_certificate
                              else f"{key}.tls.listen_certificate",
                              "listen_certificate and listen_private_key go together")
        if t.enable_mtls and not t.root_ca_certificate:
            raise ConfigError(f"{key}.tls.root_ca_certificate", "enable_mtls needs the CA certificate "
                              "that signed the certificates of the sessions allowed in")
        for i, endpoint in enumerate(self.listen):
            if endpoint.split("/", 1)[0] in _ENCRYPTED and not t.listen_certificate:
                raise ConfigError(f"{key}.tls.listen_certificate", f"{endpoint} ({key}.listen[{i}]) needs "
                                  "a certificate and its private key (tls.listen_certificate, "
                                  "listen_private_key)")
        for name, kind in (("listen_certificate", "CERTIFICATE"), ("listen_private_key", "PRIVATE KEY"),
                           ("root_ca_certificate", "CERTIFICATE")):
            if getattr(t, name):
                check_pem(getattr(t, name), f"{key}.tls.{name}", kind)

    def resolved_domain_id(self) -> int:
        """``domain_id``, else ``ROS_DOMAIN_ID`` from the environment, else 0."""
        return ros_domain_id(self.domain_id, "zenoh.domain_id")


def parse_endpoint(endpoint: str, key: str) -> tuple[str, str, int | None]:
    """``proto/host:port[#...]`` as (protocol, host, port); ConfigError naming ``key`` if malformed."""
    proto, sep, rest = endpoint.partition("/")
    if not sep or proto not in _PROTOCOLS:
        raise ConfigError(key, f"{endpoint!r} is not a Zenoh endpoint (like tcp/127.0.0.1:7447); "
                               f"protocols: {', '.join(_PROTOCOLS)}")
    address = rest.split("#", 1)[0].split("?", 1)[0]
    if proto == "unixsock-stream":
        return proto, address, None
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or not host or int(port) > 65535:
        raise ConfigError(key, f"{endpoint!r}: expected host:port")
    return proto, host.strip("[]"), int(port)


def check_connect(endpoint: object, key: str) -> str:
    """``endpoint`` if it is ``<protocol>/<address>`` (``tcp/127.0.0.1:7447``), checked before Zenoh
    reads it (its error for ``localhost:7447`` is a JSON5 parse error); ConfigError naming ``key``,
    with the likely fix for a bare ``host:port``."""
    try:
        if not isinstance(endpoint, str):
            raise ConfigError(key, f"{endpoint!r} is not a Zenoh endpoint (like tcp/127.0.0.1:7447)")
        parse_endpoint(endpoint, key)
    except ConfigError as err:
        if isinstance(endpoint, str) and "/" not in endpoint and ":" in endpoint:
            raise ConfigError(err.key, f"{str(err).removeprefix(f'{err.key}: ')}; did you mean "
                                       f"'tcp/{endpoint}'?") from None
        raise
    return endpoint


#: rmw_zenoh's settings (rmw_zenoh_cpp/config/DEFAULT_RMW_ZENOH_{ROUTER,SESSION}_CONFIG.json5, as of
#: rmw_zenoh PRs #509 and #820) that matter here, set even where they equal Zenoh 1.10's defaults so
#: another Zenoh release cannot change them; the router and session files agree on all of them.
#: Their ``routing/router/peers_failover_brokering`` is left out: Zenoh 1.10 ignores it (and warns).
RMW_ZENOH_SETTINGS: dict[str, Any] = {
    "scouting/gossip/enabled": True,
    "scouting/gossip/multihop": False,
    "scouting/gossip/target": {"router": ["router", "peer"], "peer": ["router"]},
    "scouting/gossip/autoconnect": {"router": [], "peer": ["router", "peer"]},
    # the publication caches behind TRANSIENT_LOCAL need timestamps
    "timestamping/enabled": {"router": True, "peer": True, "client": True},
    # ms; only the advanced subscribers' history queries use it (10 min, PR #820)
    "queries_default_timeout": 600000,
    # many ROS nodes starting at once on a loaded computer: handshakes and leases get time (PR #509)
    "transport/unicast/open_timeout": 60000,
    "transport/unicast/accept_timeout": 60000,
    "transport/unicast/accept_pending": 10000,
    "transport/unicast/max_sessions": 10000,
    "transport/link/tx/lease": 60000,
    "transport/link/tx/keep_alive": 2,
}


def session_config(mode: str, listen: list[str], connect: list[str], *, multicast: bool = False,
                   auth: ZenohAuthParams | None = None, tls: ZenohTlsParams | None = None) -> Any:
    """A ``zenoh.Config`` for a session: rmw_zenoh's settings (:data:`RMW_ZENOH_SETTINGS`), these
    endpoints, and the credentials given."""
    import zenoh  # noqa: PLC0415 - the Rust extension loads only when a session is opened

    values: dict[str, Any] = {
        "mode": mode,
        "listen/endpoints": listen,
        "connect/endpoints": connect,
        "scouting/multicast/enabled": multicast,
        **RMW_ZENOH_SETTINGS,
        # a listen that fails (port in use) ends the open with an error instead of retrying
        "listen/exit_on_failure": True,
    }
    if mode == "client":
        values["connect/timeout_ms"] = 3000
    if auth is not None:
        if auth.dictionary_file:
            values["transport/auth/usrpwd/dictionary_file"] = auth.dictionary_file
        if auth.user:
            values["transport/auth/usrpwd/user"] = auth.user
            values["transport/auth/usrpwd/password"] = auth.password
    if tls is not None:
        for name in ("listen_certificate", "listen_private_key", "root_ca_certificate"):
            if getattr(tls, name):
                values[f"transport/link/tls/{name}"] = getattr(tls, name)
        if tls.enable_mtls:
            values["transport/link/tls/enable_mtls"] = True
    config = zenoh.Config()
    for path, value in values.items():
        config.insert_json5(path, json.dumps(value))
    return config


def config_for(params: ZenohParams) -> Any:
    """The daemon's ``zenoh.Config`` from its section."""
    return session_config(params.mode, params.listen, params.connect,
                          multicast=params.multicast_scouting, auth=params.auth, tls=params.tls)
