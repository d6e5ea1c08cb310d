"""Inertial-only initialisation on real EuRoC IMU + ground-truth motion (issue 3 benchmark).

For each sequence, consecutive windows of ``--duration`` seconds start where the IMU stops being static
(the first static segment found by ``detect_static_segments``). Keyframes every ``--spacing`` seconds
(ground-truth stamps) give camera poses (cam0 extrinsic) in the first keyframe's camera frame, with
positions multiplied by a random factor in [0.2, 5] (log-uniform) and each rotation perturbed by
``--rot-noise`` degrees about a random axis. ``inertial_only_init`` must recover the inverse factor
(scale) and the gravity direction. Prints one markdown table with every window.

    vigs bench imu_init [--sequences V1_01_easy,V2_01_easy,MH_03_medium] [--windows 4] [--duration 10]
                        [--spacing 0.25] [--rot-noise 0.5] [--seed 0] [--noise-scale 1] [--refine-rotations]
                        [--bias-walk] [--walk-scale 1]
"""
from __future__ import annotations

import argparse
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

SHARED = Path(os.environ.get("VIGS_SHARED", "/work/shared")) / "data" / "euroc"


def main(argv: list[str] | None = None) -> int:
    from vigs_core.imu.inertial_init import InertialInitConfig, inertial_only_init
    from vigs_core.imu.init_scenario import init_errors, make_scenario
    from vigs_core.imu.static_init import detect_static_segments
    from vigs_core.io import EurocSequence, read_camera_yaml

    parser = argparse.ArgumentParser(prog="vigs bench imu_init", description=__doc__.split("\n")[0])
    parser.add_argument("--sequences", default="V1_01_easy,V2_01_easy,MH_03_medium")
    parser.add_argument("--windows", type=int, default=4, help="windows per sequence")
    parser.add_argument("--duration", type=float, default=10.0, help="window length (s)")
    parser.add_argument("--spacing", type=float, default=0.25, help="keyframe spacing (s)")
    parser.add_argument("--rot-noise", type=float, default=0.5, help="rotation noise per keyframe (deg)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise-scale", type=float, default=1.0,
                        help="multiply the YAML white-noise densities (imu-check measures 4-9x on EuRoC)")
    parser.add_argument("--refine-rotations", action="store_true",
                        help="estimate a rotation correction per keyframe instead of holding the rotations fixed")
    parser.add_argument("--bias-walk", action="store_true",
                        help="one bias per keyframe tied by the bias random walk instead of one bias per window")
    parser.add_argument("--walk-scale", type=float, default=1.0,
                        help="multiply the YAML bias random walks (the V1_01 ground-truth biases wander 4-5x faster)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    calib = read_camera_yaml(SHARED / "calib" / "cam0_sensor.yaml")
    T_cb = torch.as_tensor(np.linalg.inv(calib.T_BS))
    config = InertialInitConfig(refine_rotations=args.refine_rotations, bias_random_walk=args.bias_walk)
    rng = np.random.default_rng(args.seed)
    rows, scale_errs, grav_errs = [], [], []
    for name in args.sequences.split(","):
        seq = EurocSequence(SHARED / name)
        imu, gt, noise = seq.imu, seq.groundtruth, seq.imu_noise
        noise = replace(noise, gyro_noise_density=noise.gyro_noise_density * args.noise_scale,
                        acc_noise_density=noise.acc_noise_density * args.noise_scale,
                        gyro_random_walk=noise.gyro_random_walk * args.walk_scale,
                        acc_random_walk=noise.acc_random_walk * args.walk_scale)
        static = detect_static_segments(imu)
        start = int(static[0, 1]) if len(static) else int(imu.t_ns[0])
        start = max(start, int(gt.t_ns[0]))
        end = min(int(imu.t_ns[-1]), int(gt.t_ns[-1]))
        for w in range(args.windows):
            t0 = start + int(round(w * args.duration * 1e9))
            if t0 + args.duration * 1e9 > end:
                break
            factor = float(np.exp(rng.uniform(math.log(0.2), math.log(5.0))))
            scenario = make_scenario(gt, t0, args.duration, args.spacing, calib.T_BS, factor, args.rot_noise, rng)
            tic = time.perf_counter()
            result = inertial_only_init(scenario.T_wc, scenario.stamps_ns, imu, noise, T_cb, config)
            elapsed = time.perf_counter() - tic
            scale_err, grav_err = init_errors(result, scenario)
            signed = result.scale / scenario.true_scale - 1.0
            scale_errs.append(scale_err)
            grav_errs.append(grav_err)
            rows.append(
                f"| {name} | {(t0 - imu.t_ns[0]) * 1e-9:.1f} | {len(scenario.stamps_ns)} | {factor:.3f} | "
                f"{signed * 100:+.2f} | {grav_err:.2f} | {result.log_scale_std * 100:.2f} | "
                f"{result.gravity_std_deg:.2f} | {result.chi2_per_dof:.2f} | {'yes' if result.trustworthy else 'no'} | "
                f"{elapsed:.2f} |"
            )
    print(f"Inertial-only initialisation: {args.duration:g} s windows, keyframes every {args.spacing:g} s, "
          f"{args.rot_noise:g} deg rotation noise, positions scaled by a factor in [0.2, 5], IMU noise densities x "
          f"{args.noise_scale:g}, rotations {'refined' if args.refine_rotations else 'fixed'}, "
          f"{'bias per keyframe, random walks x ' + format(args.walk_scale, 'g') if args.bias_walk else 'one bias'}\n")
    print("| sequence | window start (s) | keyframes | position factor | scale error (%, signed) | gravity error (deg) "
          "| reported scale std (%) | reported gravity std (deg) | chi2/dof | trusted | time (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    s, g = np.array(scale_errs) * 100, np.array(grav_errs)
    print(f"\n{len(s)} windows: scale error median {np.median(s):.2f} %, max {s.max():.2f} %, "
          f"within 1 %: {(s < 1).sum()}/{len(s)}; gravity error median {np.median(g):.2f} deg, "
          f"max {g.max():.2f} deg, within 1 deg: {(g < 1).sum()}/{len(g)}")
    return 0
