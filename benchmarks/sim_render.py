"""Simulator rendering speed: frames/s of the ray caster at 376x240 and 752x480 (EuRoC cam0, radtan).

Renders consecutive frames along the V1_01 ground truth (../shared/data/euroc; the built-in procedural
motion when it is missing) in the room scene `vigs sim` builds, one CPU thread, image + depth per frame.
Targets (issue 4): >= 10 frames/s at 376x240 and >= 3 frames/s at 752x480.

Usage: vigs bench sim_render [--frames N] [--supersample S ...] [--threads T]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

V1_01 = Path(__file__).resolve().parent.parent.parent / "shared/data/euroc/V1_01_easy"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="vigs bench sim_render", description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40, help="frames rendered per configuration")
    parser.add_argument("--supersample", type=int, nargs="+", default=[1], help="supersampling factors to time")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args(argv)

    import numpy as np
    import torch

    from vigs_core.io import EurocSequence
    from vigs_core.sim.hybrid import SimConfig, SimSequence, euroc_cam0_calibration, hybrid_source, synthetic_source
    from vigs_core.sim.render import RenderConfig
    from vigs_core.sim.trajectory import ProceduralMotion
    from vigs_core.types import ImuNoise

    torch.set_num_threads(args.threads)
    cal = euroc_cam0_calibration()
    if V1_01.is_dir():
        seq = EurocSequence(V1_01)
        source, motion_name = hybrid_source(seq.groundtruth, seq.imu), "V1_01_easy ground truth"
    else:
        source = synthetic_source(ProceduralMotion(0, cal.T_BS[:3, :3]), ImuNoise())
        motion_name = "procedural motion"
    print(f"sim_render: {args.frames} frames per row along {motion_name}, from 10 s in, {args.threads} thread(s)")
    print(f"{'resolution':>10} {'supersample':>11} {'frames/s':>9} {'ms/frame':>9}")
    for width, height in ((376, 240), (752, 480)):
        for ss in args.supersample:
            config = SimConfig(start_s=10.0, render=RenderConfig(supersample=ss))
            sim = SimSequence(source, cal.camera.resized(width, height), cal.T_BS, config)
            sim.render_frame(0)  # warm-up
            started = time.perf_counter()
            for k in range(args.frames):
                frame = sim.render_frame(1 + k)
            elapsed = time.perf_counter() - started
            assert frame.image.shape == (height, width) and np.isfinite(frame.depth).all()
            fps = args.frames / elapsed
            print(f"{width:>4}x{height:<5} {ss:>11} {fps:>9.1f} {1000 / fps:>9.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
