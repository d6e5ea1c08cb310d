"""On-manifold IMU preintegration (Forster et al., "On-Manifold Preintegration for Real-Time
Visual-Inertial Odometry", T-RO 2017), vectorised over the samples; the arithmetic is float64 NumPy on
the host (:func:`preintegrate_segments`), the results torch tensors.

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

from vigs_core.arrays import host
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
        with ``db = b - b_lin``. Shapes: biases (..., 3) -> ((..., 3, 3), (..., 3), (..., 3)); torch tensors, or
        NumPy arrays on a :meth:`host` copy.
        """
        dbg = bias_gyro - self.bias_gyro
        dba = bias_acc - self.bias_acc
        mv = lambda m, x: (m @ x[..., None])[..., 0]  # noqa: E731
        dR = self.delta_R @ so3_exp(mv(self.J_R_bg, dbg))
        dv = self.delta_v + mv(self.J_v_bg, dbg) + mv(self.J_v_ba, dba)
        dp = self.delta_p + mv(self.J_p_bg, dbg) + mv(self.J_p_ba, dba)
        return dR, dv, dp

    def host(self) -> "Preintegrated":
        """A copy whose tensors are float64 NumPy arrays on the host (for NumPy arithmetic, e.g. the inertial
        factor); the stamps stay as they are."""
        return Preintegrated(**{
            name: (value if name in ("t0_ns", "t1_ns") else host(value))
            for name, value in vars(self).items()
        })

    def item(self, k: int) -> "Preintegrated":
        """Element ``k`` of a batched :class:`Preintegrated`."""
        return Preintegrated(**{
            name: (value[k] if name not in ("t0_ns", "t1_ns") else np.int64(value[k]))
            for name, value in vars(self).items()
        })


@dataclass
class _PieceMatrices:
    """The SO(3) matrices of the pieces' rotation vectors ``phi`` (K, 3), each (K, 3, 3) (NumPy), from one ``[phi]x``
    and one set of Rodrigues coefficients ``a = sin t / t``, ``b = (1 - cos t) / t^2``,
    ``c = (t - sin t) / t^3`` (``t = |phi|``; :mod:`vigs_core.geometry.so3`, Taylor near 0)::

        Exp(phi) = I + a [phi]x + b [phi]x^2
        J_r(phi) = I - b [phi]x + c [phi]x^2,   J_l(phi) = J_r(-phi) = I + b [phi]x + c [phi]x^2
        G2(phi)  = sum_n [phi]x^n / (n+2)! = I/2 + c [phi]x + d [phi]x^2,   d = (t^2/2 + cos t - 1) / t^4

    (``G2`` is the double integral of ``Exp(s phi)``; ``J_l`` and ``G2`` only for the closed-form scheme.)
    """

    exp: np.ndarray
    right_jacobian: np.ndarray
    left_jacobian: np.ndarray | None
    gamma2: np.ndarray | None

    @staticmethod
    def of(phi: np.ndarray, scheme: str) -> "_PieceMatrices":
        a, b, c = (x[..., None, None] for x in rodrigues_coefficients(phi))
        k = hat(phi)
        kk = k @ k
        eye = np.eye(3)
        exp, ck2 = eye + a * k + b * kk, c * kk
        right = eye - b * k + ck2
        if scheme != "closed_form":
            return _PieceMatrices(exp, right, None, None)
        t2 = (phi * phi).sum(-1)
        small = t2 < _SMALL_ANGLE**2
        t = np.sqrt(np.where(small, 1.0, t2))
        d = np.where(small, 1 / 24 - t2 / 720 + t2**2 / 40320, (0.5 * t**2 + np.cos(t) - 1) / t**4)
        return _PieceMatrices(exp, right, eye + b * k + ck2, 0.5 * eye + c * k + d[..., None, None] * kk)


