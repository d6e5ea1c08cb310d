"""Lens distortion on the normalized image plane, batched over leading dimensions.

All functions act on normalized coordinates ``xy = (X/Z, Y/Z)`` (..., 2), before the intrinsics
``u = fx * x_d + cx``, ``v = fy * y_d + cy`` are applied. They work for float32 and float64 on any
device and are differentiable with autograd (the inverses are unrolled iterations).

Radial-tangential ("radtan", Brown-Conrady; the model of OpenCV ``projectPoints`` and of EuRoC's
``sensor.yaml``), coefficients ``(k1, k2, p1, p2[, k3])``::

    r^2 = x^2 + y^2,   a = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x_d = a x + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = a y + p1 (r^2 + 2 y^2) + 2 p2 x y

Equidistant ("equidistant", the Kannala-Brandt fisheye model of Kalibr's ``pinhole-equi`` and of
OpenCV's ``cv2.fisheye``; Kannala & Brandt, T-PAMI 2006, Eq. (6)), coefficients ``(k1, k2, k3, k4)``::

    r = |xy|,   theta = atan(r),   theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    xy_d = (theta_d / r) xy

The inverses solve ``distort(xy) = xy_d`` for ``xy``: Newton's method on the 2x2 system for radtan
(starting from ``xy = xy_d``) and on the scalar ``theta_d(theta)`` for equidistant. Iteration stops
when the largest residual is below ``tol`` (normalized units) or after ``max_iters`` steps.
Inputs outside the region where the forward model is monotonic (far outside a real lens's field of
view) have no unique inverse; the iteration then returns its last iterate.
"""
from __future__ import annotations

from typing import Sequence

import torch

DISTORTION_COEFF_COUNTS: dict[str, tuple[int, ...]] = {
    "none": (0,),
    "radtan": (4, 5),
    "equidistant": (4,),
}
"""Allowed number of coefficients for each distortion model."""

# Largest theta (rad) the equidistant inverse may return: rays with z = 1 need theta < pi / 2.
_MAX_THETA = 0.5 * torch.pi - 1e-6


def _small_threshold(dtype: torch.dtype) -> float:
    """``r^2`` below which Taylor series replace ratios like ``theta_d / r`` (accurate to eps)."""
    return torch.finfo(dtype).eps ** 0.5


def radtan_distort(xy: torch.Tensor, coeffs: Sequence[float]) -> torch.Tensor:
    """Apply radial-tangential distortion: undistorted ``xy`` (..., 2) -> distorted ``xy_d`` (..., 2)."""
    k1, k2, p1, p2 = coeffs[:4]
    k3 = coeffs[4] if len(coeffs) > 4 else 0.0
    x, y = xy.unbind(-1)
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = a * x + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = a * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return torch.stack((xd, yd), -1)


