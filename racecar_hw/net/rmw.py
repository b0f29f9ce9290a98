"""rmw_zenoh's wire format, without I/O: key expressions, attachments, liveliness tokens, QoS strings.

ROS 2's Zenoh middleware (``rmw_zenoh_cpp``) puts every topic on Zenoh as follows (sources:
``ros2/rmw_zenoh`` ``docs/design.md`` and ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``,
``attachment_helpers.cpp``, ``qos.cpp``, ``rmw_publisher_data.cpp``):

* **Data key**: ``<domain_id>/<topic without its leading and trailing '/'>/<DDS type>/<type hash>``,
  e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``. The DDS type of
  ``sensor_msgs/msg/LaserScan`` is ``sensor_msgs::msg::dds_::LaserScan_``; the type hash is the
  RIHS01 hash of the full type description (REP-2011), here from rosbags' typestore.
* **Payload**: CDR, little endian, with its 4-byte encapsulation header (:mod:`racecar_hw.rosmsg`).
* **Attachment** on every sample: int64 sequence number (per publisher, from 1), int64 source
  timestamp (ns since the epoch), then the 16-byte publisher GID as a Zenoh-serialized byte array
  (a LEB128 length, 0x10, then the bytes): 33 bytes. rmw_zenoh drops a sample without one.
* **Liveliness tokens** make the ROS graph (``ros2 node list``, ``ros2 topic list``)::

      @ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
      @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node name>
          /<topic>/<DDS type>/<type hash>/<qos>

  where every ``/`` inside a part is ``%`` and an empty part is ``%`` (``/scan`` -> ``%scan``).
* **QoS string**: ``R:D:H,depth:DLs,DLns:LSs,LSns:L,Ls,Lns``, each value empty when it equals
  rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite durations, automatic).
* **GID**: XXH3-128 of the entity's liveliness token, low 64 bits first (``liveliness_utils.cpp``).
* **Distributions**: rmw_zenoh's Humble releases (0.1.x) write :data:`HUMBLE_TYPE_HASH`
  (``TypeHashNotSupported``) where later releases write the RIHS01 hash, in data keys and tokens
  alike (:func:`wire_type_hash`); a Humble node and a Jazzy+ node never meet on a key. rmw_zenoh
  0.10+ (Lyrical, Rolling) may append a 14th ``backends`` field to endpoint tokens. Jazzy releases
  0.2.0-0.2.3 used an older attachment (string keys) that nothing here decodes: update them.

Everything here is pure: strings and bytes in, strings, bytes and typed values out.
"""

from __future__ import annotations

import functools
import re
import struct
from dataclasses import dataclass, field

import xxhash

from racecar_hw.base.errors import RacecarError
from racecar_hw.net.topics import Durability, Qos, Reliability
from racecar_hw.rosmsg.typestore import ros2_types

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
ATTACHMENT_SIZE = 33
#: rmw_zenoh's defaults (``qos.cpp``), left out of a QoS string
DEFAULT_DEPTH = 42
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC = 1
#: ``RMW_DURATION_INFINITE``: a deadline, lifespan or lease that never expires
INFINITE_S, INFINITE_NS = 9223372036, 854775807

#: What rmw_zenoh's Humble releases put where later releases put the RIHS01 type hash.
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
#: The peer distribution families (``zenoh.ros_distro``): Humble, or Jazzy and every later release.
ROS_DISTROS = ("jazzy", "humble")

NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT = "NN", "MP", "MS", "SS", "SC"
ENTITY_KINDS = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)

_ATTACHMENT = struct.Struct("<qqB16s")
_NAME_PART = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class WireError(RacecarError):
    """Bytes or a key that do not follow rmw_zenoh's format."""


# --- names and types ----------------------------------------------------------------------------


def dds_type(ros_type: str) -> str:
    """The DDS type name of a ROS 2 type: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = _split_type(ros_type)
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """The ROS 2 type name of a DDS type name (inverse of :func:`dds_type`)."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise WireError(f"{dds!r} is not a DDS type name (pkg::msg::dds_::Name_)")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _split_type(ros_type: str) -> tuple[str, str, str]:
    parts = ros_type.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv", "action") or not all(parts):
        raise WireError(f"{ros_type!r} is not a ROS 2 type name (pkg/msg/Name)")
    return parts[0], parts[1], parts[2]


