"""``vigs sim``: render a visual-inertial sequence (images, exact depth, IMU, ground truth) into an EuRoC
ASL folder and/or a ROS 2 bag.

Motion sources (one of):
  --euroc DIR                   recorded EuRoC sequence: its IMU and ground truth (hybrid sequence)
  --trajectory FILE [--imu CSV] TUM or EuRoC ground-truth trajectory; with a real IMU CSV (hybrid) or
                                with IMU synthesised from a spline through the trajectory
  --procedural                  built-in smooth random motion with synthesised IMU
"""
from __future__ import annotations

import argparse
import sys

HELP = "render a visual-inertial sequence (images, depth, IMU, ground truth) to EuRoC ASL and/or a ROS 2 bag"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("motion source")
    src.add_argument("--euroc", help="EuRoC sequence folder (mav0/imu0 and ground truth)")
    src.add_argument("--trajectory", help="body trajectory: TUM text or EuRoC ground-truth CSV")
    src.add_argument("--imu", help="real IMU CSV (EuRoC imu0/data.csv format) for --trajectory")
    src.add_argument("--procedural", action="store_true", help="built-in procedural motion with synthesised IMU")
    src.add_argument("--procedural-duration", type=float, default=30.0, help="length of the procedural motion (s)")
    src.add_argument("--procedural-speed", type=float, default=1.0,
                     help="time scale of the procedural motion: its periods divided by this (2: twice the speeds and "
                          "rotation rates, four times the accelerations, over the same path)")
    cal = parser.add_argument_group("sensors")
    cal.add_argument("--camera", help="camera calibration: EuRoC sensor.yaml or Kalibr camchain (default: EuRoC cam0)")
    cal.add_argument("--imu-yaml", help="IMU noise: EuRoC sensor.yaml or Kalibr imu.yaml (default: EuRoC ADIS16448)")
    cal.add_argument("--width", type=int, help="image width (px); the calibration is scaled (default: calibration's)")
    cal.add_argument("--height", type=int, help="image height (px) (default: width times the calibration's aspect)")
    cal.add_argument("--rate", type=float, default=20.0, help="camera rate (Hz)")
    cal.add_argument("--imu-rate", type=float, default=200.0, help="rate of synthesised IMU (Hz)")
    cal.add_argument("--noise-free-imu", action="store_true", help="synthesise IMU without noise and bias")
    seq = parser.add_argument_group("sequence")
    seq.add_argument("--start", type=float, default=0.0, help="first frame this long after the motion starts (s)")
    seq.add_argument("--duration", type=float, help="sequence length (s) (default: to the end)")
    seq.add_argument("--seed", type=int, default=0, help="scene seed (layout and textures)")
    seq.add_argument("--noise-seed", type=int, default=0, help="seed of degradations and synthesised IMU noise")
    seq.add_argument("--rgb", action="store_true", help="colour images (rgb8) instead of grey (mono8)")
    seq.add_argument(
        "--supersample", type=int, default=1, help="s x s rays per pixel (textures are prefiltered anyway)"
    )
    seq.add_argument("--no-depth", action="store_true", help="do not write depth")
    seq.add_argument(
        "--objects", type=int, help="objects in the room (default: 0.2 per square metre of floor, at least 10)"
    )
    seq.add_argument(
        "--photos", help="folder of grey photographs (PNG/JPG, one size) used as textures on half of the surfaces"
    )
    deg = parser.add_argument_group("degradations")
    deg.add_argument("--blur-kernel", type=int, default=0, help="motion-blur kernel length (px), random direction")
    deg.add_argument("--exposure-time", type=float, default=0.0, help="exposure (s) for sub-frame averaged blur")
    deg.add_argument("--subframes", type=int, default=5, help="sub-frame renders per exposure")
    deg.add_argument("--exposure-amplitude", type=float, default=0.0, help="relative amplitude of exposure changes")
    deg.add_argument("--exposure-period", type=float, default=8.0, help="period of exposure changes (s)")
    deg.add_argument("--over-exposure", type=float, default=1.0, help="beta: I = min(1, beta I)")
    deg.add_argument("--low-light-gamma", type=float, default=1.0, help="gamma: I = I^gamma")
    deg.add_argument("--photon-scale", type=float, default=0.0, help="s: Poisson shot noise, I = Poisson(s I) / s")
    deg.add_argument("--read-noise", type=float, default=0.0, help="Gaussian read noise sigma (grey levels)")
    deg.add_argument("--stride", type=int, default=1, help="keep every n-th frame (IMU kept)")
    deg.add_argument("--drop-prob", type=float, default=0.0, help="probability of dropping a frame (IMU kept)")
    out = parser.add_argument_group("outputs")
    out.add_argument("--asl", help="write an EuRoC ASL folder here")
    out.add_argument("--bag", help="write a ROS 2 bag (directory) here")
    out.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="bag storage")
    out.add_argument(
        "--image-format", choices=("raw", "png"), default="raw",
        help="bag images: raw sensor_msgs/Image or lossless PNG sensor_msgs/CompressedImage (smaller)",
    )
    out.add_argument("--groundtruth", help="TUM ground-truth file (default with --bag: <bag>_groundtruth_tum.txt)")
    out.add_argument("--no-progress", action="store_true", help="no progress bar")


