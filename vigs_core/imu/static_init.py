"""Static-segment detection and static IMU initialisation (gravity direction, gyro bias).

A window of samples is static when the per-axis standard deviations of both the gyro and the
accelerometer stay under thresholds (norm over the axes). The defaults are absolute values that
tolerate the vibration of a multirotor standing with its motors on (EuRoC: about 0.02 rad/s and
0.3 m/s^2 standing, 0.1 rad/s and 1.5 m/s^2 in flight), not multiples of the white-noise density.

On a static segment the gyro measures only its bias and the accelerometer only the reaction to
gravity (``a = R_wb^T (0, 0, |g|) + b_a``), so (OpenVINS-style static initialisation)::

    b_g = mean(w),   |g| ~= |mean(a)|,   R_wb = the minimal rotation taking mean(a)/|mean(a)| to +z

(yaw is unobservable and set by the minimal rotation; the accelerometer bias is not separable from
gravity here and is left to the inertial-only stage). Where ground truth exists, still segments can also be
taken from its motion (:func:`still_segments_from_motion`), for a platform whose vibration at rest is as strong
as in motion.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.imu.residual import gravity_rotation
from vigs_core.ranges import bounded
from vigs_core.types import ImuSamples, Trajectory


@dataclass
class StaticDetectorConfig:
    """Settings of :func:`detect_static_segments`.

    Args:
        window_s: sliding-window length (s).
        gyro_std_max: largest norm of the per-axis gyro standard deviations of a static window (rad/s).
        acc_std_max: same for the accelerometer (m/s^2).
        min_duration_s: shortest static segment reported (s).
    """

    window_s: float = 0.5
    gyro_std_max: float = 0.05
    acc_std_max: float = 0.6
    min_duration_s: float = 1.0


@dataclass
class StaticInit:
    """Result of a static initialisation.

    Attributes:
        t0_ns, t1_ns: the segment used (ns).
        R_wb: (3, 3) float64 body attitude in a gravity-aligned world (z up, yaw from the minimal rotation).
        bias_gyro: (3,) rad/s, mean gyro over the segment.
        gravity_magnitude: ``|mean(acc)|`` (m/s^2).
        gyro_std: (3,) per-axis gyro standard deviation (rad/s); acc_std: (3,) (m/s^2).
        n_samples: samples used.
    """

    t0_ns: int
    t1_ns: int
    R_wb: torch.Tensor
    bias_gyro: torch.Tensor
    gravity_magnitude: float
    gyro_std: np.ndarray
    acc_std: np.ndarray
    n_samples: int


def _windowed_std(values: np.ndarray, n: int) -> np.ndarray:
    """(N, 3) -> (N - n + 1,) norm of the per-axis standard deviations over windows of n samples."""
    c1 = np.cumsum(np.concatenate((np.zeros((1, 3)), values)), axis=0)
    c2 = np.cumsum(np.concatenate((np.zeros((1, 3)), values**2)), axis=0)
    mean = (c1[n:] - c1[:-n]) / n
    var = np.maximum((c2[n:] - c2[:-n]) / n - mean**2, 0.0)
    return np.sqrt(var.sum(axis=1))


def detect_static_segments(imu: ImuSamples, config: StaticDetectorConfig | None = None) -> np.ndarray:
    """Static segments of a (sorted) IMU stream.

    Returns:
        (S, 2) int64 ``(start_ns, end_ns)`` of the maximal runs of samples covered by static windows,
        at least ``min_duration_s`` long.
    """
    cfg = config or StaticDetectorConfig()
    if len(imu) < 3:
        return np.zeros((0, 2), np.int64)
    period = float(np.median(np.diff(imu.t_ns))) * 1e-9
    n = max(int(round(cfg.window_s / period)), 2)
    if len(imu) < n:
        return np.zeros((0, 2), np.int64)
    still = (_windowed_std(imu.gyro, n) < cfg.gyro_std_max) & (_windowed_std(imu.acc, n) < cfg.acc_std_max)
    covered = np.zeros(len(imu) + 1, np.int64)  # difference array: samples covered by a static window
    starts = np.flatnonzero(still)
    np.add.at(covered, starts, 1)
    np.add.at(covered, starts + n, -1)
    return _runs(imu.t_ns, np.cumsum(covered[:-1]) > 0, cfg.min_duration_s)


def _runs(t_ns: np.ndarray, mask: np.ndarray, min_duration_s: float) -> np.ndarray:
    """(S, 2) int64 ``(first, last)`` stamps of the maximal runs of ``mask`` lasting at least ``min_duration_s``."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    segments = [(t_ns[a], t_ns[b - 1]) for a, b in zip(edges[::2], edges[1::2])]
    keep = [(a, b) for a, b in segments if (b - a) * 1e-9 >= min_duration_s]
    return np.array(keep, dtype=np.int64).reshape(-1, 2)


