"""Small textured-plane scenes for the loop-closure tests: a ray caster over rectangles with value-noise textures
(optionally periodic along one axis, to fake revisits), grey images and exact depth, and trajectories with
odometry drift injected as a chain of perturbed relative similarities."""
from __future__ import annotations

import math
from functools import lru_cache
from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.geometry import sim3_exp
from vigs_core.solver import Intrinsics

D = torch.float64


@dataclass
class Plane:
    """Rectangle ``origin + u e1 + v e2``, ``0 <= u <= width``, ``0 <= v <= height`` (metres) with a texture seed
    and an optional texture period along ``u`` (metres; 0 = none)."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    width: float
    height: float
    seed: int
    period_u: float = 0.0


@lru_cache(maxsize=64)
def _tables(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((len(OCTAVES), 256, 256))


OCTAVES = ((0.4, 1.0), (0.2, 0.6), (0.1, 0.4))  # (cell size m, amplitude)


def value_noise(u: np.ndarray, v: np.ndarray, seed: int, period_u: float) -> np.ndarray:
    """Sum of smoothstep-blended value-noise octaves (``OCTAVES``) in [0, 1]; periodic in ``u`` when asked
    (``period_u`` a multiple of every cell size)."""
    out = np.zeros_like(u)
    for table, (cell, amp) in zip(_tables(seed), OCTAVES):
        n = table.shape[0]
        x, y = u / cell, v / cell
        x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
        fx, fy = x - x0, y - y0
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
        wrap = max(int(round(period_u / cell)), 1) if period_u > 0 else n
        x1 = np.mod(x0 + 1, wrap)
        x0 = np.mod(x0, wrap)
        y0 = np.mod(y0, n)
        y1 = np.mod(y0 + 1, n)
        out += amp * (table[x0, y0] * (1 - fx) * (1 - fy) + table[x1, y0] * fx * (1 - fy)
                      + table[x0, y1] * (1 - fx) * fy + table[x1, y1] * fx * fy)
    return out / sum(a for _, a in OCTAVES)


def cast(planes: list[Plane], T_WC: torch.Tensor, uv: np.ndarray, intr: Intrinsics,
         shade: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Depth (N,) (m, inf where nothing is hit) and grey value (N,) in [0, 1] of pixels (N, 2)."""
    T = T_WC.numpy()
    rays = np.stack(((uv[:, 0] - intr.cx) / intr.fx, (uv[:, 1] - intr.cy) / intr.fy, np.ones(len(uv))), -1)
    d, o = rays @ T[:3, :3].T, T[:3, 3]
    best = np.full(len(uv), np.inf)
    value = np.zeros(len(uv))
    for p in planes:
        n = np.cross(p.e1, p.e2)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p.origin - o) @ n) / (d @ n)
            x = o + t[:, None] * d - p.origin
            a, b = x @ p.e1, x @ p.e2
        hit = (t > 1e-6) & (a >= 0) & (a <= p.width) & (b >= 0) & (b <= p.height) & (t < best)
        best = np.where(hit, t, best)
        if shade and hit.any():
            value[hit] = value_noise(a[hit], b[hit], p.seed, p.period_u)
    return best, value


def render(planes: list[Plane], T_WC: torch.Tensor, intr: Intrinsics, width: int, height: int,
           supersample: int = 1) -> np.ndarray:
    """Grey image (H, W) uint8 of the planes, ``supersample^2`` rays per pixel."""
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    img = np.zeros(height * width)
    for oy in off:
        for ox in off:
            img += cast(planes, T_WC, np.stack((uu.ravel() + ox, vv.ravel() + oy), -1), intr)[1]
    return np.clip(img.reshape(height, width) / (s * s) * 255.0, 0, 255).astype(np.uint8)


