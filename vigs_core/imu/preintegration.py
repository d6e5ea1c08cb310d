"""On-manifold IMU preintegration (Forster et al., "On-Manifold Preintegration for Real-Time
Visual-Inertial Odometry", T-RO 2017), vectorised over the samples, float64 torch.

Preintegrated deltas between stamps ``t_i`` and ``t_j`` with the bias held at ``b = (b_g, b_a)``,
for the piecewise-constant measurement sequence ``(dt_k, w_k, a_k)``, ``k = 0..K-1`` (see
:mod:`vigs_core.imu.samples`), with ``dR_k`` the rotation at the start of interval ``k``::

    dR_{k+1} = dR_k Exp((w_k - b_g) dt_k)
    dv_{k+1} = dv_k + dR_k G1_k (a_k - b_a) dt_k
    dp_{k+1} = dp_k + dv_k dt_k + dR_k G2_k (a_k - b_a) dt_k^2

``scheme="forster"``: ``G1 = I``, ``G2 = I/2`` (Forster Eq. 35-37, identical to GTSAM's
``ManifoldPreintegration``). ``scheme="closed_form"`` (default): the exact integrals for constant
body rates within the interval, ``G1 = J_l(phi)``, ``G2 = sum_n [phi]x^n / (n+2)!`` with
``phi = (w_k - b_g) dt_k``; together with the mean-value measurements this makes the integration
error second order in the sample period (the Forster scheme is first order: it uses the
start-of-interval attitude for the whole interval).

Errors (Forster Eq. 38-44): ``dR_meas = dR Exp(d_phi)``, ``dv_meas = dv + d_v``, ``dp_meas = dp + d_p``,
all in the frame of ``t_i``. Every output is a sum over the intervals, so its derivative with respect
to each measurement has a closed form (``T_k`` the time from ``t_i`` to grid point ``k``)::

    d phi_K / d w_m = dR_K^T dR_{m+1} J_r(phi_m) dt_m
    d v_K   / d w_m = -[v_K - v_{m+1}]x dR_{m+1} J_r(phi_m) dt_m               (+ in-interval term)
    d p_K   / d w_m = -[p_K - p_{m+1} - v_{m+1} (T_K - T_{m+1})]x dR_{m+1} J_r dt_m (+ in-interval term)
    d v_K   / d a_m = dR_m G1_m dt_m
    d p_K   / d a_m = dR_m (G1_m dt_m (T_K - T_{m+1}) + G2_m dt_m^2)

(in-interval terms, closed form only, to first order in ``phi_m``: ``-1/2 dR_m [a_m]x dt_m^2`` for
``v`` and ``-dR_m [a_m]x (dt_m^2 (T_K - T_{m+1}) / 2 + dt_m^3 / 6)`` for ``p``). The covariance follows
from white measurement noise with the continuous densities of the IMU YAML, discretised per interval
as ``sigma^2 / dt_k`` (Forster Eq. 47; the variance of the mean of white noise over ``dt_k``)::

    Cov = sum_m  sigma_g^2 / dt_m  D_w,m D_w,m^T  +  sigma_a^2 / dt_m  D_a,m D_a,m^T

and the bias Jacobians are ``d(.)/d b_g = -sum_m d(.)/d w_m``, ``d(.)/d b_a = -sum_m d(.)/d a_m``
(identical to Forster's recursions, Eq. 69-70). The 15x15 covariance appends the bias random walk
over the interval, ``sigma_bg^2 T`` and ``sigma_ba^2 T``, as independent blocks (order
``(phi, v, p, b_g, b_a)``).

The only sequential step, the running product of rotations, is a parallel prefix product
(``ceil(log2 K)`` batched 3x3 matrix products), so Python overhead does not grow with K.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.geometry import hat, so3_exp
from vigs_core.geometry.so3 import rodrigues_coefficients
from vigs_core.imu.samples import interval_measurements
from vigs_core.types import ImuNoise, ImuSamples

SCHEMES = ("closed_form", "forster")
_SMALL_ANGLE = 1e-4


@dataclass
class Preintegrated:
    """Preintegrated IMU measurements between ``t_i`` and ``t_j``; tensors may carry a batch dim ``B``.

    Attributes:
        t0_ns, t1_ns: () or (B,) int64 numpy stamps of the interval.
        dt: () or (B,) float64 tensor, ``t_j - t_i`` (s).
        delta_R: (..., 3, 3) ``dR_ij`` at the linearisation bias.
        delta_v: (..., 3) ``dv_ij`` (m/s), frame ``i``.
        delta_p: (..., 3) ``dp_ij`` (m), frame ``i``.
        cov: (..., 15, 15) covariance of ``(d_phi, d_v, d_p, b_g random walk, b_a random walk)``.
        J_R_bg, J_v_bg, J_v_ba, J_p_bg, J_p_ba: (..., 3, 3) bias Jacobians of the deltas
            (``J_R_bg`` maps a gyro-bias change to a right rotation increment).
        bias_gyro, bias_acc: (..., 3) linearisation biases (rad/s, m/s^2).
    """

    t0_ns: np.ndarray
    t1_ns: np.ndarray
    dt: torch.Tensor
    delta_R: torch.Tensor
    delta_v: torch.Tensor
    delta_p: torch.Tensor
    cov: torch.Tensor
    J_R_bg: torch.Tensor
    J_v_bg: torch.Tensor
    J_v_ba: torch.Tensor
    J_p_bg: torch.Tensor
    J_p_ba: torch.Tensor
    bias_gyro: torch.Tensor
    bias_acc: torch.Tensor

    def corrected(
        self, bias_gyro: torch.Tensor, bias_acc: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """First-order bias update without re-integration (Forster Eq. 44).

        ``dR(b) = dR Exp(J_R_bg db_g)``, ``dv(b) = dv + J_v_bg db_g + J_v_ba db_a``, same for ``dp``,
        with ``db = b - b_lin``. Shapes: biases (..., 3) -> ((..., 3, 3), (..., 3), (..., 3)).
        """
        dbg = bias_gyro - self.bias_gyro
        dba = bias_acc - self.bias_acc
        mv = lambda m, x: (m @ x[..., None])[..., 0]  # noqa: E731
        dR = self.delta_R @ so3_exp(mv(self.J_R_bg, dbg))
        dv = self.delta_v + mv(self.J_v_bg, dbg) + mv(self.J_v_ba, dba)
        dp = self.delta_p + mv(self.J_p_bg, dbg) + mv(self.J_p_ba, dba)
        return dR, dv, dp

    def item(self, k: int) -> "Preintegrated":
        """Element ``k`` of a batched :class:`Preintegrated`."""
        return Preintegrated(**{
            name: (value[k] if name not in ("t0_ns", "t1_ns") else np.int64(value[k]))
            for name, value in vars(self).items()
        })


@dataclass
class IntegratedPath:
    """Every grid point of one integration: the deltas from the interval start to each grid stamp.

    Attributes:
        grid_ns: (K+1,) int64 grid stamps.
        R: (K+1, 3, 3), v: (K+1, 3), p: (K+1, 3) deltas at each grid stamp (frame of the first).
    """

    grid_ns: np.ndarray
    R: torch.Tensor
    v: torch.Tensor
    p: torch.Tensor


@dataclass
class _PieceMatrices:
    """The SO(3) matrices of the pieces' rotation vectors ``phi`` (K, 3), each (K, 3, 3), from one ``[phi]x``
    and one set of Rodrigues coefficients ``a = sin t / t``, ``b = (1 - cos t) / t^2``,
    ``c = (t - sin t) / t^3`` (``t = |phi|``; :mod:`vigs_core.geometry.so3`, Taylor near 0)::

        Exp(phi) = I + a [phi]x + b [phi]x^2
        J_r(phi) = I - b [phi]x + c [phi]x^2,   J_l(phi) = J_r(-phi) = I + b [phi]x + c [phi]x^2
        G2(phi)  = sum_n [phi]x^n / (n+2)! = I/2 + c [phi]x + d [phi]x^2,   d = (t^2/2 + cos t - 1) / t^4

    (``G2`` is the double integral of ``Exp(s phi)``; ``J_l`` and ``G2`` only for the closed-form scheme.)
    """

    exp: torch.Tensor
    right_jacobian: torch.Tensor
    left_jacobian: torch.Tensor | None
    gamma2: torch.Tensor | None

    @staticmethod
    def of(phi: torch.Tensor, scheme: str) -> "_PieceMatrices":
        a, b, c = (x[..., None, None] for x in rodrigues_coefficients(phi))
        k = hat(phi)
        kk = k @ k
        eye = torch.eye(3, dtype=phi.dtype, device=phi.device)
        exp, ck2 = eye + a * k + b * kk, c * kk
        right = eye - b * k + ck2
        if scheme != "closed_form":
            return _PieceMatrices(exp, right, None, None)
        t2 = (phi * phi).sum(-1)
        small = t2 < _SMALL_ANGLE**2
        t = torch.where(small, torch.ones_like(t2), t2).sqrt()
        d = torch.where(small, 1 / 24 - t2 / 720 + t2**2 / 40320, (0.5 * t**2 + torch.cos(t) - 1) / t**4)
        return _PieceMatrices(exp, right, eye + b * k + ck2, 0.5 * eye + c * k + d[..., None, None] * kk)


def segmented_cumulative_product(mats: torch.Tensor, segment: torch.Tensor) -> torch.Tensor:
    """Inclusive prefix products ``P_k = M_first ... M_k`` of (K, 3, 3) matrices, restarting at every
    segment (``segment`` (K,) non-decreasing ids); by doubling (Hillis-Steele), ``ceil(log2 K)`` steps."""
    out = mats.clone()
    step = 1
    while step < len(out):
        same = (segment[step:] == segment[:-step])[:, None, None]
        out[step:] = torch.where(same, out[:-step] @ out[step:], out[step:])
        step *= 2
    return out


def _segmented_cumsum(x: torch.Tensor, segment: torch.Tensor, first: torch.Tensor) -> torch.Tensor:
    """Inclusive cumulative sum along dim 0 restarting at each segment (``first`` (S,) start indices)."""
    c = torch.cumsum(x, 0)
    offset = c[first] - x[first]
    return c - offset[segment]


def _integrate(dt, w, a, segment, first, scheme: str):
    """Deltas before/after every piece for bias-corrected measurements dt (K,), w (K,3), a (K,3)."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown preintegration scheme '{scheme}'; expected one of {SCHEMES}")
    phi = w * dt[:, None]
    m = _PieceMatrices.of(phi, scheme)
    eye = torch.eye(3, dtype=dt.dtype, device=dt.device)
    R_after = segmented_cumulative_product(m.exp, segment)
    is_first = torch.zeros(len(dt), dtype=torch.bool, device=dt.device)
    is_first[first] = True
    R_before = torch.where(is_first[:, None, None], eye, torch.cat((eye[None], R_after[:-1])))
    if scheme == "forster":
        g1, g2, g1a, g2a = None, None, a, 0.5 * a
    else:
        g1, g2 = m.left_jacobian, m.gamma2
        g1a, g2a = (g1 @ a[..., None])[..., 0], (g2 @ a[..., None])[..., 0]
    du = (R_before @ g1a[..., None])[..., 0] * dt[:, None]  # velocity increments (K, 3)
    v_after = _segmented_cumsum(du, segment, first)
    v_before = v_after - du
    dq = v_before * dt[:, None] + (R_before @ g2a[..., None])[..., 0] * (dt * dt)[:, None]
    p_after = _segmented_cumsum(dq, segment, first)
    return R_before, R_after, v_after, p_after, m.right_jacobian, g1, g2


