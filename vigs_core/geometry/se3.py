"""SE(3) as homogeneous 4x4 matrices, tangent ``xi = (rho, phi)`` (translation first).

``xi^ = [[phi]x, rho; 0, 0]``, ``Exp(xi) = expm(xi^) = [[Exp(phi), J_l(phi) rho]; [0, 1]]``
(Barfoot 2017, Eq. 7.83-7.85). Adjoint ``Ad_T = [[R, [t]x R]; [0, R]]`` so that
``T Exp(xi) T^{-1} = Exp(Ad_T xi)``.

The group Jacobians use the series ``J_l(xi) = sum_n ad_xi^n / (n+1)!``, evaluated exactly as the
top-right block of ``expm([[ad_xi, I]; [0, 0]])`` (Van Loan's block formula). This has no
small-angle special cases and is differentiable. Their inverses, which pose graphs and priors evaluate at every
iteration for small residuals, use the Bernoulli series ``J_l^{-1} = sum_n B_n ad^n / n!`` where it converges
fast (:func:`series_left_jacobian_inv`).
"""
from __future__ import annotations

import torch

from vigs_core.geometry.so3 import exp_and_left_jacobian, hat, so3_left_jacobian_inv, so3_log


def se3_from_rt(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Assemble (..., 4, 4) transforms from rotations (..., 3, 3) and translations (..., 3)."""
    out = torch.zeros(*rot.shape[:-2], 4, 4, dtype=rot.dtype, device=rot.device)
    out[..., :3, :3] = rot
    out[..., :3, 3] = trans
    out[..., 3, 3] = 1.0
    return out


def se3_rotation(t: torch.Tensor) -> torch.Tensor:
    """Rotation block (..., 3, 3) of a transform."""
    return t[..., :3, :3]


def se3_translation(t: torch.Tensor) -> torch.Tensor:
    """Translation (..., 3) of a transform."""
    return t[..., :3, 3]


def se3_hat(xi: torch.Tensor) -> torch.Tensor:
    """Lie-algebra matrix (..., 4, 4) of a twist (..., 6)."""
    out = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    out[..., :3, :3] = hat(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """``Exp(xi)`` for twists (..., 6) -> (..., 4, 4): ``R = Exp(phi)``, ``t = J_l(phi) rho``."""
    rot, left_jacobian = exp_and_left_jacobian(xi[..., 3:])
    return se3_from_rt(rot, (left_jacobian @ xi[..., :3, None])[..., 0])


def se3_log(t: torch.Tensor) -> torch.Tensor:
    """``Log(T)`` (..., 4, 4) -> (..., 6): ``phi = Log(R)``, ``rho = J_l(phi)^{-1} t``."""
    phi = so3_log(t[..., :3, :3])
    rho = (so3_left_jacobian_inv(phi) @ t[..., :3, 3:4])[..., 0]
    return torch.cat((rho, phi), -1)


def se3_inverse(t: torch.Tensor) -> torch.Tensor:
    """Inverse transform ``[[R^T, -R^T t]; [0, 1]]``."""
    rt = t[..., :3, :3].transpose(-1, -2)
    return se3_from_rt(rt, -(rt @ t[..., :3, 3:4])[..., 0])


def se3_compose(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Composition ``a b`` (broadcasting over leading dimensions)."""
    return a @ b


def se3_act(t: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply transforms (..., 4, 4) to points (..., N, 3) -> (..., N, 3): ``R p + t``."""
    return points @ t[..., :3, :3].transpose(-1, -2) + t[..., None, :3, 3]


def se3_adjoint(t: torch.Tensor) -> torch.Tensor:
    """Adjoint (..., 6, 6) ``[[R, [t]x R]; [0, R]]`` for the (rho, phi) ordering."""
    rot, trans = t[..., :3, :3], t[..., :3, 3]
    out = torch.zeros(*t.shape[:-2], 6, 6, dtype=t.dtype, device=t.device)
    out[..., :3, :3] = rot
    out[..., 3:, 3:] = rot
    out[..., :3, 3:] = hat(trans) @ rot
    return out


def se3_ad(xi: torch.Tensor) -> torch.Tensor:
    """Small adjoint (..., 6, 6) ``ad_xi = [[[phi]x, [rho]x]; [0, [phi]x]]``."""
    out = torch.zeros(*xi.shape[:-1], 6, 6, dtype=xi.dtype, device=xi.device)
    phi_x = hat(xi[..., 3:])
    out[..., :3, :3] = phi_x
    out[..., 3:, 3:] = phi_x
    out[..., :3, 3:] = hat(xi[..., :3])
    return out


def series_left_jacobian(ad: torch.Tensor) -> torch.Tensor:
    """``sum_n ad^n / (n+1)!`` for (..., n, n) ``ad`` via ``expm([[ad, I]; [0, 0]])`` (Van Loan)."""
    n = ad.shape[-1]
    block = torch.zeros(*ad.shape[:-2], 2 * n, 2 * n, dtype=ad.dtype, device=ad.device)
    block[..., :n, :n] = ad
    block[..., :n, n:] = torch.eye(n, dtype=ad.dtype, device=ad.device)
    return torch.linalg.matrix_exp(block)[..., :n, n:]


# B_n / n! of the Bernoulli numbers (B_1 = -1/2; odd ones beyond vanish): x / (e^x - 1) = sum_n B_n x^n / n!
_INV_SERIES_EVEN = (1.0 / 12.0, -1.0 / 720.0, 1.0 / 30240.0, -1.0 / 1209600.0, 1.0 / 47900160.0)
_INV_SERIES_RADIUS = 0.5   # ||ad||_F up to which the truncated series is used (next term below 2e-13)


def series_left_jacobian_inv(ad: torch.Tensor) -> torch.Tensor:
    """Inverse (..., n, n) of :func:`series_left_jacobian`: ``I - ad/2 + sum_k B_2k ad^2k / (2k)!`` up to ``ad^10``
    where ``||ad||_F <= 0.5`` (the omitted terms are below 2e-13 there: a handful of small matrix products instead
    of a matrix exponential of twice the size and an inverse), the exact inverse elsewhere."""
    n = ad.shape[-1]
    eye = torch.eye(n, dtype=ad.dtype, device=ad.device)
    ad2 = ad @ ad
    power, out = ad2, eye - 0.5 * ad
    for k, c in enumerate(_INV_SERIES_EVEN):
        out = out + c * power
        if k + 1 < len(_INV_SERIES_EVEN):
            power = power @ ad2
    far = torch.linalg.matrix_norm(ad) > _INV_SERIES_RADIUS
    if bool(far.any()):
        out[far] = torch.linalg.inv(series_left_jacobian(ad[far]))
    return out


def se3_left_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """Left Jacobian (..., 6, 6): ``Exp(xi + d) ~= Exp(J_l(xi) d) Exp(xi)``."""
    return series_left_jacobian(se3_ad(xi))


def se3_right_jacobian(xi: torch.Tensor) -> torch.Tensor:
    """Right Jacobian ``J_r(xi) = J_l(-xi)``: ``Exp(xi + d) ~= Exp(xi) Exp(J_r(xi) d)``."""
    return series_left_jacobian(se3_ad(-xi))


def se3_left_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`se3_left_jacobian`."""
    return series_left_jacobian_inv(se3_ad(xi))


def se3_right_jacobian_inv(xi: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`se3_right_jacobian`."""
    return series_left_jacobian_inv(se3_ad(-xi))
