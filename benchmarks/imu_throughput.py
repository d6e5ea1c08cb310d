"""Preintegration throughput in samples per second (issue 3 benchmark).

Preintegrates windows of real EuRoC V1_01 IMU (or analytic motion with ``--synthetic``) of several
lengths between stamps that fall between samples, with covariance and bias Jacobians, and reports the
best of ``--repeats`` timings per configuration. Also times one batched call over consecutive keyframe
intervals and state propagation at IMU rate. Prints one markdown table.

    vigs bench imu_throughput [--repeats 20] [--synthetic] [--rate 200]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

SHARED = Path(os.environ.get("VIGS_SHARED", "/work/shared")) / "data" / "euroc"


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - tic)
    return best


def main(argv: list[str] | None = None) -> int:
    from vigs_core.imu.analytic_motion import AnalyticMotion
    from vigs_core.imu.preintegration import preintegrate, preintegrate_between
    from vigs_core.imu.propagation import ImuState, propagate_path
    from vigs_core.io import read_euroc_imu
    from vigs_core.types import ImuNoise

    parser = argparse.ArgumentParser(prog="vigs bench imu_throughput", description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--synthetic", action="store_true", help="analytic motion instead of real V1_01 IMU")
    parser.add_argument("--rate", type=float, default=200.0, help="sample rate of the synthetic IMU (Hz)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    if args.synthetic:
        step = int(round(1e9 / args.rate))
        imu = AnalyticMotion.default().imu(np.arange(0, 40_000_000_000, step))
        source = f"analytic motion at {args.rate:g} Hz"
    else:
        imu = read_euroc_imu(SHARED / "V1_01_easy" / "mav0" / "imu0" / "data.csv")
        source = "EuRoC V1_01 IMU (200 Hz)"
    noise = ImuNoise()
    t0 = int(imu.t_ns[100]) + 1_234_567
    rows = []
    for scheme in ("closed_form", "forster"):
        for seconds in (0.1, 0.5, 2.0, 10.0):
            t1 = t0 + int(seconds * 1e9)
            samples = int(((imu.t_ns > t0) & (imu.t_ns < t1)).sum()) + 1
            best = _best(lambda: preintegrate(imu, t0, t1, noise, scheme=scheme), args.repeats)
            rows.append(f"| preintegrate ({scheme}) | {seconds:g} s | {samples} | {best * 1e3:.2f} | "
                        f"{samples / best:,.0f} |")
    stamps = t0 + np.arange(0, 21) * 500_000_000  # 20 keyframe intervals of 0.5 s
    samples = int(((imu.t_ns > stamps[0]) & (imu.t_ns < stamps[-1])).sum()) + 20
    best = _best(lambda: preintegrate_between(imu, stamps, noise), max(args.repeats // 4, 1))
    rows.append(f"| preintegrate_between, 20 x 0.5 s | 10 s | {samples} | {best * 1e3:.2f} | {samples / best:,.0f} |")
    zero = torch.zeros(3, dtype=torch.float64)
    state = ImuState(t0, torch.eye(3, dtype=torch.float64), zero, zero, zero, zero)
    t1 = t0 + 2_000_000_000
    samples = int(((imu.t_ns > t0) & (imu.t_ns < t1)).sum()) + 1
    best = _best(lambda: propagate_path(state, imu, t1), args.repeats)
    rows.append(f"| propagate_path (IMU-rate states) | 2 s | {samples} | {best * 1e3:.2f} | {samples / best:,.0f} |")
    print(f"Preintegration throughput on {source}, float64, 1 thread, best of {args.repeats}\n")
    print("| operation | interval | integrated pieces | time (ms) | samples/s |")
    print("| --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    return 0