def integrate_path(
    dt: torch.Tensor, gyro: torch.Tensor, acc: torch.Tensor, bias_gyro: torch.Tensor, bias_acc: torch.Tensor,
    scheme: str = "closed_form",
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Deltas ``(R (K+1,3,3), v (K+1,3), p (K+1,3))`` at every grid point (no covariance, no Jacobians)."""
    segment = torch.zeros(len(dt), dtype=torch.long, device=dt.device)
    first = torch.zeros(1, dtype=torch.long, device=dt.device)
    _, R, v, p, *_ = _integrate(dt, gyro - bias_gyro, acc - bias_acc, segment, first, scheme)
    eye = torch.eye(3, dtype=dt.dtype, device=dt.device)
    zero = torch.zeros(1, 3, dtype=dt.dtype, device=dt.device)
    return torch.cat((eye[None], R)), torch.cat((zero, v)), torch.cat((zero, p))


def preintegrate_segments(
    dt: torch.Tensor,
    gyro: torch.Tensor,
    acc: torch.Tensor,
    segment: torch.Tensor,
    noise: ImuNoise,
    bias_gyro: torch.Tensor,
    bias_acc: torch.Tensor,
    scheme: str = "closed_form",
) -> Preintegrated:
    """Preintegrate S measurement sequences at once (see the module docstring for the maths).

    Args:
        dt: (K,) piece lengths (s), all positive.
        gyro: (K, 3) angular velocity (rad/s); acc: (K, 3) specific force (m/s^2).
        segment: (K,) int64 non-decreasing ids ``0..S-1``: which sequence each piece belongs to
            (every id present).
        noise: continuous noise densities (``ImuNoise``).
        bias_gyro, bias_acc: (S, 3) linearisation biases of each sequence.
        scheme: ``"closed_form"`` or ``"forster"`` (GTSAM ``ManifoldPreintegration``-identical).

    Returns:
        :class:`Preintegrated` with batch dimension S (stamps set to 0 and the total length in ns).
    """
    _check_pieces(dt, gyro, acc)
    f = dict(dtype=torch.float64, device=dt.device)
    n_seg = bias_gyro.shape[0]
    counts = torch.bincount(segment, minlength=n_seg)
    if len(counts) != n_seg or bool((counts == 0).any()) or bool((segment[1:] < segment[:-1]).any()):
        raise ValueError(f"segment ids must be non-decreasing and cover 0..{n_seg - 1}, each at least once")
    last = torch.cumsum(counts, 0) - 1
    first = last - counts + 1
    a = acc - bias_acc[segment]
    R_before, R_after, v_after, p_after, J_r, g1, g2 = _integrate(
        dt, gyro - bias_gyro[segment], a, segment, first, scheme)

    t_after = _segmented_cumsum(dt, segment, first)
    total = t_after[last]
    remain = total[segment] - t_after  # T_K - T_{m+1}, (K,)
    R_N, v_N, p_N = R_after[last], v_after[last], p_after[last]
    RJ = R_after @ J_r * dt[:, None, None]  # dR_{m+1} J_r(phi_m) dt_m
    s_v = v_N[segment] - v_after
    s_p = p_N[segment] - p_after - v_after * remain[:, None]
    hat_sv, hat_sp, hat_a = hat(torch.stack((s_v, s_p, a)))
    d_phi_w = R_N[segment].transpose(-1, -2) @ RJ
    d_v_w = -hat_sv @ RJ
    d_p_w = -hat_sp @ RJ
    if scheme == "closed_form":
        Ra = R_before @ hat_a
        d_v_w = d_v_w - 0.5 * Ra * (dt * dt)[:, None, None]
        d_p_w = d_p_w - Ra * (0.5 * dt * dt * remain + dt**3 / 6.0)[:, None, None]
        d_v_a = R_before @ g1 * dt[:, None, None]
        d_p_a = R_before @ (g1 * (dt * remain)[:, None, None] + g2 * (dt * dt)[:, None, None])
    else:
        d_v_a = R_before * dt[:, None, None]
        d_p_a = R_before * (dt * remain + 0.5 * dt * dt)[:, None, None]

    D_w = torch.cat((d_phi_w, d_v_w, d_p_w), dim=1)  # (K, 9, 3)
    D_a = torch.cat((torch.zeros_like(d_v_a), d_v_a, d_p_a), dim=1)
    inv_dt = (1.0 / dt)[:, None, None]
    piece_cov = noise.gyro_noise_density**2 * (D_w * inv_dt) @ D_w.transpose(-1, -2)
    piece_cov = piece_cov + noise.acc_noise_density**2 * (D_a * inv_dt) @ D_a.transpose(-1, -2)
    cov9 = torch.zeros(n_seg, 9, 9, **f).index_add_(0, segment, piece_cov)
    cov = torch.zeros(n_seg, 15, 15, **f)
    cov[:, :9, :9] = 0.5 * (cov9 + cov9.transpose(-1, -2))
    eye = torch.eye(3, **f)
    cov[:, 9:12, 9:12] = noise.gyro_random_walk**2 * total[:, None, None] * eye
    cov[:, 12:15, 12:15] = noise.acc_random_walk**2 * total[:, None, None] * eye

    # bias Jacobians: -sum over each segment's pieces, (S, 3, 3) each
    per_piece = torch.stack((d_phi_w, d_v_w, d_v_a, d_p_w, d_p_a), 1)
    J_R_bg, J_v_bg, J_v_ba, J_p_bg, J_p_ba = (
        -torch.zeros(n_seg, 5, 3, 3, **f).index_add_(0, segment, per_piece)).unbind(1)
    stamps = np.round(total.detach().cpu().numpy() * 1e9).astype(np.int64)
    return Preintegrated(
        t0_ns=np.zeros(n_seg, np.int64), t1_ns=stamps, dt=total,
        delta_R=R_N, delta_v=v_N, delta_p=p_N, cov=cov,
        J_R_bg=J_R_bg, J_v_bg=J_v_bg, J_v_ba=J_v_ba,
        J_p_bg=J_p_bg, J_p_ba=J_p_ba, bias_gyro=bias_gyro, bias_acc=bias_acc,
    )


def preintegrate_measurements(
    dt: torch.Tensor,
    gyro: torch.Tensor,
    acc: torch.Tensor,
    noise: ImuNoise,
    bias_gyro: torch.Tensor | None = None,
    bias_acc: torch.Tensor | None = None,
    scheme: str = "closed_form",
) -> Preintegrated:
    """Preintegrate one piecewise-constant measurement sequence (see the module docstring for the maths).

    Args:
        dt: (K,) piece lengths (s), all positive.
        gyro: (K, 3) angular velocity (rad/s); acc: (K, 3) specific force (m/s^2).
        noise: continuous noise densities (``ImuNoise``).
        bias_gyro, bias_acc: (3,) linearisation biases (default zero).
        scheme: ``"closed_form"`` or ``"forster"`` (GTSAM ``ManifoldPreintegration``-identical).
    """
    dt = torch.as_tensor(dt, dtype=torch.float64)
    dev = dt.device
    gyro = torch.as_tensor(gyro, dtype=torch.float64, device=dev).reshape(-1, 3)
    acc = torch.as_tensor(acc, dtype=torch.float64, device=dev).reshape(-1, 3)
    zeros = torch.zeros(3, dtype=torch.float64, device=dev)
    bg = zeros if bias_gyro is None else _as_f64(bias_gyro, dev)
    ba = zeros if bias_acc is None else _as_f64(bias_acc, dev)
    segment = torch.zeros(len(dt), dtype=torch.long, device=dev)
    batch = preintegrate_segments(dt, gyro, acc, segment, noise, bg[None], ba[None], scheme)
    return batch.item(0)


def _check_pieces(dt: torch.Tensor, gyro: torch.Tensor, acc: torch.Tensor) -> None:
    if not (len(dt) == len(gyro) == len(acc)) or len(dt) == 0:
        raise ValueError(f"need K >= 1 equal-length dt/gyro/acc, got {len(dt)}, {len(gyro)}, {len(acc)}")
    if bool((dt <= 0).any()):
        raise ValueError("preintegration needs positive piece lengths dt")


def _as_f64(x, device) -> torch.Tensor:
    """A float64 tensor on ``device`` from a tensor, array or sequence."""
    if isinstance(x, torch.Tensor):
        return x.to(dtype=torch.float64, device=device)
    return torch.as_tensor(np.asarray(x, dtype=np.float64), device=device)


def preintegrate(
    imu: ImuSamples,
    t0_ns: int,
    t1_ns: int,
    noise: ImuNoise,
    bias_gyro: torch.Tensor | np.ndarray | None = None,
    bias_acc: torch.Tensor | np.ndarray | None = None,
    scheme: str = "closed_form",
    device: torch.device | str = "cpu",
) -> Preintegrated:
    """Preintegrate the IMU from ``t0_ns`` to ``t1_ns`` exactly (boundary samples interpolated).

    Warns (:class:`~vigs_core.imu.samples.ImuDataWarning`) on gaps, out-of-order or duplicated
    samples around the interval. Biases are (3,) rad/s and m/s^2 (default zero).
    """
    return preintegrate_intervals(imu, np.array([t0_ns]), np.array([t1_ns]), noise, bias_gyro, bias_acc, scheme,
                                  device).item(0)


def preintegrate_rotation(
    imu: ImuSamples,
    t0_ns: int,
    t1_ns: int,
    bias_gyro: torch.Tensor | np.ndarray | None = None,
    rate_hz: float | None = None,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """The rotation ``dR_ij`` (3, 3) alone, ``prod_k Exp((w_k - b_g) dt_k)`` (the same for both schemes):
    the ``delta_R`` of :func:`preintegrate` without its velocity, position, covariance and Jacobians.
    ``rate_hz`` is the nominal rate of the gap warnings (``noise.rate_hz`` in :func:`preintegrate`)."""
    _, dt, gyro, _ = interval_measurements(imu, t0_ns, t1_ns, rate_hz=rate_hz)
    f64 = dict(dtype=torch.float64, device=device)
    bg = torch.zeros(3, **f64) if bias_gyro is None else _as_f64(bias_gyro, device)
    dt = torch.as_tensor(dt, **f64)
    phi = (torch.as_tensor(gyro, **f64) - bg) * dt[:, None]
    segment = torch.zeros(len(dt), dtype=torch.long, device=device)
    return segmented_cumulative_product(so3_exp(phi), segment)[-1]


def preintegrate_path(
    imu: ImuSamples,
    t0_ns: int,
    t1_ns: int,
    bias_gyro: torch.Tensor | np.ndarray | None = None,
    bias_acc: torch.Tensor | np.ndarray | None = None,
    scheme: str = "closed_form",
    rate_hz: float | None = None,
    device: torch.device | str = "cpu",
) -> IntegratedPath:
    """Deltas from ``t0_ns`` to every sample inside the interval and to ``t1_ns`` (for IMU-rate output)."""
    grid_ns, dt, gyro, acc = interval_measurements(imu, t0_ns, t1_ns, rate_hz=rate_hz)
    f64 = dict(dtype=torch.float64, device=device)
    bg = torch.zeros(3, **f64) if bias_gyro is None else _as_f64(bias_gyro, device)
    ba = torch.zeros(3, **f64) if bias_acc is None else _as_f64(bias_acc, device)
    R, v, p = integrate_path(
        torch.as_tensor(dt, **f64), torch.as_tensor(gyro, **f64), torch.as_tensor(acc, **f64), bg, ba, scheme
    )
    return IntegratedPath(grid_ns, R, v, p)


def stack_preintegrated(items: list[Preintegrated]) -> Preintegrated:
    """Stack single preintegrations into one batched :class:`Preintegrated` (leading dim ``B``)."""
    if not items:
        raise ValueError("stack_preintegrated needs at least one Preintegrated")
    fields = ("dt", "delta_R", "delta_v", "delta_p", "cov", "J_R_bg", "J_v_bg", "J_v_ba", "J_p_bg", "J_p_ba",
              "bias_gyro", "bias_acc")
    stacked = {f: torch.stack([getattr(x, f) for x in items]) for f in fields}
    return Preintegrated(
        t0_ns=np.array([x.t0_ns for x in items], dtype=np.int64),
        t1_ns=np.array([x.t1_ns for x in items], dtype=np.int64),
        **stacked,
    )


def preintegrate_between(
    imu: ImuSamples,
    stamps_ns: np.ndarray,
    noise: ImuNoise,
    bias_gyro: torch.Tensor | np.ndarray | None = None,
    bias_acc: torch.Tensor | np.ndarray | None = None,
    scheme: str = "closed_form",
    device: torch.device | str = "cpu",
) -> Preintegrated:
    """Batched preintegration between consecutive stamps (M,) -> ``Preintegrated`` with ``B = M - 1``,
    computed in one vectorised pass over all intervals.

    Biases may be (3,) (shared) or (M-1, 3) (one per interval, e.g. each interval's start keyframe).
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    if len(stamps_ns) < 2:
        raise ValueError(f"need at least 2 stamps, got {len(stamps_ns)}")
    return preintegrate_intervals(imu, stamps_ns[:-1], stamps_ns[1:], noise, bias_gyro, bias_acc, scheme, device)


def preintegrate_intervals(
    imu: ImuSamples,
    t0_ns: np.ndarray,
    t1_ns: np.ndarray,
    noise: ImuNoise,
    bias_gyro: torch.Tensor | np.ndarray | None = None,
    bias_acc: torch.Tensor | np.ndarray | None = None,
    scheme: str = "closed_form",
    device: torch.device | str = "cpu",
) -> Preintegrated:
    """Batched preintegration of B arbitrary intervals ``[t0_ns[b], t1_ns[b]]`` ((B,) each) in one vectorised
    pass -> ``Preintegrated`` with batch dimension B. Biases may be (3,) (shared) or (B, 3) (one per interval).
    """
    t0_ns, t1_ns = np.asarray(t0_ns, dtype=np.int64), np.asarray(t1_ns, dtype=np.int64)
    if t0_ns.ndim != 1 or t0_ns.shape != t1_ns.shape or len(t0_ns) < 1:
        raise ValueError(f"need (B,) interval starts and ends, B >= 1, got {t0_ns.shape} and {t1_ns.shape}")
    n = len(t0_ns)
    pieces = [interval_measurements(imu, t0_ns[k], t1_ns[k], rate_hz=noise.rate_hz) for k in range(n)]
    f64 = dict(dtype=torch.float64, device=device)
    dt = torch.as_tensor(np.concatenate([p[1] for p in pieces]), **f64)
    gyro = torch.as_tensor(np.concatenate([p[2] for p in pieces]), **f64)
    acc = torch.as_tensor(np.concatenate([p[3] for p in pieces]), **f64)
    segment = torch.as_tensor(np.repeat(np.arange(n), [len(p[1]) for p in pieces]), device=device)

    def per_interval(b):
        b = torch.zeros(3, **f64) if b is None else _as_f64(b, device)
        return b.expand(n, 3) if b.ndim == 1 else b

    out = preintegrate_segments(dt, gyro, acc, segment, noise, per_interval(bias_gyro), per_interval(bias_acc),
                                scheme)
    out.t0_ns, out.t1_ns = t0_ns.copy(), t1_ns.copy()
    return out