def check_topic_name(name: str) -> str:
    """``name`` if it is an absolute ROS 2 topic name (``/a/b_c``), else :class:`WireError`.

    ROS 2 names (design article "Topic and Service name mapping"): tokens of letters, digits and
    underscores, not starting with a digit, separated by single slashes; no trailing slash.
    """
    if not name.startswith("/") or name == "/" or name.endswith("/"):
        raise WireError(f"{name!r} is not an absolute topic name (like /scan or /car1/odom)")
    for token in name[1:].split("/"):
        if not _NAME_PART.fullmatch(token) or "__" in token:
            raise WireError(f"{name!r} is not a valid ROS 2 topic name (bad part {token!r})")
    return name


def check_namespace(namespace: str) -> str:
    """A namespace normalised to ``""`` (none) or ``/a/b``; :class:`WireError` if invalid."""
    if namespace in ("", "/"):
        return ""
    if not namespace.startswith("/"):
        namespace = "/" + namespace
    check_topic_name(namespace)
    return namespace


def strip_slashes(name: str) -> str:
    """``name`` without one leading and one trailing slash, as rmw_zenoh builds data keys."""
    if name.startswith("/"):
        name = name[1:]
    if name.endswith("/"):
        name = name[:-1]
    return name


def mangle(name: str) -> str:
    """A name as a liveliness token part: ``/`` becomes ``%``; an empty name is ``%``."""
    return name.replace("/", "%") if name else "%"


def demangle(part: str) -> str:
    """The name a liveliness token part stands for (``%`` becomes ``/``)."""
    return part.replace("%", "/")


@functools.cache
def type_hash(ros_type_name: str) -> str:
    """The RIHS01 hash of a ROS 2 type, from the full type description in racecar-hw's typestore."""
    return ros2_types().digest(ros_type_name)


def wire_type_hash(ros_type_name: str, distro: str = "jazzy") -> str:
    """The type hash field of keys and tokens for peers of ``distro`` (one of :data:`ROS_DISTROS`)."""
    if distro == "humble":
        return HUMBLE_TYPE_HASH
    if distro != "jazzy":
        raise WireError(f"unknown ROS distribution family {distro!r}; one of {', '.join(ROS_DISTROS)}")
    return type_hash(ros_type_name)


def topic_key(domain_id: int, topic: str, ros_type_name: str, type_hash: str) -> str:
    """The Zenoh key a topic's samples are put on."""
    return f"{domain_id}/{strip_slashes(topic)}/{dds_type(ros_type_name)}/{type_hash}"


def topic_key_pattern(domain_id: int, topic: str) -> str:
    """A key expression matching ``topic`` whatever its type and hash (for ``topic echo``)."""
    return f"{domain_id}/{strip_slashes(topic)}/*/*"


