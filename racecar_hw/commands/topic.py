"""``racecar-hw topic list | echo | hz | pub``: ROS 2 topics over Zenoh, like ``ros2 topic``, no ROS needed.

They speak rmw_zenoh's format (:mod:`racecar_hw.net.rmw`), so they see the car and any ROS 2 node on
rmw_zenoh alike. ``list`` reads the ROS graph (liveliness tokens); ``echo`` and ``hz`` take the
topic's type from the graph; ``pub`` takes a type racecar-hw knows (``std_msgs/msg/Bool``,
``ackermann_msgs/msg/AckermannDriveStamped``, ``geometry_msgs/msg/Twist``, ...) and a YAML mapping.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import threading
import time
import typing
from collections.abc import Iterator
from typing import Any

import numpy as np
import yaml

from racecar_hw.base import messages
from racecar_hw.base.errors import ConfigError, RacecarError
from racecar_hw.base.messages import Message
from racecar_hw.net import rmw
from racecar_hw.net.zenoh_config import DEFAULT_ENDPOINT, ZenohAuthParams, check_connect, session_config
from racecar_hw.net.zenoh_security import check_credentials, zenoh_error_text
from racecar_hw.rosmsg.typestore import MESSAGE_CLASSES, ros2_types

NODE = "racecar_hw_topic"


class TopicError(RacecarError):
    """A topic command could not do what was asked."""


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``topic`` with its four subcommands."""
    p = sub.add_parser("topic", help="list, echo, measure or publish ROS 2 topics over Zenoh",
                       description="Inspect and publish ROS 2 topics in rmw_zenoh's format, from this "
                                   "machine or a laptop, without ROS.")
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
                   help=f"Zenoh endpoint of the daemon or a router (default {DEFAULT_ENDPOINT})")
    p.add_argument("--mode", default="client", choices=("client", "peer"), help="Zenoh mode (default client)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS domain id (default ROS_DOMAIN_ID or 0)")
    p.add_argument("--user", default="", help="user name, when the daemon requires one")
    p.add_argument("--password", default="", help="its password")
    cmds = p.add_subparsers(dest="topic_command", metavar="SUBCOMMAND", required=True)
    ls = cmds.add_parser("list", help="topics in the ROS graph, with their types")
    ls.add_argument("-v", "--verbose", action="store_true", help="also the publishing and subscribing nodes")
    echo = cmds.add_parser("echo", help="print the messages on a topic")
    echo.add_argument("topic")
    echo.add_argument("-n", "--count", type=int, default=0, help="stop after this many (default: never)")
    echo.add_argument("--full", action="store_true", help="print whole arrays (default: the first 8)")
    hz = cmds.add_parser("hz", help="print the rate of a topic every second")
    hz.add_argument("topic")
    hz.add_argument("--duration", type=float, default=0.0, metavar="S", help="stop after S seconds")
    pub = cmds.add_parser("pub", help="publish a message, once or at a rate")
    pub.add_argument("topic")
    pub.add_argument("type", help="the ROS 2 type, e.g. std_msgs/msg/Bool")
    pub.add_argument("values", nargs="?", default="{}", help="the message as YAML, e.g. '{data: true}'")
    pub.add_argument("--rate", type=float, default=0.0, metavar="HZ", help="repeat at this rate")
    pub.add_argument("--times", type=int, default=1, help="how many to send (0: until Ctrl-C; default 1)")
    pub.add_argument("--ros-distro", default="jazzy", choices=rmw.ROS_DISTROS,
                     help="the subscribers' rmw_zenoh: jazzy (Jazzy and later, RIHS01 hashes; default) "
                          "or humble (TypeHashNotSupported); echo and hz read it from the graph")
    p.set_defaults(func=cmd_topic)


def cmd_topic(args: argparse.Namespace) -> int:
    import zenoh  # noqa: PLC0415

    from racecar_hw.net.zenoh_config import ZenohParams  # noqa: PLC0415

    domain = args.domain_id if args.domain_id is not None else ZenohParams().resolved_domain_id()
    try:
        check_credentials(args.user, args.password, "--user", "--password")
    except ConfigError as err:
        raise TopicError(str(err)) from None
    auth = ZenohAuthParams(user=args.user, password=args.password)
    try:
        check_connect(args.connect, "--connect")
    except ConfigError as err:
        raise TopicError(str(err)) from None
    try:
        session = zenoh.open(session_config(args.mode, [], [args.connect], auth=auth))
    except zenoh.ZError as err:
        hint = "is the daemon running, and are --user and --password right?" if args.user else (
            "is the daemon running, and does it want --user and --password?")
        raise TopicError(f"cannot connect to {args.connect}: {hint} "
                         f"(Zenoh: {zenoh_error_text(err)})") from None
    try:
        handler = {"list": _list, "echo": _echo, "hz": _hz, "pub": _pub}[args.topic_command]
        return handler(session, domain, args)
    except KeyboardInterrupt:
        return 0
    finally:
        session.close()


