"""QoS profiles as rosbag2 metadata (version 8) writes them: ``offered_qos_profiles``' YAML text.

The same text as ``rosbags.rosbag2.metadata.dump_qos_v8`` (a test compares them), written with
PyYAML so that the recorder does not import ``rosbags.rosbag2``: that package imports rosbags'
bag readers and writers with their storage plug-ins (SQLite, apsw, zstd, lz4), about 2 MB of a
daemon that never reads a bag and writes its own (see docs/install.md, "Memory").
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import yaml
from rosbags.interfaces import Qos


def _time(t: Any) -> dict[str, int]:
    return {"sec": t.sec, "nsec": t.nsec}


def dump_qos_v8(profiles: Iterable[Qos]) -> str:
    """``profiles`` as rosbag2 v8 metadata's ``offered_qos_profiles`` string ('' for none)."""
    dcts = [{
        "history": q.history.value,
        "depth": q.depth,
        "reliability": q.reliability.value,
        "durability": q.durability.value,
        "deadline": _time(q.deadline),
        "lifespan": _time(q.lifespan),
        "liveliness": q.liveliness.value,
        "liveliness_lease_duration": _time(q.liveliness_lease_duration),
        "avoid_ros_namespace_conventions": q.avoid_ros_namespace_conventions,
    } for q in profiles]
    if not dcts:
        return ""
    return yaml.safe_dump(dcts, default_flow_style=None, sort_keys=True).strip()


__all__ = ["dump_qos_v8"]
