"""Synthetic visual-inertial scenarios for the vio tests: an analytic body motion (the simulator's
:class:`ProceduralMotion`), exact IMU synthesised from it, keyframe camera poses and an exact dense
correspondence problem between the keyframes (points on a slanted wall in front of the first camera)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.geometry import se3_inverse
from vigs_core.sim.imu_synthesis import imu_stamps, synthesize_imu
from vigs_core.sim.trajectory import ProceduralConfig, ProceduralMotion
from vigs_core.solver import EdgeSet, Intrinsics, reproject
from vigs_core.types import ImuNoise, ImuSamples

INTR = Intrinsics(180.0, 180.0, 94.5, 59.5)
# EuRoC cam0 extrinsic T_BS (camera in body), rounded
T_BC = torch.tensor([[0.0148655, -0.9998809, 0.0041403, -0.0216401],
                     [0.9995572, 0.0149672, 0.0257155, -0.0646770],
                     [-0.0257744, 0.0037562, 0.9996607, 0.0098107],
                     [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)
_U, _, _Vh = torch.linalg.svd(T_BC[:3, :3])
T_BC[:3, :3] = _U @ _Vh  # exactly orthonormal
T_CB = se3_inverse(T_BC)
NOISE = ImuNoise()


@dataclass
class Scenario:
    """Keyframes of an analytic motion (metric, gravity-aligned world, gravity (0, 0, -9.81)).

    stamps_ns (n,), T_wc (n, 4, 4) true camera poses, T_wb (n, 4, 4) body poses, velocities (n, 3) m/s,
    imu: exact measurements (plus constant biases bias_gyro, bias_acc (3,)).
    """

    stamps_ns: np.ndarray
    T_wc: torch.Tensor
    T_wb: torch.Tensor
    velocities: torch.Tensor
    imu: ImuSamples
    bias_gyro: np.ndarray
    bias_acc: np.ndarray


def make_scenario(n: int = 8, spacing_s: float = 0.25, seed: int = 0, duration_s: float = 12.0,
                  bias_gyro=(0.0, 0.0, 0.0), bias_acc=(0.0, 0.0, 0.0), start_s: float = 0.5,
                  config: ProceduralConfig | None = None, imu_noise: bool = False) -> Scenario:
    """``n`` keyframes every ``spacing_s`` from ``start_s``; IMU exact (plus constant biases) or, with
    ``imu_noise``, with EuRoC-like white noise and bias random walk."""
    cfg = config or ProceduralConfig(duration_s=duration_s, min_period_s=3.0, max_period_s=8.0)
    motion = ProceduralMotion(seed, T_BC[:3, :3].numpy(), cfg, start_ns=10**9)
    t_imu = imu_stamps(motion.start_ns, motion.end_ns, 200.0)
    syn = synthesize_imu(motion, t_imu, NOISE if imu_noise else None, seed=seed,
                         initial_bias_gyro=np.array(bias_gyro),
                         initial_bias_acc=np.array(bias_acc))
    # keyframe stamps deliberately between IMU samples
    stamps = motion.start_ns + np.round((start_s + spacing_s * np.arange(n)) * 1e9).astype(np.int64) + 1_234_567
    state = motion.evaluate(stamps)
    T_wb = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    T_wb[:, :3, :3] = torch.from_numpy(state.rotation)
    T_wb[:, :3, 3] = torch.from_numpy(state.position)
    return Scenario(stamps, T_wb @ T_BC, T_wb, torch.from_numpy(state.velocity), syn.imu,
                    np.array(bias_gyro, dtype=np.float64), np.array(bias_acc, dtype=np.float64))


def visual_problem(T_cw: torch.Tensor, grid=(10, 7), seed: int = 0, depth=(2.0, 4.0)):
    """Exact dense correspondences between all keyframe pairs (both directions) for world->camera poses
    ``T_cw`` (n, 4, 4): random depths per keyframe pixel; returns (disps (n, P), coords (P, 2), EdgeSet)."""
    g = torch.Generator().manual_seed(seed)
    n = T_cw.shape[0]
    us = torch.linspace(8, 180, grid[0], dtype=torch.float64)
    vs = torch.linspace(6, 112, grid[1], dtype=torch.float64)
    coords = torch.stack(torch.meshgrid(us, vs, indexing="xy"), -1).reshape(-1, 2)
    d = depth[0] + (depth[1] - depth[0]) * torch.rand(n, coords.shape[0], generator=g, dtype=torch.float64)
    disps = 1.0 / d
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j and abs(i - j) <= 3]
    ii = torch.tensor([p[0] for p in pairs])
    jj = torch.tensor([p[1] for p in pairs])
    proj = reproject(T_cw[ii], T_cw[jj], disps[ii], coords, INTR)
    inside = (proj.uv[..., 0] > 0) & (proj.uv[..., 0] < 190) & (proj.uv[..., 1] > 0) & (proj.uv[..., 1] < 120)
    w = (proj.valid & inside).to(torch.float64)
    return disps, coords, EdgeSet(ii, jj, proj.uv, w)


def _texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """(size, size) float32 multi-scale random texture in [0, 255]."""
    import cv2
    tex = np.zeros((size, size), np.float32)
    for cells, amp in ((4, 0.5), (16, 0.8), (64, 1.0), (256, 0.6)):
        tex += amp * cv2.resize(rng.random((cells, cells)).astype(np.float32), (size, size),
                                interpolation=cv2.INTER_CUBIC)
    tex -= tex.min()
    return 255.0 * tex / tex.max()


class BoxRoom:
    """A textured box room ``[-half, half]^2 x [0, height]`` (m), rendered by ray casting: each pixel ray hits
    the nearest of the six faces, whose texture is sampled bilinearly. Fast enough for VIO tests."""

    def __init__(self, half: float = 4.0, height: float = 3.0, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        h = half
        # (origin, u axis, v axis, u extent, v extent): faces spanned by o + u a + v b
        self.faces = [
            (np.array([h, -h, 0.0]), np.array([0.0, 1, 0]), np.array([0.0, 0, 1]), 2 * h, height),
            (np.array([-h, -h, 0.0]), np.array([0.0, 1, 0]), np.array([0.0, 0, 1]), 2 * h, height),
            (np.array([-h, h, 0.0]), np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 2 * h, height),
            (np.array([-h, -h, 0.0]), np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), 2 * h, height),
            (np.array([-h, -h, 0.0]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), 2 * h, 2 * h),
            (np.array([-h, -h, height]), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), 2 * h, 2 * h),
        ]
        self.textures = [_texture(rng) for _ in self.faces]

    def render(self, T_wc: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int,
               height: int) -> np.ndarray:
        """(height, width) uint8 grey image of camera pose ``T_wc`` (4, 4) with pinhole intrinsics."""
        import cv2
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays = np.stack(((u - cx) / fx, (v - cy) / fy, np.ones_like(u)), -1) @ T_wc[:3, :3].T
        c = T_wc[:3, 3]
        best = np.full(u.shape, np.inf)
        image = np.zeros(u.shape, np.float32)
        for (o, a, b, ea, eb), tex in zip(self.faces, self.textures):
            n = np.cross(a, b)
            denom = rays @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((o - c) @ n) / denom
            p = c + t[..., None] * rays
            pu, pv = (p - o) @ a, (p - o) @ b
            hit = (t > 0) & (t < best) & (pu >= 0) & (pu <= ea) & (pv >= 0) & (pv <= eb)
            size = tex.shape[0] - 1
            mx = np.where(hit, pu / ea * size, 0).astype(np.float32)
            my = np.where(hit, pv / eb * size, 0).astype(np.float32)
            sample = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
            image = np.where(hit, sample, image)
            best = np.where(hit, t, best)
        return np.clip(image, 0, 255).astype(np.uint8)