def graph(session: Any, domain: int, timeout: float = 2.0) -> list[rmw.Entity]:
    """Every entity of the ROS graph in ``domain`` (rmw_zenoh liveliness tokens)."""
    out = []
    for reply in session.liveliness().get(rmw.liveliness_pattern(domain), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            out.append(rmw.parse_token(str(reply.ok.key_expr)))
        except rmw.WireError:
            continue
    return out


def _list(session: Any, domain: int, args: argparse.Namespace) -> int:
    topics: dict[tuple[str, str], dict[str, set[str]]] = {}
    for e in graph(session, domain):
        if e.kind in (rmw.PUBLISHER, rmw.SUBSCRIPTION):
            entry = topics.setdefault((e.topic, e.ros_type), {"pub": set(), "sub": set()})
            entry["pub" if e.kind == rmw.PUBLISHER else "sub"].add(e.node)
    if not topics:
        print(f"no topics in domain {domain} (is the daemon up and reachable at {args.connect}?)",
              file=sys.stderr)
        return 1
    width = max(len(t) for t, _ in topics)
    for (topic, ros_type), who in sorted(topics.items()):
        line = f"{topic:{width}}  [{ros_type}]"
        if args.verbose:
            line += (f"  publishers: {', '.join(sorted(who['pub'])) or '-'}; "
                     f"subscribers: {', '.join(sorted(who['sub'])) or '-'}")
        print(line)
    return 0


def _topic_type(session: Any, domain: int, topic: str) -> tuple[str, str, bool]:
    """(ROS type, type hash, latched) of ``topic`` from its publishers (else subscribers) in the graph."""
    rmw.check_topic_name(topic)
    found = [e for e in graph(session, domain) if e.topic == topic and e.kind in (rmw.PUBLISHER,
                                                                                 rmw.SUBSCRIPTION)]
    found.sort(key=lambda e: e.kind != rmw.PUBLISHER)
    if not found:
        raise TopicError(f"{topic} is not in the ROS graph of domain {domain}; see racecar-hw topic list")
    e = found[0]
    latched = e.kind == rmw.PUBLISHER and e.qos is not None and e.qos.durability == rmw.TRANSIENT_LOCAL
    return e.ros_type, e.type_hash, latched


def _samples(session: Any, key: str, latched: bool) -> Iterator[Any]:
    """The samples on ``key``; with ``latched``, a publisher's cached ones first (TRANSIENT_LOCAL)."""
    import zenoh  # noqa: PLC0415
    import zenoh.ext  # noqa: PLC0415

    if latched:
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=10)
        sub = zenoh.ext.declare_advanced_subscriber(session, key, zenoh.handlers.FifoChannel(256),
                                                    history=history)
    else:
        sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(256))
    try:
        while True:
            sample = sub.try_recv()
            if sample is None:
                time.sleep(0.005)
                continue
            yield sample
    finally:
        sub.undeclare()


def _echo(session: Any, domain: int, args: argparse.Namespace) -> int:
    ros_type, type_hash, latched = _topic_type(session, domain, args.topic)
    store = ros2_types().store
    if ros_type not in store.fielddefs:
        raise TopicError(f"{ros_type} is not a type racecar-hw knows; it cannot print {args.topic}")
    n = 0
    for sample in _samples(session, rmw.topic_key(domain, args.topic, ros_type, type_hash), latched):
        try:
            obj = store.deserialize_cdr(sample.payload.to_bytes(), ros_type)
        except Exception as err:  # noqa: BLE001 - a malformed sample is reported, not fatal
            print(f"# a malformed {ros_type} sample: {err}", file=sys.stderr)
            continue
        print(yaml.safe_dump(_plain(obj, args.full), sort_keys=False, default_flow_style=None).rstrip())
        print("---", flush=True)
        n += 1
        if args.count and n >= args.count:
            return 0
    return 0


def _plain(obj: Any, full: bool) -> Any:
    """A rosbags message as plain data for YAML; arrays cut to 8 values unless ``full``."""
    if isinstance(obj, np.ndarray):
        values = obj.tolist()
        return values if full or len(values) <= 8 else [*values[:8], f"... {len(values)} values"]
    if isinstance(obj, (list, tuple)):
        return [_plain(v, full) for v in obj]
    if dataclasses.is_dataclass(obj):
        return {f.name: _plain(getattr(obj, f.name), full) for f in dataclasses.fields(obj)
                if not f.name.startswith("_")}
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _hz(session: Any, domain: int, args: argparse.Namespace) -> int:
    ros_type, type_hash, _ = _topic_type(session, domain, args.topic)
    stamps: list[float] = []
    lock = threading.Lock()

    def on_sample(_sample: Any) -> None:
        with lock:
            stamps.append(time.monotonic())

    sub = session.declare_subscriber(rmw.topic_key(domain, args.topic, ros_type, type_hash), on_sample)
    started = time.monotonic()
    try:
        while not args.duration or time.monotonic() - started < args.duration:
            time.sleep(1.0)
            with lock:
                window = stamps[-1000:]
            if len(window) < 2:
                print(f"{args.topic}: no messages yet", flush=True)
                continue
            gaps = np.diff(window)
            rate = (len(window) - 1) / (window[-1] - window[0])
            print(f"{args.topic}: average rate {rate:.2f} Hz; min {gaps.min():.4f} s, "
                  f"max {gaps.max():.4f} s, std dev {statistics.pstdev(gaps.tolist()):.5f} s, "
                  f"window {len(window)}", flush=True)
    finally:
        sub.undeclare()
    return 0


