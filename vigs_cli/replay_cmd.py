"""``vigs replay BAG [--rate R | --fast] [--remap A:=B]``: publish a recorded bag into the ROS 2 graph.

MCAP or sqlite3 ROS 2 bags (directory, or a bare .mcap/.db3) and ROS 1 .bag files; publishes ``/clock``.
Exit status 0, or 2 when the bag cannot be opened or holds nothing replayable.
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="ROS 2 bag directory, .mcap, .db3 or ROS 1 .bag")
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1.0 = real time)")
    pace.add_argument("--fast", action="store_true",
                      help="as fast as the graph consumes: wait for an acknowledgement (--ack-topic) after each "
                           "image")
    parser.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                        help="publish recorded topic FROM as TO (repeatable)")
    parser.add_argument("--topics", nargs="+", help="replay only these recorded topics")
    parser.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    parser.add_argument("--gate-topic", help="recorded topic paced by acknowledgements with --fast "
                                             "(default: the first image topic)")
    parser.add_argument("--ack-topic", default="/vigs/frame_done",
                        help="std_msgs/Header acknowledgements for --fast (default /vigs/frame_done)")
    parser.add_argument("--ack-timeout", type=float, default=5.0, help="longest wait per acknowledgement (s)")
    parser.add_argument("--fast-lookahead", type=float, default=0.1,
                        help="with --fast, recorded seconds of other topics published ahead of each gated message")
    parser.add_argument("--wait-for", action="append", default=[], metavar="TOPIC",
                        help="wait until TOPIC (as published) has a subscriber before starting (repeatable)")
    parser.add_argument("--wait-timeout", type=float, default=10.0, help="longest wait for --wait-for (s)")
    parser.add_argument("--settle", type=float, default=1.0,
                        help="seconds to wait after the --wait-for subscribers matched, before the first message")
    parser.add_argument("--start", type=float, default=0.0, help="skip the first START seconds of the bag")
    parser.add_argument("--duration", type=float, default=0.0, help="replay at most DURATION s (0: all)")


def run(args: argparse.Namespace) -> int:
    from vigs_ros.replay import ReplayConfig, parse_remaps, run_replay

    try:
        remap = parse_remaps(args.remap)
    except ValueError as exc:
        print(f"[replay] error: {exc}")
        return 2
    config = ReplayConfig(
        rate=args.rate, fast=args.fast, remap=remap, topics=args.topics, clock=not args.no_clock,
        gate_topic=args.gate_topic, ack_topic=args.ack_topic, ack_timeout_s=args.ack_timeout,
        fast_lookahead_s=args.fast_lookahead,
        wait_for=args.wait_for, wait_timeout_s=args.wait_timeout, settle_s=args.settle, start_offset_s=args.start,
        duration_s=args.duration,
    )
    return run_replay(args.bag, config)