# --- QoS ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RmwQos:
    """An rmw QoS profile as the liveliness token carries it (rmw enum values, durations s/ns)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = DEFAULT_DEPTH
    deadline: tuple[int, int] = (INFINITE_S, INFINITE_NS)
    lifespan: tuple[int, int] = (INFINITE_S, INFINITE_NS)
    liveliness: int = AUTOMATIC
    lease: tuple[int, int] = (INFINITE_S, INFINITE_NS)

    @classmethod
    def from_qos(cls, qos: Qos) -> RmwQos:
        """The rmw profile of a topic table QoS (keep last ``depth``)."""
        return cls(reliability=int(qos.reliability), durability=int(qos.durability), depth=qos.depth)

    def to_qos(self) -> Qos:
        """The topic table QoS closest to this profile (history and durations dropped)."""
        return Qos(Reliability(self.reliability), Durability(self.durability), self.depth)


_DEFAULT_RMW_QOS = RmwQos()


def qos_to_string(qos: RmwQos | Qos) -> str:
    """The QoS part of a liveliness token (``qos_to_keyexpr`` in ``liveliness_utils.cpp``)."""
    if isinstance(qos, Qos):
        qos = RmwQos.from_qos(qos)
    d = _DEFAULT_RMW_QOS

    def part(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (f"{part(qos.reliability, d.reliability)}:{part(qos.durability, d.durability)}:"
            f"{part(qos.history, d.history)},{part(qos.depth, d.depth)}:"
            f"{part(qos.deadline[0], d.deadline[0])},{part(qos.deadline[1], d.deadline[1])}:"
            f"{part(qos.lifespan[0], d.lifespan[0])},{part(qos.lifespan[1], d.lifespan[1])}:"
            f"{part(qos.liveliness, d.liveliness)},{part(qos.lease[0], d.lease[0])},"
            f"{part(qos.lease[1], d.lease[1])}")


def qos_from_string(text: str) -> RmwQos:
    """Parse the QoS part of a liveliness token (``keyexpr_to_qos``); :class:`WireError` if malformed."""
    parts = text.split(":")
    if len(parts) != 6:
        raise WireError(f"QoS {text!r}: expected 6 ':'-separated fields")
    history, deadline, lifespan, live = (p.split(",") for p in parts[2:6])
    if len(history) != 2 or len(deadline) != 2 or len(lifespan) != 2 or len(live) != 3:
        raise WireError(f"QoS {text!r}: wrong number of ','-separated values")
    d = _DEFAULT_RMW_QOS

    def num(value: str, default: int, allowed: tuple[int, ...] | None = None) -> int:
        if value == "":
            return default
        if not value.isdigit():
            raise WireError(f"QoS {text!r}: {value!r} is not a number")
        n = int(value)
        if allowed is not None and n not in allowed:
            raise WireError(f"QoS {text!r}: {n} is not one of {allowed}")
        return n

    return RmwQos(
        reliability=num(parts[0], d.reliability, (0, RELIABLE, BEST_EFFORT, 3, 4)),
        durability=num(parts[1], d.durability, (0, TRANSIENT_LOCAL, VOLATILE, 3, 4)),
        history=num(history[0], d.history, (0, KEEP_LAST, KEEP_ALL, 3)),
        depth=num(history[1], d.depth),
        deadline=(num(deadline[0], d.deadline[0]), num(deadline[1], d.deadline[1])),
        lifespan=(num(lifespan[0], d.lifespan[0]), num(lifespan[1], d.lifespan[1])),
        liveliness=num(live[0], d.liveliness, (0, AUTOMATIC, 2, 3, 4, 5)),
        lease=(num(live[1], d.lease[0]), num(live[2], d.lease[1])),
    )


# --- liveliness tokens --------------------------------------------------------------------------


@dataclass(frozen=True)
class Entity:
    """One entity of the ROS graph, as its liveliness token names it."""

    domain_id: int
    zid: str                 #: the Zenoh session id, lowercase hex
    node_id: int
    entity_id: int
    kind: str                #: NN, MP, MS, SS or SC
    enclave: str             #: "" or "/..."
    namespace: str           #: "" or "/..."
    node_name: str
    topic: str = ""          #: the absolute topic (or service) name; "" for a node
    dds_type: str = ""
    type_hash: str = ""
    qos: RmwQos | None = None
    #: rmw_zenoh 0.10+'s optional 14th field of an endpoint token (buffer backends), kept as is
    backends: str = ""

    @property
    def node(self) -> str:
        """The node's fully qualified name (``/ns/name``)."""
        return f"{self.namespace}/{self.node_name}"

    @property
    def ros_type(self) -> str:
        """The ROS 2 type name of the topic ("" for a node)."""
        return ros_type(self.dds_type) if self.dds_type else ""

    def token(self) -> str:
        """This entity's liveliness token."""
        parts = [ADMIN_SPACE, str(self.domain_id), self.zid, str(self.node_id), str(self.entity_id),
                 self.kind, mangle(self.enclave), mangle(self.namespace), mangle(self.node_name)]
        if self.kind != NODE:
            if self.qos is None:
                raise WireError(f"{self.kind} entity without QoS")
            parts += [mangle(self.topic), mangle(self.dds_type), mangle(self.type_hash),
                      qos_to_string(self.qos)]
            if self.backends:
                parts.append(self.backends)
        return "/".join(parts)

    def gid(self) -> bytes:
        """The 16-byte GID rmw_zenoh derives from the liveliness token."""
        return gid_of(self.token())


def gid_of(token: str) -> bytes:
    """XXH3-128 of a liveliness token, low 64 bits then high 64 bits, little endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def parse_token(token: str) -> Entity:
    """The entity a liveliness token describes; :class:`WireError` if it is not rmw_zenoh's."""
    parts = token.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE:
        raise WireError(f"{token!r} is not an rmw_zenoh liveliness token")
    if any(p == "" for p in parts):
        raise WireError(f"{token!r} has an empty part")
    kind = parts[5]
    if kind not in ENTITY_KINDS:
        raise WireError(f"{token!r}: unknown entity kind {kind!r}")
    for i in (1, 3, 4):
        if not parts[i].isdigit():
            raise WireError(f"{token!r}: part {i} ({parts[i]!r}) is not a number")
    enclave = demangle(parts[6]).rstrip("/") if parts[6] != "%" else ""
    namespace = demangle(parts[7]).rstrip("/") if parts[7] != "%" else ""
    common = dict(domain_id=int(parts[1]), zid=parts[2], node_id=int(parts[3]),
                  entity_id=int(parts[4]), kind=kind, enclave=enclave, namespace=namespace,
                  node_name=demangle(parts[8]))
    if kind == NODE:
        if len(parts) != 9:
            raise WireError(f"{token!r}: a node token has 9 parts")
        return Entity(**common)
    if len(parts) not in (13, 14):
        raise WireError(f"{token!r}: an endpoint token has 13 parts (14 with rmw_zenoh 0.10+'s backends)")
    return Entity(**common, topic=demangle(parts[9]), dds_type=demangle(parts[10]),
                  type_hash=demangle(parts[11]), qos=qos_from_string(parts[12]),
                  backends=parts[13] if len(parts) == 14 else "")


