"""``racecar-hw fake-lidar`` (a fake Hokuyo or RPLIDAR) and ``racecar-hw lidar-info`` (ask a lidar)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import threading
import time

from lidar_drivers.base import LidarDriver, RandomRangeSource, RangeSource, RoomRangeSource, summarize
from lidar_drivers.params import ETHERNET_MODELS, HOKUYO_MODELS, HOKUYO_USB_MODELS, MODELS, LidarParams
from lidar_drivers.registry import family, make_driver, make_fake, model_for_reported, model_name
from racecar_hw.base.bus import Bus
from racecar_hw.base.errors import DeviceError
from racecar_hw.base.link import parse_host_port
from racecar_hw.base.messages import LaserScan
from racecar_hw.runtime.devicethread import DeviceThread
from racecar_hw.runtime.signals import interrupt_on_stop_signals


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``fake-lidar`` and ``lidar-info`` commands."""
    fake = subparsers.add_parser(
        "fake-lidar", help="run a fake lidar (Hokuyo on a pty or TCP, RPLIDAR on a pty)",
        description="Serve a fake lidar speaking the model's real protocol until Ctrl-C: "
                    "a Hokuyo (SCIP 2.0) on a pty at --link and/or (Ethernet models) a TCP port "
                    "at --tcp, or an RPLIDAR on a pty at --link. It measures a rectangular room "
                    "or random ranges.")
    fake.add_argument("--model", required=True, choices=MODELS, type=str.lower, help="lidar model")
    fake.add_argument("--link", metavar="PATH", help="symlink to the pty to create, e.g. /tmp/lidar")
    fake.add_argument("--tcp", metavar="HOST:PORT", type=_host_port,
                      help="listen for SCIP clients here (Ethernet Hokuyo models only: "
                           f"{', '.join(m for m in HOKUYO_MODELS if m not in HOKUYO_USB_MODELS)}; "
                           "port 0 = any free port)")
    fake.add_argument("--firmware", type=_firmware, metavar="X.Y",
                      help="RPLIDAR: the firmware version to report (default: the model's own); "
                           "an A-series unit below 1.24 has no GET_LIDAR_CONF scan modes")
    world = fake.add_mutually_exclusive_group()
    world.add_argument("--room", default=(8.0, 6.0), type=_room, metavar="WxD",
                       help="the laser in the middle of a W x D metre room (default 8x6)")
    world.add_argument("--random", action="store_true",
                       help="uniform random ranges in [1, 10) m instead of a room")
    fake.set_defaults(func=fake_lidar)

    info = subparsers.add_parser(
        "lidar-info", help="print a lidar's model, firmware, geometry and one scan's summary",
        description="Connect to the lidar, read its identity and scan geometry, wait for one "
                    "scan and print the closest and farthest valid return with their angles.")
    where = info.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", metavar="PATH", help="serial path or pyserial URL")
    where.add_argument("--tcp", metavar="HOST:PORT", help="Ethernet Hokuyo address")
    info.add_argument("--model", choices=MODELS, type=str.lower,
                      help="lidar model (default: the one the device reports; with --port a Hokuyo "
                           "is tried first, then an RPLIDAR: a port that is there but does not "
                           "answer one protocol is tried with the next at once)")
    info.add_argument("--baudrate", type=int, default=None, help="serial baud (default: the model's)")
    info.add_argument("--timeout", type=float, default=5.0, metavar="S",
                      help="seconds to wait for the first scan (default 5)")
    info.set_defaults(func=lidar_info)


