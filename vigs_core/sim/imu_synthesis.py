"""IMU measurements synthesised from a differentiable body motion.

Noise-free model (body frame B = IMU frame, world z up, gravity ``g = (0, 0, -g0)``):

    omega_B = vee(R_WB^T R_WB')          (gyroscope, rad/s)
    a_B     = R_WB^T (p_WB'' - g)        (accelerometer specific force, m/s^2; +g0 on z when level at rest)

Noise (Kalibr / EuRoC continuous-time model, discretised at sample period ``dt``; Trawny & Roumeliotis,
"Indirect Kalman filter for 3D attitude estimation", 2005; Kalibr wiki "IMU Noise Model"):

    measurement_k = true_k + b_k + sigma_c / sqrt(dt) * n_k,     b_{k+1} = b_k + sigma_b * sqrt(dt) * m_k

with ``n_k, m_k ~ N(0, I_3)``, ``sigma_c`` the noise density and ``sigma_b`` the bias random walk of
:class:`~vigs_core.types.ImuNoise`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vigs_core.sim.trajectory import ProceduralMotion, SplineMotion
from vigs_core.types import ImuNoise, ImuSamples

GRAVITY = 9.81


@dataclass
class SynthesizedImu:
    """Synthesised IMU stream and the biases that were added.

    Attributes:
        imu: the measurements (noise and bias included unless synthesised noise-free).
        bias_gyro: (N, 3) gyroscope bias at each sample (rad/s).
        bias_acc: (N, 3) accelerometer bias at each sample (m/s^2).
    """

    imu: ImuSamples
    bias_gyro: np.ndarray
    bias_acc: np.ndarray


def imu_stamps(start_ns: int, end_ns: int, rate_hz: float) -> np.ndarray:
    """(N,) int64 stamps ``start_ns + round(k * 1e9 / rate_hz)`` up to ``end_ns`` inclusive."""
    if rate_hz <= 0:
        raise ValueError(f"imu_stamps: rate_hz must be positive, got {rate_hz}")
    n = int(np.floor((end_ns - start_ns) * 1e-9 * rate_hz + 1e-9)) + 1
    return start_ns + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)


def synthesize_imu(
    motion: ProceduralMotion | SplineMotion,
    t_ns: np.ndarray,
    noise: ImuNoise | None = None,
    seed: int = 0,
    gravity: float = GRAVITY,
    initial_bias_gyro: np.ndarray | None = None,
    initial_bias_acc: np.ndarray | None = None,
) -> SynthesizedImu:
    """IMU measurements of ``motion`` at stamps ``t_ns`` (N,).

    Args:
        motion: differentiable body motion (its body frame is the IMU frame).
        t_ns: (N,) increasing sample stamps (ns).
        noise: noise model; None synthesises the exact, noise-free and bias-free measurements.
        seed: random seed of noise and bias walks.
        gravity: magnitude g0 (m/s^2) of gravity along world -z.
        initial_bias_gyro: (3,) bias at the first sample (rad/s); zero if None.
        initial_bias_acc: (3,) bias at the first sample (m/s^2); zero if None.

    Returns:
        :class:`SynthesizedImu`.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    state = motion.evaluate(t_ns)
    g = np.array([0.0, 0.0, -gravity])
    acc = np.einsum("nji,nj->ni", state.rotation, state.acceleration - g)  # R^T (p'' - g)
    gyro = state.omega_body.copy()
    n = len(t_ns)
    b_g = np.zeros((n, 3)) + (0.0 if initial_bias_gyro is None else np.asarray(initial_bias_gyro, dtype=np.float64))
    b_a = np.zeros((n, 3)) + (0.0 if initial_bias_acc is None else np.asarray(initial_bias_acc, dtype=np.float64))
    if noise is not None and n > 0:
        rng = np.random.default_rng([seed, 4])
        dt = np.diff(t_ns) * 1e-9
        dt_sample = np.concatenate([dt[:1], dt]) if n > 1 else np.array([1.0 / noise.rate_hz])
        walk_g = noise.gyro_random_walk * np.sqrt(dt)[:, None] * rng.standard_normal((n - 1, 3))
        walk_a = noise.acc_random_walk * np.sqrt(dt)[:, None] * rng.standard_normal((n - 1, 3))
        b_g = b_g + np.concatenate([np.zeros((1, 3)), np.cumsum(walk_g, axis=0)])
        b_a = b_a + np.concatenate([np.zeros((1, 3)), np.cumsum(walk_a, axis=0)])
        white_g = noise.gyro_noise_density / np.sqrt(dt_sample)[:, None] * rng.standard_normal((n, 3))
        white_a = noise.acc_noise_density / np.sqrt(dt_sample)[:, None] * rng.standard_normal((n, 3))
        gyro = gyro + b_g + white_g
        acc = acc + b_a + white_a
    else:
        gyro = gyro + b_g
        acc = acc + b_a
    return SynthesizedImu(ImuSamples(t_ns, gyro, acc), b_g, b_a)
