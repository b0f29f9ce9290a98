"""Serializer benchmarks: what the generated serializers and readers earn against rosbags, and what
writing MCAP with the ``mcap`` library costs per message against rosbags' own rosbag2 writer.

Per message class of the daemon's streams: microseconds per message, best and median of 7 runs,
for the generated CDR serializer (:mod:`racecar_hw.rosmsg.serde`) against rosbags' path (our
dataclass to a rosbags object, ``Typestore.serialize_cdr``), and the generated reader against
``Typestore.deserialize_cdr`` plus the conversion back. Then microseconds per message to append
already serialized bytes to an MCAP file: :class:`racecar_hw.bags.writers.McapStorage` (``mcap``'s
``Writer``, chunk CRCs on) against ``rosbags.rosbag2.Writer.write``.

Run: ``python benchmarks/bench_serde.py``. ``run()`` returns the rows for benchmarks/run_all.py.
"""

from __future__ import annotations

import functools
import statistics
import tempfile
import timeit
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from table import print_rows

from racecar_hw.bags.writers import McapStorage
from racecar_hw.base.messages import (
    AckermannDrive,
    AckermannDriveStamped,
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    KeyValue,
    LaserScan,
    Message,
    Odometry,
    TFMessage,
    Time,
    TransformStamped,
    Twist,
    VescStateStamped,
)
from racecar_hw.rosmsg.typestore import ros2_types

RUNS = 7


def samples() -> list[Message]:
    r = np.linspace(0.5, 10.0, 1081, dtype=np.float32)
    return [
        LaserScan(Header(Time(1, 0), "laser"), -2.35, 2.35, 0.00436, 0.0, 0.025, 0.02, 30.0, r, r),
        Odometry(Header(Time(1, 0), "odom"), "base_link"),
        AckermannDriveStamped(Header(Time(1, 0), "base_link"), AckermannDrive(0.1, 0.0, 1.0)),
        Twist(),
        TFMessage([TransformStamped(Header(Time(1, 0), "odom"), "base_link")]),
        VescStateStamped(),
        DiagnosticArray(Header(Time(1, 0)), [DiagnosticStatus(name="mux", values=[KeyValue("k", "v")] * 4)]),
    ]


def per_call_us(fn: Callable[[], object], number: int) -> tuple[float, float]:
    """Best and median of :data:`RUNS` runs of ``number`` calls, microseconds per call."""
    times = [t / number * 1e6 for t in timeit.repeat(fn, number=number, repeat=RUNS)]
    return min(times), statistics.median(times)


def serializer_rows() -> list[dict]:
    types = ros2_types()
    rows = []
    for msg in samples():
        cls = type(msg)
        raw = types.serialize(msg)
        assert raw == types.serialize_generic(msg)
        name = cls.__name__
        for what, fn in (("generated serializer", lambda m=msg: types.serialize(m)),
                         ("rosbags serializer", lambda m=msg: types.serialize_generic(m)),
                         ("generated reader", lambda r=raw, c=cls: types.deserialize(r, c)),
                         ("rosbags reader", lambda r=raw, c=cls: types.deserialize_generic(r, c))):
            best, median = per_call_us(fn, 2000 if "generated" in what else 300)
            rows.append({"name": f"{name}: {what}, best / median", "value": f"{best:.1f} / {median:.1f}",
                         "unit": "µs", "target": None})
    return rows


def append_ours(msg: Message, raw: bytes, n: int) -> None:
    """``n`` appends of ``raw`` to a new MCAP file with :class:`McapStorage`, closed."""
    types = ros2_types()
    with tempfile.TemporaryDirectory() as tmp:
        storage = McapStorage(Path(tmp) / "b.mcap")
        cid = storage.add_connection("/x", msg.ROS_TYPE, types.msgdef(msg.ROS_TYPE),
                                     types.digest(msg.ROS_TYPE), "")
        for i in range(n):
            storage.write(cid, i, raw)
        storage.close("")


def append_rosbags(msg: Message, raw: bytes, n: int) -> None:
    """The same with rosbags' rosbag2 writer (its public API)."""
    types = ros2_types()
    with tempfile.TemporaryDirectory() as tmp:
        writer = Writer2(Path(tmp) / "b", version=8, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        conn = writer.add_connection("/x", msg.ROS_TYPE, typestore=types.store)
        for i in range(n):
            writer.write(conn, i, raw)
        writer.close()


def mcap_rows(count: int = 20000) -> list[dict]:
    types = ros2_types()
    rows = []
    for msg in (samples()[2], samples()[0]):
        raw = types.serialize(msg)
        n = count if len(raw) < 1000 else count // 10
        name = type(msg).__name__
        for what, fn in (("mcap library (McapStorage, CRCs)", append_ours),
                         ("rosbags rosbag2.Writer.write", append_rosbags)):
            call = functools.partial(fn, msg, raw, n)
            times = [t / n * 1e6 for t in timeit.repeat(call, number=1, repeat=5)]
            rows.append({"name": f"MCAP append {name} ({len(raw)} B), {what}, best / median",
                         "value": f"{min(times):.2f} / {statistics.median(times):.2f}", "unit": "µs/msg",
                         "target": None})
    return rows


def run() -> list[dict]:
    return serializer_rows() + mcap_rows()


if __name__ == "__main__":
    print_rows(run())
