"""Sim(3) as homogeneous 4x4 matrices ``[[s R, t]; [0, 1]]``, tangent ``(rho, phi, sigma)``.

``xi^ = [[[phi]x + sigma I, rho]; [0, 0]]`` and ``Exp(xi) = expm(xi^)`` gives ``s = e^sigma``,
``R = Exp(phi)``, ``t = W rho`` with ``W = int_0^1 e^{sigma u} Exp(u phi) du`` (Eade, "Lie groups
for computer vision", Sec. 6). ``W`` is evaluated exactly as the top-right block of
``expm([[[phi]x + sigma I, I]; [0, 0]])`` (Van Loan), avoiding the many special cases of its
closed form. Adjoint for the (rho, phi, sigma) ordering:
``Ad_S = [[s R, [t]x R, -t]; [0, R, 0]; [0, 0, 1]]``.
"""
from __future__ import annotations

import torch

from vigs_core.geometry.se3 import series_left_jacobian, series_left_jacobian_inv
from vigs_core.geometry.so3 import hat, so3_exp, so3_log


def sim3_from_srt(scale: torch.Tensor, rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Assemble (..., 4, 4) from scales (...), rotations (..., 3, 3) and translations (..., 3)."""
    out = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    out[..., :3, :3] = scale[..., None, None] * rot
    out[..., :3, 3] = trans
    out[..., 3, 3] = 1.0
    return out


def sim3_scale(s: torch.Tensor) -> torch.Tensor:
    """Scale factor (...) of a similarity: the cube root of ``det(s R)``."""
    return torch.linalg.det(s[..., :3, :3]).clamp_min(1e-300) ** (1.0 / 3.0)


def sim3_hat(xi: torch.Tensor) -> torch.Tensor:
    """Lie-algebra matrix (..., 4, 4) of (..., 7)."""
    out = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    out[..., :3, :3] = hat(xi[..., 3:6]) + xi[..., 6, None, None] * eye
    out[..., :3, 3] = xi[..., :3]
    return out


def _w_matrix(phi: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """``W = int_0^1 exp(u ([phi]x + sigma I)) du`` (..., 3, 3)."""
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
    return series_left_jacobian(hat(phi) + sigma[..., None, None] * eye)


def sim3_exp(xi: torch.Tensor) -> torch.Tensor:
    """``Exp(xi)`` (..., 7) -> (..., 4, 4)."""
    phi, sigma = xi[..., 3:6], xi[..., 6]
    trans = (_w_matrix(phi, sigma) @ xi[..., :3, None])[..., 0]
    return sim3_from_srt(torch.exp(sigma), so3_exp(phi), trans)


def sim3_log(s: torch.Tensor) -> torch.Tensor:
    """``Log(S)`` (..., 4, 4) -> (..., 7): ``sigma = log s``, ``phi = Log(R)``, ``rho = W^{-1} t``."""
    scale = sim3_scale(s)
    phi = so3_log(s[..., :3, :3] / scale[..., None, None])
    sigma = torch.log(scale)
    rho = torch.linalg.solve(_w_matrix(phi, sigma), s[..., :3, 3:4])[..., 0]
    return torch.cat((rho, phi, sigma[..., None]), -1)


def sim3_inverse(s: torch.Tensor) -> torch.Tensor:
    """Inverse ``[[R^T / s, -R^T t / s]; [0, 1]]``."""
    scale = sim3_scale(s)
    inv_lin = s[..., :3, :3].transpose(-1, -2) / (scale**2)[..., None, None]
    out = torch.zeros_like(s)
    out[..., :3, :3] = inv_lin
    out[..., :3, 3] = -(inv_lin @ s[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def sim3_compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Composition ``a b``."""
    return a @ b


def sim3_act(s: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply similarities (..., 4, 4) to points (..., N, 3): ``s R p + t``."""
    return points @ s[..., :3, :3].transpose(-1, -2) + s[..., None, :3, 3]


def sim3_adjoint(s: torch.Tensor) -> torch.Tensor:
    """Adjoint (..., 7, 7) so that ``S Exp(xi) S^{-1} = Exp(Ad_S xi)``."""
    scale = sim3_scale(s)
    rot = s[..., :3, :3] / scale[..., None, None]
    trans = s[..., :3, 3]
    out = torch.zeros(*s.shape[:-2], 7, 7, dtype=s.dtype, device=s.device)
    out[..., :3, :3] = scale[..., None, None] * rot
    out[..., :3, 3:6] = hat(trans) @ rot
    out[..., :3, 6] = -trans
    out[..., 3:6, 3:6] = rot
    out[..., 6, 6] = 1.0
    return out


def sim3_ad(xi: torch.Tensor) -> torch.Tensor:
    """Small adjoint (..., 7, 7): ``ad_xi = [[[phi]x + sigma I, [rho]x, -rho]; [0, [phi]x, 0]; 0]``."""
    rho, phi, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6]
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    out = torch.zeros(*xi.shape[:-1], 7, 7, dtype=xi.dtype, device=xi.device)
    out[..., :3, :3] = hat(phi) + sigma[..., None, None] * eye
    out[..., :3, 3:6] = hat(rho)
    out[..., :3, 6] = -rho
    out[..., 3:6, 3:6] = hat(phi)
    return out


def sim3_left_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian (..., 7, 7): ``Exp(xi + d) ~= Exp(J_l(xi) d) Exp(xi)``."""
    return series_left_jacobian(sim3_ad(xi))


def sim3_right_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """Right Jacobian ``J_r(xi) = J_l(-xi)``."""
    return series_left_jacobian(sim3_ad(-xi))


def sim3_left_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`sim3_left_jacobian`."""
    return series_left_jacobian_inv(sim3_ad(xi))


def sim3_right_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`sim3_right_jacobian`."""
    return series_left_jacobian_inv(sim3_ad(-xi))