@dataclass
class NodeNames:
    """One ROS node on rmw_zenoh, without I/O: the ids, tokens and keys of its entities.

    The daemon's bridge and the Python client are both such a node. ``zid`` is the Zenoh session's
    id (set once the session is open); ``distro`` the peers' distribution family
    (:data:`ROS_DISTROS`), which picks the type hash of keys and tokens. Endpoint ids count from 1
    in the order of :meth:`endpoint` calls (the node itself is entity 0), as rmw_zenoh numbers them.
    """

    domain_id: int
    namespace: str
    name: str
    distro: str = "jazzy"
    zid: str = ""
    _next_entity: int = field(default=1, repr=False)

    def type_hash(self, ros_type_name: str) -> str:
        """The type hash field of keys and tokens for the peers' distribution."""
        return wire_type_hash(ros_type_name, self.distro)

    def key(self, topic: str, ros_type_name: str) -> str:
        """The Zenoh key of the samples of ``topic`` (a full ROS name) of type ``ros_type_name``."""
        return topic_key(self.domain_id, topic, ros_type_name, self.type_hash(ros_type_name))

    def node(self) -> Entity:
        """The node itself (its token makes ``ros2 node list`` show it)."""
        return Entity(self.domain_id, self.zid, 0, 0, NODE, "", self.namespace, self.name)

    def endpoint(self, kind: str, topic: str, ros_type_name: str, qos: RmwQos | Qos) -> Entity:
        """A new publisher, subscription, service or client of the node (the next entity id)."""
        entity_id, self._next_entity = self._next_entity, self._next_entity + 1
        rmw_qos = RmwQos.from_qos(qos) if isinstance(qos, Qos) else qos
        return Entity(self.domain_id, self.zid, 0, entity_id, kind, "", self.namespace, self.name, topic,
                      dds_type(ros_type_name), self.type_hash(ros_type_name), rmw_qos)


def liveliness_pattern(domain_id: int) -> str:
    """The key expression every liveliness token of a domain matches."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


# --- attachment ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample."""

    sequence_number: int     #: per publisher, from 1
    source_timestamp_ns: int  #: wall clock, ns since the epoch
    gid: bytes               #: the publisher's 16-byte GID

    def encode(self) -> bytes:
        """The 33 bytes on the wire."""
        if len(self.gid) != GID_SIZE:
            raise WireError(f"a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        return _ATTACHMENT.pack(self.sequence_number, self.source_timestamp_ns, GID_SIZE, self.gid)

    @classmethod
    def decode(cls, data: bytes | bytearray | memoryview) -> Attachment:
        """Parse an attachment; :class:`WireError` unless it is exactly rmw_zenoh's 33 bytes."""
        if len(data) != ATTACHMENT_SIZE:
            raise WireError(f"attachment of {len(data)} bytes, expected {ATTACHMENT_SIZE}")
        seq, stamp, length, gid = _ATTACHMENT.unpack(bytes(data))
        if length != GID_SIZE:
            raise WireError(f"attachment GID length {length}, expected {GID_SIZE}")
        return cls(seq, stamp, gid)


def is_old_attachment(data: bytes | bytearray | memoryview) -> bool:
    """Whether an attachment is the string-keyed map of rmw_zenoh before 0.2.4 (Jazzy 0.2.0-0.2.3).

    Those releases attached a Zenoh bytes map with the keys ``sequence_number``, ``source_timestamp``
    and ``source_gid``; nothing here decodes it (update such a node), but it is told apart from noise.
    """
    raw = bytes(data)
    return b"sequence_number" in raw and b"source_gid" in raw


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment bytes for one sample (the publisher thread's fast path)."""
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_SIZE, gid)


class SampleStamps:
    """One publisher's attachments: its GID and the sequence numbers of its samples (from 1)."""

    __slots__ = ("gid", "sequence")

    def __init__(self, gid: bytes) -> None:
        self.gid = gid
        self.sequence = 0

    def next(self, source_timestamp_ns: int) -> bytes:
        """The attachment of the publisher's next sample, stamped ``source_timestamp_ns`` (wall ns)."""
        self.sequence += 1
        return _ATTACHMENT.pack(self.sequence, source_timestamp_ns, GID_SIZE, self.gid)