@dataclass
class MotionStillConfig:
    """Settings of :func:`still_segments_from_motion`.

    Args:
        span_s: speeds and angular rates are taken over this span around each pose (s; smooths the motion
            capture's noise).
        max_speed: largest speed of a still pose (m/s).
        max_rate: largest angular rate of a still pose (rad/s).
        min_duration_s: shortest still segment reported (s).
    """

    span_s: float = bounded(0.2, 0, lo_open=True)
    max_speed: float = bounded(0.02, 0, lo_open=True)
    max_rate: float = bounded(0.05, 0, lo_open=True)
    min_duration_s: float = bounded(0.25, 0)


def still_segments_from_motion(gt: Trajectory, config: MotionStillConfig | None = None) -> np.ndarray:
    """(S, 2) int64 ``(start_ns, end_ns)`` where a ground-truth trajectory stands still (speed and angular rate
    under the limits, over ``span_s``): the static segments of a platform whose vibration hides them from the
    IMU alone (a hovering or idling vehicle)."""
    cfg = config or MotionStillConfig()
    t = (gt.t_ns - gt.t_ns[0]) * 1e-9
    if len(t) < 3:
        return np.zeros((0, 2), np.int64)
    lo = np.searchsorted(t, t - cfg.span_s / 2)
    hi = np.minimum(np.searchsorted(t, t + cfg.span_s / 2, side="right") - 1, len(t) - 1)
    hi = np.maximum(hi, np.minimum(lo + 1, len(t) - 1))
    lo = np.minimum(lo, hi - 1)
    dt = t[hi] - t[lo]
    speed = np.linalg.norm(gt.position[hi] - gt.position[lo], axis=1) / dt
    q = gt.quat_wxyz
    dots = np.abs((q[hi] * q[lo]).sum(1)).clip(max=1.0)
    rate = 2 * np.arccos(dots) / dt
    return _runs(gt.t_ns, (speed <= cfg.max_speed) & (rate <= cfg.max_rate), cfg.min_duration_s)


def static_initialize(imu: ImuSamples, t0_ns: int, t1_ns: int) -> StaticInit:
    """Gyro bias, gravity magnitude and gravity-aligned attitude from samples in ``[t0_ns, t1_ns]``."""
    m = (imu.t_ns >= t0_ns) & (imu.t_ns <= t1_ns)
    n = int(m.sum())
    if n < 10:
        raise ValueError(f"static initialisation needs at least 10 samples in [{t0_ns}, {t1_ns}] ns, got {n}")
    gyro, acc = imu.gyro[m], imu.acc[m]
    a_mean = acc.mean(axis=0)
    up_body = torch.as_tensor(a_mean / np.linalg.norm(a_mean))
    # R_wb maps up_body to +z: R_wb = gravity_rotation(-up_body)^T since gravity_rotation maps -z -> dir.
    R_wb = gravity_rotation(-up_body).T
    return StaticInit(
        t0_ns=int(t0_ns), t1_ns=int(t1_ns), R_wb=R_wb, bias_gyro=torch.as_tensor(gyro.mean(axis=0)),
        gravity_magnitude=float(np.linalg.norm(a_mean)), gyro_std=gyro.std(axis=0), acc_std=acc.std(axis=0),
        n_samples=n,
    )