def _pub(session: Any, domain: int, args: argparse.Namespace) -> int:
    rmw.check_topic_name(args.topic)
    cls = MESSAGE_CLASSES.get(args.type)
    if cls is None:
        raise TopicError(f"racecar-hw cannot publish {args.type}; it can publish: "
                         + ", ".join(sorted(MESSAGE_CLASSES)))
    try:
        values = yaml.safe_load(args.values) or {}
        msg = from_plain(cls, values)
        # the serializer checks what from_plain cannot: array lengths, integer ranges (struct)
        payload = ros2_types().serialize(msg)
    except Exception as err:  # noqa: BLE001 - whatever the values make the parser or serializer raise
        raise TopicError(f"{args.values!r} is not a {args.type}: {' '.join(str(err).split())}") from None
    _check_pub_type(session, domain, args.topic, args.type)
    type_hash = rmw.wire_type_hash(args.type, args.ros_distro)
    zid = str(session.zid())
    liveliness = session.liveliness()
    node = rmw.Entity(domain, zid, 0, 0, rmw.NODE, "", "", NODE)
    entity = rmw.Entity(domain, zid, 0, 1, rmw.PUBLISHER, "", "", NODE, args.topic, rmw.dds_type(args.type),
                        type_hash, rmw.RmwQos(depth=10))
    tokens = [liveliness.declare_token(node.token()), liveliness.declare_token(entity.token())]
    key = rmw.topic_key(domain, args.topic, args.type, type_hash)
    publisher = session.declare_publisher(key)
    time.sleep(0.3)  # let subscribers' sessions learn of this publisher before the first put
    period = 1.0 / args.rate if args.rate > 0 else 0.1
    sent = 0
    gid = entity.gid()
    try:
        while not args.times or sent < args.times:
            sent += 1
            publisher.put(payload, attachment=rmw.encode_attachment(sent, time.time_ns(), gid))
            print(f"publishing #{sent}: {args.type} on {args.topic}", flush=True)
            if not args.times or sent < args.times:
                time.sleep(period)
    finally:
        time.sleep(0.1)
        publisher.undeclare()
        for token in tokens:
            token.undeclare()
    return 0


def _check_pub_type(session: Any, domain: int, topic: str, ros_type: str) -> None:
    """Refuse to publish ``ros_type`` on a topic the graph knows with other types only.

    rmw_zenoh puts each type on its own key, so a subscriber of another type (the daemon's mux
    inputs) would never see the message: publishing it would only look like success. A topic not in
    the graph yet is published to as ``ros2 topic pub`` does.
    """
    found = [e for e in graph(session, domain) if e.topic == topic
             and e.kind in (rmw.PUBLISHER, rmw.SUBSCRIPTION)]
    types = sorted({e.ros_type for e in found})
    if found and ros_type not in types:
        takers = sorted({e.node for e in found if e.kind == rmw.SUBSCRIPTION})
        who = f" (subscribed by {', '.join(takers)})" if takers else ""
        raise TopicError(f"{topic} takes {' or '.join(types)}{who}, not {ros_type}; a message of "
                         f"another type would never arrive")


def from_plain(cls: type[Message], data: Any) -> Message:
    """A racecar-hw message built from plain data (a YAML mapping); missing fields keep defaults."""
    if not isinstance(data, dict):
        raise TypeError(f"{cls.ROS_TYPE} needs a mapping of fields, got {data!r}")
    hints = typing.get_type_hints(cls, vars(messages))
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown:
        raise TypeError(f"{cls.ROS_TYPE} has no field {unknown[0]!r}; fields: {', '.join(sorted(names))}")
    values = {}
    for name, value in data.items():
        hint = hints[name]
        if isinstance(hint, type) and issubclass(hint, Message):
            values[name] = from_plain(hint, value)
        elif hint is np.ndarray:
            values[name] = np.asarray(value, dtype=getattr(cls(), name).dtype)
        elif typing.get_origin(hint) is list:
            (inner,) = typing.get_args(hint)
            values[name] = [from_plain(inner, v) for v in value]
        elif hint is float:
            values[name] = float(value)
        elif hint is int:
            values[name] = int(value)
        elif hint is bool:
            if not isinstance(value, bool):
                raise TypeError(f"{name}: expected true or false, got {value!r}")
            values[name] = value
        else:
            values[name] = str(value)
    return cls(**values)
