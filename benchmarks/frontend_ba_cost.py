"""Cost of one dense-BA LM iteration versus window size (synthetic, 376x240 input, 1/8 grid = 47x30).

Usage: ``vigs bench frontend_ba_cost [--windows 4 6 8 10 12 16] [--dtype float32] [--radius 3] [--repeat 3]``

Each keyframe is connected to its ``radius`` predecessors in both directions (the frontend's temporal edges).
Prints per window size: edges, seconds per linearisation + Schur + solve + back-substitution + trial cost
(one :func:`bundle_adjust` iteration), median over repeats.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

from vigs_core.geometry import se3_exp
from vigs_core.solver import BAConfig, EdgeSet, Intrinsics, bundle_adjust, reproject


def problem(n: int, radius: int, dtype: torch.dtype):
    g = torch.Generator().manual_seed(0)
    us = torch.arange(47, dtype=torch.float64) * 8 + 3.5
    vs = torch.arange(30, dtype=torch.float64) * 8 + 3.5
    coords = torch.stack(torch.meshgrid(us, vs, indexing="xy"), -1).reshape(-1, 2)
    intr = Intrinsics(229.3, 228.6, 183.1, 123.7)
    poses = torch.stack([se3_exp(torch.tensor([0.04 * k, 0.01 * k, 0.0, 0.005 * k, 0.01 * k, 0.0],
                                              dtype=torch.float64)) for k in range(n)])
    disps = 0.25 + 0.1 * torch.rand(n, coords.shape[0], generator=g, dtype=torch.float64)
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j and abs(i - j) <= radius]
    ii, jj = torch.tensor([p[0] for p in pairs]), torch.tensor([p[1] for p in pairs])
    uv = reproject(poses[ii], poses[jj], disps[ii], coords, intr).uv
    target = uv + 0.5 * torch.randn(uv.shape, generator=g, dtype=torch.float64)
    edges = EdgeSet(ii, jj, target.to(dtype), torch.ones(len(pairs), coords.shape[0], dtype=dtype))
    fixed = torch.zeros(n, dtype=torch.bool)
    fixed[0] = True
    return poses.to(dtype), (disps * 1.05).to(dtype), edges, coords.to(dtype), intr, fixed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="frontend_ba_cost", description=__doc__.splitlines()[0])
    parser.add_argument("--windows", type=int, nargs="+", default=[4, 6, 8, 10, 12, 16])
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--radius", type=int, default=3)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    print(f"{'window':>7}{'edges':>7}{'residuals':>11}{'s/iter':>9}")
    for n in args.windows:
        poses, disps, edges, coords, intr, fixed = problem(n, args.radius, dtype)
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            bundle_adjust(poses, disps, edges, coords, intr, fixed, BAConfig(iterations=1))
            times.append(time.perf_counter() - t0)
        print(f"{n:>7}{len(edges.ii):>7}{len(edges.ii) * coords.shape[0]:>11}{statistics.median(times):>9.4f}")
    print(f"dtype {args.dtype}, threads {args.threads}, load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
