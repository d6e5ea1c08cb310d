"""``vigs view [--connect URL | --rrd FILE] [--ros-args ...]``: the viewer node (:mod:`vigs_ros.viewer_node`),
which logs a running graph's topics to rerun: a local viewer by default, a viewer on another machine with
``--connect`` (e.g. a laptop watching a robot), or an ``.rrd`` file. It runs until Ctrl-C."""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--connect", metavar="URL", help="stream to the rerun viewer at URL "
                                                         "(e.g. rerun+http://laptop:9876/proxy)")
    where.add_argument("--rrd", metavar="FILE", help="record to a rerun file instead of showing a viewer")
    parser.add_argument("ros_args", nargs=argparse.REMAINDER,
                        help="--ros-args ... passed to the node (parameters, remaps)")


def run(args: argparse.Namespace) -> int:
    from vigs_ros.viewer_node import main

    target = args.connect or args.rrd or "spawn"
    ros_args = list(args.ros_args)
    if "--ros-args" not in ros_args:
        ros_args.insert(0, "--ros-args")
    return main(["vigs_view", *ros_args, "-p", f"rerun_target:={target}"])
