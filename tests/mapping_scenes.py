"""Analytic scenes for the mapping tests: textured planes ray-cast exactly (colour and depth per pixel)."""
from __future__ import annotations

import math

import torch

from vigs_core.geometry import se3_from_rt, so3_exp


def texture(points: torch.Tensor) -> torch.Tensor:
    """(..., 3) RGB in [0, 1] of a smooth procedural texture at world points (..., 3)."""
    x, y, z = points.unbind(-1)
    r = 0.5 + 0.35 * torch.sin(3.1 * x + 1.3 * y) * torch.cos(2.3 * z - 0.7 * y)
    g = 0.5 + 0.3 * torch.sin(2.2 * y - 1.7 * z + 0.4) + 0.1 * torch.cos(5.0 * x)
    b = 0.5 + 0.3 * torch.cos(2.7 * z + 1.9 * x) * torch.sin(1.1 * y + 0.3)
    return torch.stack((r, g, b), -1).clamp(0, 1)


# Planes n . p = d (unit normal n): a floor and three walls of a room around the origin.
PLANES = ((0.0, 0.0, 1.0, -1.2), (0.0, -1.0, 0.0, -3.0), (1.0, 0.0, 0.0, -3.0), (-1.0, 0.0, 0.0, -3.0))


def raycast(T_WC: torch.Tensor, camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact ``(image (H, W, 3), depth (H, W))`` (depth = camera z, metres) of the plane room."""
    dt = torch.float64
    v, u = torch.meshgrid(
        torch.arange(camera.height, dtype=dt), torch.arange(camera.width, dtype=dt), indexing="ij"
    )
    rays_c = torch.stack(((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, torch.ones_like(u)), -1)
    T = T_WC.to(dt)
    rays_w = rays_c @ T[:3, :3].T
    origin = T[:3, 3]
    best = torch.full(u.shape, math.inf, dtype=dt)
    for nx, ny, nz, d in PLANES:
        n = torch.tensor((nx, ny, nz), dtype=dt)
        denom = rays_w @ n
        lam = (d - origin @ n) / denom  # camera depth along the z=1 ray
        lam = torch.where((denom.abs() > 1e-9) & (lam > 0), lam, torch.full_like(lam, math.inf))
        best = torch.minimum(best, lam)
    points = origin + best[..., None] * rays_w
    return texture(points).float(), best.float()


def orbit_pose(angle: float, radius: float = 0.6, height: float = 0.1) -> torch.Tensor:
    """(4, 4) T_WC of a camera on a small circle, looking roughly along +y (camera z) with image y down."""
    base = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    yaw = so3_exp(torch.tensor([0.0, 0.0, 0.35 * math.sin(angle)], dtype=torch.float64))
    R = yaw @ base
    p = torch.tensor([radius * math.cos(angle), radius * math.sin(angle) - 1.0, height], dtype=torch.float64)
    return se3_from_rt(R, p)
