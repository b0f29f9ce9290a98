"""ROS 2's node graph over DDS, without I/O: ``ros_discovery_info`` and the endpoints' USER_DATA.

DDS knows participants, readers and writers, not ROS nodes. ROS 2's DDS middlewares
(``rmw_dds_common``, used by rmw_fastrtps and rmw_cyclonedds alike) name the nodes on the topic
``ros_discovery_info`` (no ``rt/`` prefix), type ``rmw_dds_common/msg/ParticipantEntitiesInfo``,
reliable and transient local: each participant publishes its GID and, per node, the namespace,
the name, and the GIDs of the node's readers and writers. ``ros2 node list`` reads it; ``ros2 topic
info -v`` names an endpoint's node through it. Without it the car's writers show up under
``_CREATED_BY_BARE_DDS_APP_``.

A GID is the entity's 16-byte DDS GUID (prefix then entity id); Humble's ``Gid`` message is 24 bytes
(the GUID, then zeros), Iron and later 16. Since Iron, each endpoint's USER_DATA carries
``typehash=RIHS01_<hex>;`` (informational: without it ``ros2 topic info -v`` shows INVALID).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

DISCOVERY_TOPIC = "ros_discovery_info"
DISCOVERY_TYPE = "rmw_dds_common/msg/ParticipantEntitiesInfo"

_NODE_INFO = """string<=256 node_namespace
string<=256 node_name
rmw_dds_common/Gid[] reader_gid_seq
rmw_dds_common/Gid[] writer_gid_seq
"""
_PARTICIPANT_INFO = """rmw_dds_common/Gid gid
rmw_dds_common/NodeEntitiesInfo[] node_entities_info_seq
"""


@functools.cache
def graph_store(gid_size: int) -> Typestore:
    """A typestore with ``rmw_dds_common``'s graph messages for GIDs of ``gid_size`` bytes (16 or 24)."""
    if gid_size not in (16, 24):
        raise ValueError(f"a GID has 16 (Iron and later) or 24 (Humble) bytes, not {gid_size}")
    store = get_typestore(Stores.EMPTY)
    types = {}
    types.update(get_types_from_msg(f"char[{gid_size}] data\n", "rmw_dds_common/msg/Gid"))
    types.update(get_types_from_msg(_NODE_INFO, "rmw_dds_common/msg/NodeEntitiesInfo"))
    types.update(get_types_from_msg(_PARTICIPANT_INFO, DISCOVERY_TYPE))
    store.register(types)
    return store


@dataclass
class NodeInfo:
    """One ROS node of a participant: namespace (``/`` for none), name, its endpoints' GIDs."""

    namespace: str
    name: str
    readers: list[bytes] = field(default_factory=list)
    writers: list[bytes] = field(default_factory=list)


@dataclass
class ParticipantInfo:
    """A participant's ``ros_discovery_info`` sample."""

    gid: bytes
    nodes: list[NodeInfo] = field(default_factory=list)


def _pad(gid: bytes, size: int) -> bytes:
    if len(gid) > size:
        raise ValueError(f"a GID of {len(gid)} bytes does not fit {size}")
    return gid + bytes(size - len(gid))


def encode_participant_info(info: ParticipantInfo, gid_size: int = 16) -> bytes:
    """``info`` as the CDR of ``rmw_dds_common/msg/ParticipantEntitiesInfo`` (with the header)."""
    import numpy as np  # noqa: PLC0415

    store = graph_store(gid_size)
    gid_cls = store.types["rmw_dds_common/msg/Gid"]
    node_cls = store.types["rmw_dds_common/msg/NodeEntitiesInfo"]
    info_cls = store.types[DISCOVERY_TYPE]

    def gid(raw: bytes) -> object:
        return gid_cls(data=np.frombuffer(_pad(raw, gid_size), dtype=np.uint8))

    nodes = [node_cls(node_namespace=n.namespace, node_name=n.name,
                      reader_gid_seq=[gid(g) for g in n.readers], writer_gid_seq=[gid(g) for g in n.writers])
             for n in info.nodes]
    sample = info_cls(gid=gid(info.gid), node_entities_info_seq=nodes)
    return bytes(store.serialize_cdr(sample, DISCOVERY_TYPE))


def decode_participant_info(data: bytes, gid_size: int = 16) -> ParticipantInfo:
    """The CDR of a ``ParticipantEntitiesInfo`` (trailing GID zeros kept) as :class:`ParticipantInfo`."""
    obj = graph_store(gid_size).deserialize_cdr(data, DISCOVERY_TYPE)
    return ParticipantInfo(bytes(obj.gid.data), [
        NodeInfo(n.node_namespace, n.node_name, [bytes(g.data) for g in n.reader_gid_seq],
                 [bytes(g.data) for g in n.writer_gid_seq])
        for n in obj.node_entities_info_seq])


def user_data(type_hash: str | None) -> bytes:
    """An endpoint's USER_DATA as Iron+ write it: ``typehash=RIHS01_<hex>;`` (empty without a hash)."""
    return f"typehash={type_hash};".encode() if type_hash else b""


def topic_name(ros_name: str) -> str:
    """The DDS topic of a ROS 2 topic: ``/scan`` -> ``rt/scan``."""
    return "rt" + ros_name
