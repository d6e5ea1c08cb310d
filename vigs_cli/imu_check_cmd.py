"""``vigs imu-check EUROC_DIR_OR_BAG [--gt FILE] [--imu-yaml FILE] [--json]``: IMU stream health report.

Rate, jitter, gaps, out-of-order and duplicated stamps, saturation, static segments (gyro bias, noise
level against the configured densities), gravity magnitude, and with ground truth the preintegration
consistency (mean NEES/dof). See :mod:`vigs_core.imu.check`.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = "IMU stream health: rate, jitter, gaps, saturation, static bias/noise, gravity, NEES vs ground truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="EuRoC sequence folder (with mav0/) or a ROS bag (ROS 2 folder or ROS 1 .bag)")
    parser.add_argument("--gt", help="ground truth (EuRoC CSV or TUM); default: the sequence's or the bag's own")
    parser.add_argument("--no-gt", action="store_true", help="skip the ground-truth consistency check")
    parser.add_argument("--imu-yaml", help="IMU noise YAML (EuRoC sensor.yaml or Kalibr imu.yaml); "
                                           "default: the sequence's imu0/sensor.yaml, else EuRoC ADIS16448 values")
    parser.add_argument("--imu-topic", help="IMU topic in a bag (default: found by message type)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def _load(args):
    from vigs_core.io import EurocSequence, read_euroc_imu, read_imu_yaml, read_trajectory
    from vigs_core.types import ImuNoise

    source = Path(args.source)
    noise, gt = None, None
    if (source / "mav0").is_dir() or source.name == "mav0":
        seq = EurocSequence(source)
        imu = read_euroc_imu(seq.imu_dir / "data.csv", recorded_order=True)   # the check counts disorder
        if (seq.imu_dir / "sensor.yaml").is_file():
            noise = seq.imu_noise
        if seq.has_groundtruth:
            gt = seq.groundtruth
    elif source.exists():
        from vigs_core.io.rosbag import read_bag

        rec = read_bag(source, imu_topic=args.imu_topic)
        if len(rec.imu) == 0:
            raise ValueError(f"{source}: no sensor_msgs/Imu messages found")
        imu, gt = rec.imu, rec.groundtruth
    else:
        raise FileNotFoundError(f"{source}: not found (expected a EuRoC folder with mav0/ or a ROS bag)")
    if args.imu_yaml:
        noise = read_imu_yaml(args.imu_yaml)
    if args.gt:
        gt = read_trajectory(args.gt)
    if args.no_gt:
        gt = None
    return imu, noise or ImuNoise(), gt


def run(args: argparse.Namespace) -> int:
    import torch

    from vigs_core.imu.check import check_imu, format_report

    torch.set_num_threads(1)
    try:
        imu, noise, gt = _load(args)
        report = check_imu(imu, noise, gt)
    except (OSError, ValueError) as exc:
        print(f"vigs imu-check: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 0