def segmented_cumulative_product(mats: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """Inclusive prefix products ``P_k = M_first ... M_k`` of (K, 3, 3) matrices, restarting at every
    segment (``segment`` (K,) non-decreasing ids); by doubling (Hillis-Steele), ``ceil(log2 K)`` steps."""
    out = mats.copy()
    step = 1
    while step < len(out):
        same = (segment[step:] == segment[:-step])[:, None, None]
        out[step:] = np.where(same, out[:-step] @ out[step:], out[step:])
        step *= 2
    return out


def _segmented_cumsum(x: np.ndarray, segment: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Inclusive cumulative sum along axis 0 restarting at each segment (``first`` (S,) start indices)."""
    c = np.cumsum(x, 0)
    offset = c[first] - x[first]
    return c - offset[segment]


def _integrate(dt, w, a, segment, first, scheme: str):
    """Deltas before/after every piece for bias-corrected measurements dt (K,), w (K,3), a (K,3) (NumPy)."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown preintegration scheme '{scheme}'; expected one of {SCHEMES}")
    phi = w * dt[:, None]
    m = _PieceMatrices.of(phi, scheme)
    eye = np.eye(3)
    R_after = segmented_cumulative_product(m.exp, segment)
    is_first = np.zeros(len(dt), dtype=bool)
    is_first[first] = True
    R_before = np.where(is_first[:, None, None], eye, np.concatenate((eye[None], R_after[:-1])))
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


def _bias64(b) -> np.ndarray:
    """A bias (3,) or (S, 3) as a float64 array; zero when None."""
    return np.zeros(3) if b is None else host(b, np.float64)


def _device_of(*xs) -> torch.device:
    """The device of the first tensor among ``xs`` (CPU when none is a tensor)."""
    return next((x.device for x in xs if isinstance(x, torch.Tensor)), torch.device("cpu"))


def integrate_deltas(dt: np.ndarray, gyro: np.ndarray, acc: np.ndarray, bias_gyro, bias_acc,
                     scheme: str = "closed_form") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Deltas ``(R (K+1,3,3), v (K+1,3), p (K+1,3))`` at every grid point, as float64 NumPy arrays (no
    covariance, no Jacobians): the per-sample path of IMU-rate odometry, a few intervals at a time."""
    dt, gyro, acc, bg, ba = (host(x, np.float64) for x in (dt, gyro, acc, bias_gyro, bias_acc))
    gyro, acc = gyro.reshape(-1, 3), acc.reshape(-1, 3)
    segment, first = np.zeros(len(dt), dtype=np.int64), np.zeros(1, dtype=np.int64)
    _, R, v, p, *_ = _integrate(dt, gyro - bg, acc - ba, segment, first, scheme)
    zero = np.zeros((1, 3))
    return np.concatenate((np.eye(3)[None], R)), np.concatenate((zero, v)), np.concatenate((zero, p))


def preintegrate_segments(
    dt: torch.Tensor | np.ndarray,
    gyro: torch.Tensor | np.ndarray,
    acc: torch.Tensor | np.ndarray,
    segment: torch.Tensor | np.ndarray,
    noise: ImuNoise,
    bias_gyro: torch.Tensor | np.ndarray,
    bias_acc: torch.Tensor | np.ndarray,
    scheme: str = "closed_form",
    device: torch.device | str | None = None,
) -> Preintegrated:
    """Preintegrate S measurement sequences at once (see the module docstring for the maths).

    The arithmetic runs in float64 NumPy on the host: a preintegration is a few hundred operations on arrays
    of tens of samples, where torch's per-operation overhead (several microseconds each, on any device) is most
    of the cost (a single 0.15 s interval took about 2.5 ms through torch, once per tracked frame).

    Args:
        dt: (K,) piece lengths (s), all positive.
        gyro: (K, 3) angular velocity (rad/s); acc: (K, 3) specific force (m/s^2).
        segment: (K,) int64 non-decreasing ids ``0..S-1``: which sequence each piece belongs to
            (every id present).
        noise: continuous noise densities (``ImuNoise``).
        bias_gyro, bias_acc: (S, 3) linearisation biases of each sequence.
        scheme: ``"closed_form"`` or ``"forster"`` (GTSAM ``ManifoldPreintegration``-identical).
        device: device of the returned tensors (default: that of the inputs, CPU for arrays).

    Returns:
        :class:`Preintegrated` with batch dimension S (stamps set to 0 and the total length in ns).
    """
    device = _device_of(dt, gyro, acc, bias_gyro) if device is None else torch.device(device)
    dt, gyro, acc, bg, ba = (host(x, np.float64) for x in (dt, gyro, acc, bias_gyro, bias_acc))
    gyro, acc, bg, ba = (x.reshape(-1, 3) for x in (gyro, acc, bg, ba))
    segment = host(segment, np.int64)
    _check_pieces(dt, gyro, acc)
    n_seg = bg.shape[0]
    counts = np.bincount(segment, minlength=n_seg)
    if len(counts) != n_seg or bool((counts == 0).any()) or bool((segment[1:] < segment[:-1]).any()):
        raise ValueError(f"segment ids must be non-decreasing and cover 0..{n_seg - 1}, each at least once")
    last = np.cumsum(counts) - 1
    first = last - counts + 1
    a = acc - ba[segment]
    R_before, R_after, v_after, p_after, J_r, g1, g2 = _integrate(dt, gyro - bg[segment], a, segment, first, scheme)

    t_after = _segmented_cumsum(dt, segment, first)
    total = t_after[last]
    remain = total[segment] - t_after  # T_K - T_{m+1}, (K,)
    R_N, v_N, p_N = R_after[last], v_after[last], p_after[last]
    RJ = R_after @ J_r * dt[:, None, None]  # dR_{m+1} J_r(phi_m) dt_m
    s_v = v_N[segment] - v_after
    s_p = p_N[segment] - p_after - v_after * remain[:, None]
    hat_sv, hat_sp, hat_a = hat(np.stack((s_v, s_p, a)))
    d_phi_w = R_N[segment].swapaxes(-1, -2) @ RJ
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

    D_w = np.concatenate((d_phi_w, d_v_w, d_p_w), axis=1)  # (K, 9, 3)
    D_a = np.concatenate((np.zeros_like(d_v_a), d_v_a, d_p_a), axis=1)
    inv_dt = (1.0 / dt)[:, None, None]
    piece_cov = noise.gyro_noise_density**2 * (D_w * inv_dt) @ D_w.swapaxes(-1, -2)
    piece_cov = piece_cov + noise.acc_noise_density**2 * (D_a * inv_dt) @ D_a.swapaxes(-1, -2)
    cov9 = np.zeros((n_seg, 9, 9))
    np.add.at(cov9, segment, piece_cov)
    cov = np.zeros((n_seg, 15, 15))
    cov[:, :9, :9] = 0.5 * (cov9 + cov9.swapaxes(-1, -2))
    eye = np.eye(3)
    cov[:, 9:12, 9:12] = noise.gyro_random_walk**2 * total[:, None, None] * eye
    cov[:, 12:15, 12:15] = noise.acc_random_walk**2 * total[:, None, None] * eye

    # bias Jacobians: -sum over each segment's pieces, (S, 3, 3) each
    per_piece = np.stack((d_phi_w, d_v_w, d_v_a, d_p_w, d_p_a), 1)
    sums = np.zeros((n_seg, 5, 3, 3))
    np.add.at(sums, segment, per_piece)
    J_R_bg, J_v_bg, J_v_ba, J_p_bg, J_p_ba = (-sums).swapaxes(0, 1)
    stamps = np.round(total * 1e9).astype(np.int64)
    t = lambda x: torch.from_numpy(np.require(x, requirements=("C", "W"))).to(device)  # noqa: E731
    return Preintegrated(
        t0_ns=np.zeros(n_seg, np.int64), t1_ns=stamps, dt=t(total),
        delta_R=t(R_N), delta_v=t(v_N), delta_p=t(p_N), cov=t(cov),
        J_R_bg=t(J_R_bg), J_v_bg=t(J_v_bg), J_v_ba=t(J_v_ba),
        J_p_bg=t(J_p_bg), J_p_ba=t(J_p_ba), bias_gyro=t(bg), bias_acc=t(ba),
    )


def preintegrate_measurements(
    dt: torch.Tensor | np.ndarray,
    gyro: torch.Tensor | np.ndarray,
    acc: torch.Tensor | np.ndarray,
    noise: ImuNoise,
    bias_gyro: torch.Tensor | np.ndarray | None = None,
    bias_acc: torch.Tensor | np.ndarray | None = None,
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
    bg, ba = _bias64(bias_gyro), _bias64(bias_acc)
    segment = np.zeros(len(dt), dtype=np.int64)
    batch = preintegrate_segments(dt, gyro, acc, segment, noise, bg[None], ba[None], scheme,
                                  _device_of(dt, gyro, acc))
    return batch.item(0)


def _check_pieces(dt: np.ndarray, gyro: np.ndarray, acc: np.ndarray) -> None:
    if not (len(dt) == len(gyro) == len(acc)) or len(dt) == 0:
        raise ValueError(f"need K >= 1 equal-length dt/gyro/acc, got {len(dt)}, {len(gyro)}, {len(acc)}")
    if bool((dt <= 0).any()):
        raise ValueError("preintegration needs positive piece lengths dt")


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
    bg = _bias64(bias_gyro)
    exp = _PieceMatrices.of((gyro - bg) * dt[:, None], "forster").exp
    return torch.from_numpy(segmented_cumulative_product(exp, np.zeros(len(dt), dtype=np.int64))[-1]).to(device)


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
    dt = np.concatenate([p[1] for p in pieces])
    gyro = np.concatenate([p[2] for p in pieces])
    acc = np.concatenate([p[3] for p in pieces])
    segment = np.repeat(np.arange(n), [len(p[1]) for p in pieces])

    def per_interval(b):
        b = _bias64(b)
        return np.broadcast_to(b, (n, 3)) if b.ndim == 1 else b

    out = preintegrate_segments(dt, gyro, acc, segment, noise, per_interval(bias_gyro), per_interval(bias_acc),
                                scheme, device)
    out.t0_ns, out.t1_ns = t0_ns.copy(), t1_ns.copy()
    return out