def room(size: float = 8.0, h: float = 3.0, seed: int = 0) -> list[Plane]:
    """A closed square room ``[-size/2, size/2]^2 x [0, h]``, each of its six faces with its own texture."""
    a = size / 2
    e = np.eye(3)
    return [
        Plane(np.array([-a, -a, 0.0]), e[0], e[1], size, size, seed + 1),             # floor
        Plane(np.array([-a, -a, h]), e[0], e[1], size, size, seed + 2),               # ceiling
        Plane(np.array([-a, a, 0.0]), e[0], e[2], size, h, seed + 3),                 # wall y = +a
        Plane(np.array([-a, -a, 0.0]), e[0], e[2], size, h, seed + 4),                # wall y = -a
        Plane(np.array([a, -a, 0.0]), e[1], e[2], size, h, seed + 5),                 # wall x = +a
        Plane(np.array([-a, -a, 0.0]), e[1], e[2], size, h, seed + 6),                # wall x = -a
    ]


def look(yaw: float, position: np.ndarray, pitch: float = 0.0) -> torch.Tensor:
    """``T_WC`` of a camera (x right, y down, z forward) at ``position`` looking horizontally along ``yaw``
    (rad, from the world x axis, z up), pitched down by ``pitch`` (rad)."""
    fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), -math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, fwd, position
    return torch.from_numpy(T)


def drifted_chain(truth: torch.Tensor, rot_per_step: float, log_scale_per_step: float, trans_noise: float,
                  seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Odometry with drift: ``S_k = S_{k-1} Z_k Exp(n_k)`` with ``Z_k`` the true relative poses (N, 4, 4) and
    ``n_k`` a constant yaw (about the camera's y axis) and log-scale drift plus translation noise. Returns the
    rigid estimated poses ``T_WC`` (N, 4, 4) and each keyframe's depth scale ``sigma_k`` (N,) (estimated depth =
    ``sigma_k`` x true depth)."""
    n = truth.shape[0]
    gen = torch.Generator().manual_seed(seed)
    S = [truth[0].clone()]
    for k in range(1, n):
        z = torch.linalg.inv(truth[k - 1]) @ truth[k]
        noise = torch.zeros(7, dtype=D)
        noise[:3] = trans_noise * torch.randn(3, generator=gen, dtype=D)
        noise[4] = rot_per_step
        noise[6] = log_scale_per_step
        S.append(S[-1] @ z @ sim3_exp(noise))
    S = torch.stack(S)
    sigma = torch.linalg.det(S[:, :3, :3]) ** (1.0 / 3.0)
    rigid = S.clone()
    rigid[:, :3, :3] = S[:, :3, :3] / sigma[:, None, None]
    return rigid, sigma


def circle_pose(k: int, step_deg: float = 6.0, radius: float = 1.0) -> torch.Tensor:
    """``T_WC`` of keyframe ``k`` on a circle of ``radius`` (m) at 1.5 m height in :func:`room`, looking outwards,
    ``step_deg`` apart (keyframe ``360 / step_deg`` is back at keyframe 0)."""
    a = math.radians(step_deg * k)
    return look(a, np.array([radius * math.cos(a), radius * math.sin(a), 1.5]))


@lru_cache(maxsize=2)
def circle_sequence(n: int, width: int, height: int, fx: float, stride: int) -> tuple[torch.Tensor, list, list]:
    """Ground-truth poses (n, 4, 4), grey images and reduced-grid depths (P,) (m) of :func:`circle_pose`
    keyframes in :func:`room` for a ``width x height`` pinhole camera with focal ``fx`` (rendered once per
    process)."""
    intr = Intrinsics(fx, fx, (width - 1) / 2, (height - 1) / 2)
    planes = room()
    truth = torch.stack([circle_pose(k) for k in range(n)])
    s = stride
    uu, vv = np.meshgrid(s * np.arange(width // s) + (s - 1) / 2, s * np.arange(height // s) + (s - 1) / 2)
    coords = np.stack((uu.ravel(), vv.ravel()), -1)
    images = [render(planes, truth[k], intr, width, height) for k in range(n)]
    depths = [torch.from_numpy(cast(planes, truth[k], coords, intr, shade=False)[0]) for k in range(n)]
    return truth, images, depths
