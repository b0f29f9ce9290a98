"""``racecar-hw bag info`` (what a bag holds, whether it is complete) and ``racecar-hw bag recover``."""

from __future__ import annotations

import argparse

# The bag modules are imported by the verbs that use them: every command's module is imported to
# build the parser, and a daemon (``racecar-hw run``) has no use for them (docs/install.md, "Memory").


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bag", help="look into a bag, or recover an interrupted recording",
                       description="Bags: ROS 1 .bag files and ROS 2 bag directories (MCAP or sqlite3).")
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    info = verbs.add_parser("info", help="topics, types, counts, time range, complete or not",
                            description="Print the bag's format, whether it is complete (closed by "
                                        "its recorder), its time range, and each topic with its "
                                        "type and message count.")
    info.add_argument("bag", help="ROS 1 .bag file or ROS 2 bag directory")
    info.set_defaults(func=cmd_info)
    rec = verbs.add_parser("recover", help="make an interrupted recording readable",
                           description="Rewrite an interrupted MCAP or ROS 1 recording into a new, "
                                       "closed bag (default: NAME.recovered next to it, or "
                                       "STEM.recovered.bag) with every message that reached the "
                                       "disk; fix a sqlite3 bag's metadata.yaml in place (with "
                                       "-o: in a copy at OUT, the bag left as it is). A complete "
                                       "bag is left alone.")
    rec.add_argument("bag", help="ROS 1 .bag file or ROS 2 bag directory")
    rec.add_argument("-o", "--output", metavar="OUT",
                     help="where to write the recovered bag (sqlite3: a fixed copy); must not exist")
    rec.set_defaults(func=cmd_recover)


def cmd_info(args: argparse.Namespace) -> int:
    from racecar_hw.bags.info import bag_info, format_info  # noqa: PLC0415

    print(format_info(bag_info(args.bag)))
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    from racecar_hw.bags.recover import recover_bag  # noqa: PLC0415

    result = recover_bag(args.bag, args.output)
    if result.was_complete:
        print(f"{result.path} is complete ({result.messages} messages): nothing to recover")
    else:
        print(f"recovered {result.messages} messages into {result.path}")
    for bad in result.bad_chunks:
        print(f"left out (damaged): {bad}")
    return 0
