"""``racecar-hw fake-vesc`` (a fake VESC on a pty) and ``racecar-hw vesc-info`` (ask a VESC)."""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys

from racecar_hw.runtime.signals import run_until_stop_signal
from vesc.codec import KNOWN_MAJORS, firmware_text, values_layout
from vesc.driver import probe


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``fake-vesc`` and ``vesc-info`` commands."""
    fake = subparsers.add_parser(
        "fake-vesc", help="run a fake VESC on a pty until interrupted",
        description="Create a pty that speaks the VESC protocol (motor, servo, battery model) and a "
                    "symlink to it at --link, then serve until Ctrl-C.")
    fake.add_argument("--link", required=True, metavar="PATH", help="symlink to create, e.g. /tmp/vesc")
    fake.add_argument("--firmware", default="6.02", type=_firmware, metavar="X.YY",
                      help="firmware version to emulate, as vesc-info prints it; picks the "
                           "GET_VALUES layout (default 6.02)")
    fake.set_defaults(func=fake_vesc)

    info = subparsers.add_parser(
        "vesc-info", help="print a VESC's firmware version and one telemetry sample",
        description="Open the VESC at --port, ask FW_VERSION and GET_VALUES, print both.")
    info.add_argument("--port", required=True, metavar="PATH", help="serial path or pyserial URL")
    info.add_argument("--baudrate", type=int, default=115200, help="baud rate (default 115200)")
    info.add_argument("--timeout", type=float, default=2.0, metavar="S",
                      help="seconds to wait for each reply (default 2)")
    info.set_defaults(func=vesc_info)


def _firmware(text: str) -> tuple[int, int]:
    major, sep, minor = text.partition(".")
    if not sep or not major.isdigit() or not minor.isdigit():
        raise argparse.ArgumentTypeError(f"{text!r} is not a version like 6.02 or 3.40")
    return int(major), int(minor)


def fake_vesc(args: argparse.Namespace) -> int:
    """Serve a fake VESC at ``args.link`` until SIGINT (Ctrl-C) or SIGTERM; exits 0.

    The banner is printed by the serving coroutine, so only once the stop handlers of
    :func:`run_until_stop_signal` are in place: a stop signal after it is the command's documented
    end (exit 0, the link removed). Printed before them, a signal in between interrupted the
    start-up instead (exit 130), though the banner said the fake VESC was serving.
    """
    from vesc.fake import FakeVesc  # noqa: PLC0415 - here, not in every daemon that builds the parser

    fake = FakeVesc(args.link, firmware=args.firmware)

    async def serve() -> None:
        print(f"fake VESC (firmware {firmware_text(args.firmware)}) at {fake.path} -> "
              f"{fake.port.slave_path}; Ctrl-C to stop", flush=True)
        await fake.serve()

    try:
        fake.open()
        run_until_stop_signal(serve)
    finally:
        fake.port.close()
    return 0


def vesc_info(args: argparse.Namespace) -> int:
    """Print the firmware version and one decoded GET_VALUES reply of the VESC at ``args.port``.

    A firmware whose telemetry layout is not known is reported as unknown, without telemetry, and
    the exit status is 1: the driver would not drive that VESC.
    """
    fw, values = asyncio.run(probe(args.port, args.baudrate, args.timeout))
    known = values is not None
    print(f"firmware: {firmware_text(fw.version)}" + ("" if known else " (unknown)"))
    print(f"hardware: {fw.hw_name if fw.hw_name is not None else '(not reported)'}")
    if fw.uuid is not None:
        print(f"uuid:     {fw.uuid.hex()}")
    if values is None:
        print(f"racecar-hw vesc-info: firmware {firmware_text(fw.version)} is not one racecar-hw knows "
              f"(it knows {KNOWN_MAJORS.start}.x to {KNOWN_MAJORS.stop - 1}.x): its telemetry layout is "
              "unknown, so none was decoded, and the driver will not drive this VESC", file=sys.stderr)
        return 1
    layout = values_layout(fw.version)
    print(f"telemetry (GET_VALUES layout {layout.name}, {layout.value} bytes):")
    for f in dataclasses.fields(values):
        print(f"  {f.name:<20} {getattr(values, f.name)}")
    return 0