def _directory_size(path) -> int:
    from pathlib import Path

    p = Path(path)
    return p.stat().st_size if p.is_file() else sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def run(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    import numpy as np
    import torch
    from tqdm import tqdm

    from vigs_core.io import EurocSequence, read_camera_yaml, read_euroc_imu, read_imu_yaml, read_trajectory, write_tum
    from vigs_core.io.rosbag import BagWriter
    from vigs_core.sim.degrade import DegradeConfig
    from vigs_core.sim.hybrid import SimConfig, SimSequence, euroc_cam0_calibration, hybrid_source, synthetic_source
    from vigs_core.sim.render import RenderConfig
    from vigs_core.sim.scene import SceneConfig
    from vigs_core.sim.trajectory import ProceduralConfig, ProceduralMotion, SplineMotion
    from vigs_core.sim.writers import AslWriter
    from vigs_core.types import ImuNoise

    torch.set_num_threads(1)
    sources = [bool(args.euroc), bool(args.trajectory), bool(args.procedural)]
    if sum(sources) != 1:
        print("vigs sim: give exactly one of --euroc, --trajectory, --procedural", file=sys.stderr)
        return 2
    if not (args.asl or args.bag):
        print("vigs sim: give an output: --asl DIR and/or --bag DIR", file=sys.stderr)
        return 2
    for target in (args.asl, args.bag):
        if target and Path(target).exists() and any(Path(target).iterdir()):
            print(f"vigs sim: output {target} exists and is not empty", file=sys.stderr)
            return 2
    calibration = read_camera_yaml(args.camera) if args.camera else euroc_cam0_calibration()
    noise = read_imu_yaml(args.imu_yaml) if args.imu_yaml else ImuNoise()
    camera = calibration.camera
    if args.width or args.height:
        width = args.width or round(args.height * camera.width / camera.height)
        height = args.height or round(width * camera.height / camera.width)
        camera = camera.resized(width, height)
    if args.euroc:
        euroc = EurocSequence(args.euroc)
        source = hybrid_source(euroc.groundtruth, euroc.imu)
    elif args.trajectory and args.imu:
        source = hybrid_source(read_trajectory(args.trajectory), read_euroc_imu(args.imu))
    elif args.trajectory:
        source = synthetic_source(
            SplineMotion(read_trajectory(args.trajectory)), noise, args.imu_rate, args.noise_seed, args.noise_free_imu
        )
    else:
        if not args.procedural_speed > 0:
            print(f"vigs sim: --procedural-speed {args.procedural_speed}; expected > 0", file=sys.stderr)
            return 2
        base = ProceduralConfig()
        shape = ProceduralConfig(duration_s=args.procedural_duration,
                                 min_period_s=base.min_period_s / args.procedural_speed,
                                 max_period_s=base.max_period_s / args.procedural_speed)
        motion = ProceduralMotion(args.seed, calibration.T_BS[:3, :3], shape)
        source = synthetic_source(motion, noise, args.imu_rate, args.noise_seed, args.noise_free_imu)
    degrade = DegradeConfig(
        blur_kernel=args.blur_kernel,
        exposure_time_s=args.exposure_time,
        blur_subframes=args.subframes,
        exposure_amplitude=args.exposure_amplitude,
        exposure_period_s=args.exposure_period,
        over_exposure=args.over_exposure,
        low_light_gamma=args.low_light_gamma,
        photon_scale=args.photon_scale,
        read_noise=args.read_noise,
        stride=args.stride,
        drop_probability=args.drop_prob,
        seed=args.noise_seed,
    )
    config = SimConfig(
        rate_hz=args.rate,
        start_s=args.start,
        duration_s=args.duration,
        with_depth=not args.no_depth,
        scene_seed=args.seed,
        render=RenderConfig(supersample=args.supersample, rgb=args.rgb),
        scene=SceneConfig(n_objects=args.objects),
        degrade=degrade,
    )
    photos = []
    if args.photos:
        import cv2

        paths = sorted(p for p in Path(args.photos).iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        if not paths:
            print(f"vigs sim: no PNG/JPG images in {args.photos}", file=sys.stderr)
            return 2
        photos = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths]
    sequence = SimSequence(source, camera, calibration.T_BS, config, photos=photos)
    asl = AslWriter(args.asl, camera, calibration.T_BS, args.rate, config.with_depth) if args.asl else None
    bag = None
    if args.bag:
        bag = BagWriter(
            args.bag,
            camera,
            calibration.T_BS,
            sequence.imu,
            sequence.groundtruth,
            args.storage,
            with_depth=config.with_depth,
            image_format=args.image_format,
        )
    started = time.monotonic()
    for frame in tqdm(sequence.frames(), total=len(sequence), unit="frame", disable=args.no_progress):
        if asl:
            asl.write_frame(frame.t_ns, frame.image, frame.depth)
        if bag:
            bag.write_frame(frame.t_ns, frame.image, frame.depth)
    if asl:
        asl.close(sequence.imu, noise, sequence.groundtruth)
    outputs = [p for p in (args.asl, args.bag) if p]
    if bag:
        bag.close()
        gt_path = args.groundtruth or f"{str(args.bag).rstrip('/')}_groundtruth_tum.txt"
        write_tum(gt_path, sequence.groundtruth)
        outputs.append(gt_path)
    elif args.groundtruth:
        write_tum(args.groundtruth, sequence.groundtruth)
        outputs.append(args.groundtruth)
    elapsed = time.monotonic() - started
    size = sum(_directory_size(p) for p in outputs)
    print(
        f"vigs sim: {len(sequence)} frames {camera.width}x{camera.height} at {args.rate:g} Hz "
        f"({source.kind}), {sequence.duration_s:.2f} s, path length {sequence.path_length():.2f} m, "
        f"{len(sequence.imu)} IMU samples, {sequence.scene.num_boxes - 1} objects; "
        f"rendered in {elapsed:.1f} s ({len(sequence) / max(elapsed, 1e-9):.1f} frames/s); "
        f"output {size / 1e6:.1f} MB: {', '.join(str(p) for p in outputs)}"
    )
    return 0
