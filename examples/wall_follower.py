"""Follow the right-hand wall around a loop, from /scan only, with racecar_hw.client.

Start the simulated car on the track map, then this, in another terminal (from the checkout, with
the README's ``.venv``)::

    .venv/bin/racecar-hw sim --scenario wall --scenario-set map=track \
        --scenario-set 'drivers=[]' --duration 120
    .venv/bin/python examples/wall_follower.py --laps 1

It drives counter-clockwise (the outer wall on the right), the classic F1TENTH wall follower: two
beams on the right give the wall's distance and angle, projected ``lookahead_m`` ahead; a PD
controller steers to keep ``distance_m`` from it; the speed drops with the free distance straight
ahead and with the steering. Only /scan steers; /odom counts the laps: one lap is a full turn of
heading and the car three metres past its start line (x = 3 m in the odom frame, which starts where
the car did): odometry from the wheels and the servo drifts by a few percent of the distance (2.4 m
after one 56 m lap of the simulated track was seen), and the margin keeps that drift from ending a
lap short of the start.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np

from racecar_hw.client import Car, ClientError, Scan

STEERING_MAX_RAD = 0.26
#: How far past its start line (odom x, m) the car must be for a lap to count (see above).
PAST_START_M = 3.0


def range_at(scan: Scan, angle: float, width: float = 0.04) -> float:
    """The median valid range within ``width`` rad of ``angle`` (laser frame), inf if none."""
    near = np.abs(scan.angles - angle) <= width
    values = scan.ranges[near]
    values = values[np.isfinite(values) & (values > scan.range_min)]
    return float(np.median(values)) if values.size else math.inf


class WallFollower:
    """Right-wall PD controller: :meth:`command` maps a scan to (speed m/s, steering rad)."""

    def __init__(self, distance_m: float = 0.8, lookahead_m: float = 0.6, kp: float = 1.2,
                 kd: float = 0.12, max_speed: float = 2.0, min_speed: float = 0.6) -> None:
        self.distance_m = distance_m
        self.lookahead_m = lookahead_m
        self.kp, self.kd = kp, kd
        self.max_speed, self.min_speed = max_speed, min_speed
        self._last_error: float | None = None
        self._last_t = 0.0

    def command(self, scan: Scan) -> tuple[float, float]:
        theta = math.radians(50.0)
        b = range_at(scan, -math.pi / 2)            # straight to the right
        a = range_at(scan, -math.pi / 2 + theta)    # 50 deg further forward
        front = range_at(scan, 0.0, 0.15)
        if not math.isfinite(b):
            b = 3.0
        if not math.isfinite(a):
            a = b / math.cos(theta)
        alpha = math.atan2(a * math.cos(theta) - b, a * math.sin(theta))  # > 0: heading away
        distance = b * math.cos(alpha) + self.lookahead_m * math.sin(alpha)
        error = self.distance_m - distance                                 # > 0: too close
        t = scan.stamp_s
        derivative = 0.0
        if self._last_error is not None and t > self._last_t:
            derivative = (error - self._last_error) / (t - self._last_t)
        self._last_error, self._last_t = error, t
        steering = self.kp * error + self.kd * derivative
        if front < 2.5:  # a wall ahead: the corridor turns left
            steering += 0.6 * (2.5 - front)
        steering = max(-STEERING_MAX_RAD, min(STEERING_MAX_RAD, steering))
        speed = min(self.max_speed, max(self.min_speed, 0.7 * (front - 0.8)))
        speed *= 1.0 - 0.5 * abs(steering) / STEERING_MAX_RAD
        return max(self.min_speed * 0.5, speed), steering


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the daemon's Zenoh endpoint")
    parser.add_argument("--namespace", default="", help="the car's ROS namespace")
    parser.add_argument("--laps", type=float, default=1.0, help="stop after this many laps (0: never)")
    parser.add_argument("--speed", type=float, default=2.0, help="top speed, m/s")
    parser.add_argument("--timeout", type=float, default=0.0, help="give up after this many s (0: never)")
    args = parser.parse_args(argv)
    follower = WallFollower(max_speed=args.speed)
    turned = 0.0
    last_yaw: float | None = None
    started = time.monotonic()
    try:
        with Car(args.connect, namespace=args.namespace) as car:
            for scan in car.scans(timeout=5.0):
                speed, steering = follower.command(scan)
                car.drive(speed, steering)
                odom = car.odom
                if odom is None:
                    continue
                if last_yaw is not None:
                    turned += math.remainder(odom.yaw - last_yaw, 2 * math.pi)
                last_yaw = odom.yaw
                if args.laps and turned >= 2 * math.pi * args.laps - 0.3 and odom.x > PAST_START_M:
                    print(f"{args.laps:g} lap(s) in {time.monotonic() - started:.1f} s", flush=True)
                    return 0
                if args.timeout and time.monotonic() - started > args.timeout:
                    print(f"gave up after {args.timeout:g} s; turned {turned:.2f} rad", flush=True)
                    return 1
    except ClientError as err:
        print(f"wall_follower: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
