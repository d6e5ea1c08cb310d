"""Propagation of a navigation state through IMU samples (keyframe initialisation, IMU-rate odometry).

With the preintegrated deltas from ``t_i`` (Forster et al. T-RO 2017, Eq. 33)::

    R_j = R_i dR_ij
    v_j = v_i + g dt_ij + R_i dv_ij
    p_j = p_i + v_i dt_ij + g dt_ij^2 / 2 + R_i dp_ij

Biases are held constant over the propagation (their expected change is zero).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from vigs_core.arrays import constant_like, host
from vigs_core.imu.preintegration import Preintegrated, integrate_deltas
from vigs_core.imu.samples import interval_measurements
from vigs_core.types import ImuSamples

GRAVITY_VECTOR = (0.0, 0.0, -9.81)


@dataclass
class ImuState:
    """Navigation state of the body (IMU) frame in a gravity-aligned world; the arrays are tensors or NumPy
    arrays (:func:`propagate_path` returns the same kind).

    Attributes:
        t_ns: stamp (ns).
        R: (3, 3) rotation ``R_wb``; p: (3,) position (m); v: (3,) velocity (m/s), world frame.
        bias_gyro: (3,) rad/s; bias_acc: (3,) m/s^2.
    """

    t_ns: int
    R: torch.Tensor | np.ndarray
    p: torch.Tensor | np.ndarray
    v: torch.Tensor | np.ndarray
    bias_gyro: torch.Tensor | np.ndarray
    bias_acc: torch.Tensor | np.ndarray


@dataclass
class PropagatedPath:
    """States at every grid stamp of a propagation: t_ns (K+1,), R (K+1,3,3), p (K+1,3), v (K+1,3)."""

    t_ns: np.ndarray
    R: torch.Tensor | np.ndarray
    p: torch.Tensor | np.ndarray
    v: torch.Tensor | np.ndarray


def _gravity(gravity, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(gravity, dtype=np.float64), dtype=like.dtype, device=like.device)


def predict_state(state: ImuState, pre: Preintegrated, gravity=GRAVITY_VECTOR) -> ImuState:
    """State at ``pre.t1_ns`` from ``state`` at ``pre.t0_ns``, deltas bias-corrected to the state's biases."""
    if int(pre.t0_ns) != int(state.t_ns):
        raise ValueError(f"preintegration starts at {int(pre.t0_ns)} ns but the state is at {state.t_ns} ns")
    g = _gravity(gravity, state.p)
    dR, dv, dp = pre.corrected(state.bias_gyro, state.bias_acc)
    dt = pre.dt
    return replace(
        state,
        t_ns=int(pre.t1_ns),
        R=state.R @ dR,
        v=state.v + g * dt + state.R @ dv,
        p=state.p + state.v * dt + 0.5 * g * dt * dt + state.R @ dp,
    )


def propagate_path(
    state: ImuState, imu: ImuSamples, t1_ns: int, gravity=GRAVITY_VECTOR, scheme: str = "closed_form",
    rate_hz: float | None = None,
) -> PropagatedPath:
    """States at every IMU sample after ``state.t_ns`` up to ``t1_ns`` (inclusive, interpolated end).

    The arithmetic is float64 NumPy on the host (IMU-rate odometry propagates one or a few samples at a
    time, where torch's per-operation cost would dominate); the states come back as the state's arrays
    (tensors on its device, or NumPy). ``rate_hz``: nominal rate of the gap warnings (default: the median)."""
    grid_ns, dt, gyro, acc = interval_measurements(imu, state.t_ns, t1_ns, rate_hz=rate_hz)
    dR, dv, dp = integrate_deltas(dt, gyro, acc, state.bias_gyro, state.bias_acc, scheme)
    R0, p0, v0 = (host(x, np.float64) for x in (state.R, state.p, state.v))
    g = np.asarray(gravity, dtype=np.float64)
    tau = ((grid_ns - grid_ns[0]) * 1e-9)[:, None]
    R = R0 @ dR
    v = v0 + g * tau + dv @ R0.T
    p = p0 + v0 * tau + 0.5 * g * tau * tau + dp @ R0.T
    return PropagatedPath(grid_ns, *(constant_like(x, state.p) for x in (R, p, v)))


def propagate(
    state: ImuState, imu: ImuSamples, t1_ns: int, gravity=GRAVITY_VECTOR, scheme: str = "closed_form"
) -> ImuState:
    """The state at ``t1_ns`` (see :func:`propagate_path`)."""
    path = propagate_path(state, imu, t1_ns, gravity, scheme)
    return replace(state, t_ns=int(t1_ns), R=path.R[-1], p=path.p[-1], v=path.v[-1])
