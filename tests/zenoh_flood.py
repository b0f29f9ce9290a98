"""A Zenoh client that floods one of the car's command topics, in a process of its own.

    python tests/zenoh_flood.py PORT [--topic /cmd_vel] [--rate HZ] [--seconds S] [--speed M/S] [--nice N]

Publishes ``geometry_msgs/Twist`` (``--speed`` forward) in rmw_zenoh's format (key, attachment with
a growing sequence number) at ``--rate`` messages per second, or as fast as one Python process can
(``--rate 0``, the default), for ``--seconds``. Prints ``flooding`` when the first message goes,
then one JSON line: ``{"sent": N, "seconds": S, "rate": N/S}``. Used by tests/test_net_cmd_vel_flood.py and
benchmarks/bench_flood.py.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import zenoh

from racecar_hw.base.messages import Twist, Vector3
from racecar_hw.net import rmw
from racecar_hw.net.zenoh_config import session_config
from racecar_hw.rosmsg.typestore import ros2_types


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("port", type=int)
    parser.add_argument("--topic", default="/cmd_vel")
    parser.add_argument("--rate", type=float, default=0.0)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--speed", type=float, default=0.5)
    parser.add_argument("--nice", type=int, default=0, help="run at this niceness (0: as started)")
    args = parser.parse_args()
    if args.nice:
        os.nice(args.nice)
    session = zenoh.open(session_config("client", [], [f"tcp/127.0.0.1:{args.port}"]))
    key = rmw.topic_key(0, args.topic, Twist.ROS_TYPE, rmw.type_hash(Twist.ROS_TYPE))
    pub = session.declare_publisher(key)
    payload = ros2_types().serialize(Twist(Vector3(x=args.speed), Vector3()))
    gid = bytes(range(16))
    time.sleep(0.3)  # the daemon's router learns of this session
    print("flooding", flush=True)
    sent = 0
    start = time.perf_counter()
    end = start + args.seconds
    interval = 1.0 / args.rate if args.rate > 0 else 0.0
    now = start
    while now < end:
        sent += 1
        pub.put(payload, attachment=rmw.encode_attachment(sent, time.time_ns(), gid))
        now = time.perf_counter()
        if interval:
            ahead = start + sent * interval - now
            if ahead > 0.001:
                time.sleep(ahead)
                now = time.perf_counter()
    elapsed = now - start
    print(json.dumps({"sent": sent, "seconds": round(elapsed, 3), "rate": round(sent / elapsed)}), flush=True)
    pub.undeclare()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
