"""``vigs launch [--bag BAG] [--params FILE] [--composed]``: start the VIGS ROS 2 node graph.

Separate processes by default, or all nodes in one process with one executor (``--composed``); with
``--bag`` a replay feeds the graph (nodes on ``use_sim_time``) and the graph shuts down after it. Ctrl-C /
SIGTERM shut everything down cleanly. Exit status: 0 after a clean shutdown, non-zero when a node died.
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bag", help="replay this bag into the graph (see vigs replay)")
    parser.add_argument("--params", action="append", default=[], metavar="FILE",
                        help="parameter file applied after the shipped params/*.yaml (repeatable)")
    parser.add_argument("--composed", action="store_true",
                        help="all nodes in one process with one MultiThreadedExecutor")
    parser.add_argument("--nodes", nargs="+", help="start only these nodes (default: all four)")
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument("--rate", type=float, help="replay speed factor (default 1.0)")
    pace.add_argument("--fast", action="store_true", help="replay as fast as the frontend consumes")
    parser.add_argument("--remap", action="append", default=[], metavar="FROM:=TO",
                        help="replay: publish recorded topic FROM as TO (repeatable; default: the bag's first "
                             "Image (or CompressedImage), CameraInfo and Imu topics onto /image, /camera_info, /imu)")
    parser.add_argument("--settle", type=float, default=1.0,
                        help="replay: seconds between the graph's inputs being matched and the first message "
                             "(longer gives late subscribers, e.g. a recorder, time to be discovered)")
    parser.add_argument("--ack-timeout", type=float, default=5.0,
                        help="replay with --fast: longest wait for the frontend to acknowledge a frame (s)")
    parser.add_argument("--linger", type=float, default=3.0,
                        help="after the replay ends, seconds for the graph to drain before shutdown")


def run(args: argparse.Namespace) -> int:
    from vigs_ros.graph import NODES, node_params
    from vigs_ros.launch import LaunchConfig, bag_input_remaps, launch
    from vigs_ros.launch_file import read_launch_file
    from vigs_ros.params import check_params_file, load_params_file

    try:   # before anything reads them
        specs = node_params()
        for f in args.params:
            check_params_file(f, specs)
    except (OSError, ValueError) as exc:
        print(f"[launch] error: bad --params: {exc}")
        return 2
    replay_args: list[str] = []
    ros_args: list[str] = []
    if args.bag:
        if args.fast:
            replay_args.append("--fast")
        elif args.rate is not None:
            replay_args += ["--rate", str(args.rate)]
        remaps = args.remap
        if not remaps:
            try:
                remaps, ros_args = bag_input_remaps(args.bag)
            except ValueError as exc:
                print(f"[launch] error: {exc}")
                return 2
        for item in remaps:
            replay_args += ["--remap", item]
        # start replaying once the frontend and the IMU node listen on their (parameterised) inputs
        inputs = {"frontend": ("image_topic", "/image"), "imu_preintegration": ("imu_topic", "/imu")}
        try:
            launch_files = {node.name: node.params for node in read_launch_file()}
        except ValueError as exc:
            print(f"[launch] error: {exc}")
            return 2
        for node, (key, default) in inputs.items():
            if args.nodes and node not in args.nodes:
                continue
            topic = default
            for f in [*launch_files.get(node, []), *args.params]:
                topic = load_params_file(f, node).get(key, topic)
            replay_args += ["--wait-for", topic]
        replay_args += ["--wait-timeout", "60", "--settle", str(args.settle), "--ack-timeout", str(args.ack_timeout)]
    try:
        config = LaunchConfig(bag=args.bag, params=args.params, composed=args.composed,
                              nodes=args.nodes or list(NODES), replay_args=replay_args, ros_args=ros_args,
                              linger_s=args.linger)
        return launch(config)
    except ValueError as exc:
        print(f"[launch] error: {exc}")
        return 2
