"""Entry point of the ``vigs`` command: one subcommand per module listed in ``SUBCOMMANDS``.

Each subcommand module defines ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their subcommand runs, so ``vigs eval`` never loads torch or rclpy.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# subcommand name -> (module, one-line help)
SUBCOMMANDS = {
    "eval": ("vigs_cli.eval_cmd", "trajectory accuracy: ATE, RPE, recall against ground truth"),
    "bench": ("vigs_cli.bench_cmd", "run a benchmark script from benchmarks/ (prints a table)"),
    "launch": ("vigs_cli.launch_cmd", "start the ROS 2 node graph (separate processes or --composed), optionally on a bag"),
    "replay": ("vigs_cli.replay_cmd", "publish a ROS 2 (MCAP/sqlite3) or ROS 1 bag with /clock at a rate or --fast"),
    "imu-check": ("vigs_cli.imu_check_cmd", "IMU stream health: rate, jitter, gaps, static bias/noise, NEES vs ground truth"),
    "sim": ("vigs_cli.sim_cmd", "render a visual-inertial sequence (images, depth, IMU, ground truth) to ASL / ROS 2 bag"),
    "view": ("vigs_cli.view_cmd", "log a running graph's topics to rerun: a live viewer, a remote one, or an .rrd file"),
    "run": ("vigs_cli.run_cmd", "dense monocular odometry on an EuRoC ASL folder or a ROS bag: trajectories + report"),
}


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vigs", description="VIGS-ROS visual-inertial Gaussian-splatting SLAM")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == selected:
            importlib.import_module(module_name).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    selected = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(selected if selected in SUBCOMMANDS else None)
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    module = importlib.import_module(SUBCOMMANDS[args.command][0])
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