def _radtan_jacobian_entries(
    xy: torch.Tensor, coeffs: Sequence[float]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Entries ``(J00, J01 = J10, J11)`` (...,) of the symmetric radtan Jacobian, see :func:`radtan_jacobian`."""
    k1, k2, p1, p2 = coeffs[:4]
    k3 = coeffs[4] if len(coeffs) > 4 else 0.0
    x, y = xy.unbind(-1)
    r2 = x * x + y * y
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    off = 2.0 * da * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    j00 = a + 2.0 * da * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    j11 = a + 2.0 * da * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return j00, off, j11


def radtan_jacobian(xy: torch.Tensor, coeffs: Sequence[float]) -> torch.Tensor:
    """Jacobian ``d xy_d / d xy`` (..., 2, 2) of :func:`radtan_distort` at ``xy`` (..., 2).

    With ``a' = d a / d r^2 = k1 + 2 k2 r^2 + 3 k3 r^4``::

        dx_d/dx = a + 2 a' x^2 + 2 p1 y + 6 p2 x      dx_d/dy = 2 a' x y + 2 p1 x + 2 p2 y
        dy_d/dx = 2 a' x y + 2 p1 x + 2 p2 y          dy_d/dy = a + 2 a' y^2 + 6 p1 y + 2 p2 x
    """
    j00, off, j11 = _radtan_jacobian_entries(xy, coeffs)
    return torch.stack((torch.stack((j00, off), -1), torch.stack((off, j11), -1)), -2)


def radtan_undistort(
    xy_d: torch.Tensor, coeffs: Sequence[float], tol: float = 1e-12, max_iters: int = 30
) -> torch.Tensor:
    """Invert :func:`radtan_distort` by Newton's method: distorted ``xy_d`` (..., 2) -> ``xy`` (..., 2).

    Each step solves the symmetric 2x2 system ``J(xy) delta = xy_d - distort(xy)`` in closed form
    (Cramer's rule); convergence is quadratic, 4-5 steps reach float64 precision for EuRoC's lens.
    """
    xy = xy_d.clone()
    for _ in range(max_iters):
        residual = xy_d - radtan_distort(xy, coeffs)
        if residual.numel() == 0 or residual.detach().abs().max() <= tol:
            break
        j00, off, j11 = _radtan_jacobian_entries(xy, coeffs)
        det = j00 * j11 - off * off
        rx, ry = residual.unbind(-1)
        xy = xy + torch.stack(((j11 * rx - off * ry) / det, (j00 * ry - off * rx) / det), -1)
    return xy


def _theta_polynomial(theta: torch.Tensor, coeffs: Sequence[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """``theta_d(theta)`` and its derivative ``d theta_d / d theta`` for the equidistant model."""
    k1, k2, k3, k4 = coeffs
    t2 = theta * theta
    poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    return theta * poly, dpoly


def equidistant_distort(xy: torch.Tensor, coeffs: Sequence[float]) -> torch.Tensor:
    """Apply equidistant (Kannala-Brandt) distortion: ``xy`` (..., 2) -> ``xy_d`` (..., 2).

    Near the optical axis ``theta_d / r = 1 + (k1 - 1/3) r^2 + O(r^4)`` replaces the ratio, so values
    and gradients stay finite at ``r = 0``.
    """
    r2 = (xy * xy).sum(-1)
    small = r2 < _small_threshold(xy.dtype)
    r_safe = torch.where(small, torch.ones_like(r2), r2).sqrt()
    theta_d, _ = _theta_polynomial(torch.atan(r_safe), coeffs)
    scale = torch.where(small, 1.0 + (coeffs[0] - 1.0 / 3.0) * r2, theta_d / r_safe)
    return xy * scale.unsqueeze(-1)


def equidistant_undistort(
    xy_d: torch.Tensor, coeffs: Sequence[float], tol: float = 1e-12, max_iters: int = 30
) -> torch.Tensor:
    """Invert :func:`equidistant_distort`: ``xy_d`` (..., 2) -> ``xy`` (..., 2).

    Newton's method on ``theta_d(theta) = |xy_d|`` from ``theta = |xy_d|``, with ``theta`` kept in
    ``[0, pi/2)``; then ``xy = (tan(theta) / theta_d) xy_d``. Near the axis the ratio uses its series
    ``1 + (1/3 - k1) theta_d^2``.
    """
    r2 = (xy_d * xy_d).sum(-1)
    small = r2 < _small_threshold(xy_d.dtype)
    theta_d = torch.where(small, torch.ones_like(r2), r2).sqrt()
    theta = theta_d.clamp(max=_MAX_THETA)
    for _ in range(max_iters):
        value, slope = _theta_polynomial(theta, coeffs)
        residual = theta_d - value
        if residual.numel() == 0 or residual.detach().abs().max() <= tol:
            break
        theta = (theta + residual / slope).clamp(0.0, _MAX_THETA)
    scale = torch.where(small, 1.0 + (1.0 / 3.0 - coeffs[0]) * r2, torch.tan(theta) / theta_d)
    return xy_d * scale.unsqueeze(-1)


def distort(kind: str, xy: torch.Tensor, coeffs: Sequence[float]) -> torch.Tensor:
    """Apply distortion model ``kind`` ("none" | "radtan" | "equidistant") to ``xy`` (..., 2)."""
    if kind == "none":
        return xy
    if kind == "radtan":
        return radtan_distort(xy, coeffs)
    if kind == "equidistant":
        return equidistant_distort(xy, coeffs)
    raise ValueError(f"unknown distortion model {kind!r}; expected one of {sorted(DISTORTION_COEFF_COUNTS)}")


def undistort(
    kind: str, xy_d: torch.Tensor, coeffs: Sequence[float], tol: float = 1e-12, max_iters: int = 30
) -> torch.Tensor:
    """Invert distortion model ``kind`` for ``xy_d`` (..., 2); ``tol`` in normalized units."""
    if kind == "none":
        return xy_d
    if kind == "radtan":
        return radtan_undistort(xy_d, coeffs, tol, max_iters)
    if kind == "equidistant":
        return equidistant_undistort(xy_d, coeffs, tol, max_iters)
    raise ValueError(f"unknown distortion model {kind!r}; expected one of {sorted(DISTORTION_COEFF_COUNTS)}")