def _room(text: str) -> tuple[float, float]:
    w, sep, d = text.lower().partition("x")
    try:
        width, depth = float(w), float(d)
    except ValueError:
        width = depth = math.nan
    if not sep or not (width > 0 and depth > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a room size like 8x6 (metres)")
    return width, depth


def _firmware(text: str) -> tuple[int, int]:
    major, sep, minor = text.partition(".")
    if not sep or not major.isdigit() or not minor.isdigit() or int(major) > 255 or int(minor) > 255:
        raise argparse.ArgumentTypeError(f"{text!r} is not a firmware version like 1.20")
    return int(major), int(minor)


def _host_port(text: str) -> tuple[str, int]:
    try:
        return parse_host_port(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def fake_lidar(args: argparse.Namespace) -> int:
    """Serve a fake lidar until SIGINT (Ctrl-C) or SIGTERM; exits 0."""
    if args.link is None and args.tcp is None:
        print("racecar-hw fake-lidar: give --link PATH and/or --tcp HOST:PORT")
        return 2
    source: RangeSource = RandomRangeSource() if args.random else RoomRangeSource(*args.room)
    if args.firmware is not None and family(args.model) != "rplidar":
        print("racecar-hw fake-lidar: --firmware is for RPLIDAR models")
        return 2
    if args.tcp is not None and args.model in HOKUYO_USB_MODELS:
        print(f"racecar-hw fake-lidar: the {args.model} is a USB lidar with no Ethernet port; "
              "serve it on a pty with --link PATH")
        return 2
    fake = make_fake(args.model, source, link=args.link, tcp=args.tcp, firmware=args.firmware)
    with DeviceThread("fake-lidar") as thread:
        served = thread.spawn(fake.serve())
        ready: threading.Event | None = getattr(fake, "ready", None)
        if ready is not None and not ready.wait(10):
            if served.done():
                served.result()
            print("racecar-hw fake-lidar: the fake lidar did not start")
            return 1
        places = []
        if args.link:
            places.append(f"pty {args.link}")
        address = getattr(fake, "tcp_address", None)
        if address is not None:
            places.append(f"tcp {address[0]}:{address[1]}")
        world = "random ranges" if args.random else f"a {args.room[0]:g} x {args.room[1]:g} m room"
        print(f"fake {args.model} at {', '.join(places)} measuring {world}; Ctrl-C to stop",
              flush=True)
        try:
            with interrupt_on_stop_signals():
                while not served.done():
                    time.sleep(0.2)
        except KeyboardInterrupt:
            return 0
        served.result()
    return 0


#: Models tried, in order, when ``lidar-info`` is not given ``--model``: each stands for its
#: protocol (SCIP 2.0 over Ethernet; SCIP on a serial port, then the RPLIDAR protocol); the model
#: the device then reports is used.
PROBE_MODELS = {"tcp": ("ust-10lx",), "port": ("urg-04lx", "a1")}


def lidar_info(args: argparse.Namespace) -> int:
    """Print the lidar's identity, geometry and one scan's closest/farthest return."""
    if args.model and args.tcp and args.model not in ETHERNET_MODELS:
        kind = "a USB lidar" if args.model in HOKUYO_MODELS else "a serial lidar"
        print(f"racecar-hw lidar-info: the {args.model} is {kind} with no Ethernet port; use --port")
        return 2
    detected = args.model is None
    driver, scan = None, None
    # detecting on a serial port that is there: a protocol the device does not answer (one session
    # of its driver ended without the device naming itself) hands over to the next at once, not
    # after --timeout; a port that is not there yet is waited for (the device may be plugged in)
    hand_over = detected and args.port is not None and os.path.exists(args.port)
    answered = False  # whether any byte came back, as any model
    for model in [args.model] if args.model else PROBE_MODELS["tcp" if args.tcp else "port"]:
        driver, scan = _probe(args, model, hand_over=hand_over)
        answered = answered or driver.stats.bytes_in > 0
        reported = driver.info.get("model")
        key = model_for_reported(reported) if reported else None
        if detected and key is not None and key != model:
            driver, scan = _probe(args, key)  # the model the device names: its own geometry
            model = key
        if not detected or scan is not None or reported:
            break
    assert driver is not None
    if detected:
        if not driver.info.get("model") and not answered:  # no model would have fared better
            print(f"racecar-hw lidar-info: {_silence(args, driver.last_error)}")
            return 1
        if not driver.info.get("model"):
            tried = " or ".join(PROBE_MODELS["tcp" if args.tcp else "port"])
            why = f" ({driver.last_error})" if driver.last_error else ""
            print(f"racecar-hw lidar-info: something answered but no lidar named itself within "
                  f"{args.timeout:g} s, tried as {tried}{why}; give --model")
            return 1
        args.model = model
    reported = driver.info.get("model")
    mismatch = None if detected else _model_mismatch(args.model, reported)
    if scan is None:
        print(f"racecar-hw lidar-info: no scan within {args.timeout:g} s"
              + (f" ({driver.last_error})" if driver.last_error else ""))
        if mismatch:
            print(f"racecar-hw lidar-info: {mismatch}")
        return 1
    print(f"model:      {args.model}" + (f" (device reports {reported})" if reported else "")
          + (", detected" if detected else ""))
    if mismatch:
        print(f"warning:    {mismatch}")
    for key, value in driver.info.items():
        if key != "model":
            print(f"{key + ':':<11} {value}")
    geo = driver.geometry
    if geo is not None:
        print(f"geometry:   {geo.beams} beams, {math.degrees(geo.angle_min):.2f}..."
              f"{math.degrees(geo.angle_max):.2f} deg every {math.degrees(geo.angle_increment):.3f}"
              f" deg, {geo.range_min:g}..{geo.range_max:g} m, scan {geo.scan_time * 1000:.1f} ms")
    s = summarize(scan)
    print(f"scan:       {len(scan.ranges)} beams, {s.valid_beams} valid")
    if s.valid_beams:
        print(f"closest:    {s.closest:.3f} m at {math.degrees(s.closest_angle):.2f} deg")
        print(f"farthest:   {s.farthest:.3f} m at {math.degrees(s.farthest_angle):.2f} deg")
    return 0


def _silence(args: argparse.Namespace, error: str | None) -> str:
    """What to tell the user when nothing answered at ``--tcp`` or ``--port`` (``error``: why)."""
    where = f"{args.tcp}" if args.tcp else f"{args.port}"
    what = error or f"nothing answered at {where} within {args.timeout:g} s"
    key = "the address (lidar.tcp)" if args.tcp else "the port (lidar.port)"
    return f"{what}; check {key}, the cable and the lidar's power"


def _model_mismatch(model: str, reported: str | None) -> str | None:
    """What to tell the user when the device names itself differently from ``--model``."""
    if not reported or reported.strip().lower() == model_name(model).lower():
        return None
    key = model_for_reported(reported)
    advice = f"use --model {key} (lidar.model: {key})" if key else "check lidar.model"
    return f"the device reports {reported}, not {model_name(model)} ({model}); {advice}"


def _probe(args: argparse.Namespace, model: str, *, hand_over: bool = False,
           ) -> tuple[LidarDriver, LaserScan | None]:
    """The driver for ``model`` at the given port or address after its first scan (None: none came).
    ``hand_over``: give up as soon as a session ended without the device naming itself (it does not
    speak this model's protocol), rather than at ``--timeout``."""
    params = LidarParams(model=model, port=args.port, tcp=args.tcp, baudrate=args.baudrate,
                         reconnect_backoff_min_s=0.2)
    return asyncio.run(_first_scan(params, args.timeout, hand_over=hand_over))


async def _first_scan(params: LidarParams, timeout: float, *, hand_over: bool = False,
                      ) -> tuple[LidarDriver, LaserScan | None]:
    bus = Bus()
    driver = make_driver(bus, params)
    got: list[LaserScan] = []
    bus.subscribe(params.topic, got.append)
    task = asyncio.create_task(driver.run())
    deadline = time.monotonic() + timeout

    def not_this_protocol() -> bool:
        return hand_over and driver.stats.device_errors > 0 and not driver.info.get("model")

    try:
        while not got and not task.done() and time.monotonic() < deadline and not not_this_protocol():
            await asyncio.sleep(0.02)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, DeviceError):
            await task
    return driver, (got[0] if got else None)
