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

from vigs_core.imu.preintegration import Preintegrated, preintegrate_path
from vigs_core.types import ImuSamples

GRAVITY_VECTOR = (0.0, 0.0, -9.81)


@dataclass
class ImuState:
    """Navigation state of the body (IMU) frame in a gravity-aligned world.

    Attributes:
        t_ns: stamp (ns).
        R: (3, 3) rotation ``R_wb``; p: (3,) position (m); v: (3,) velocity (m/s), world frame.
        bias_gyro: (3,) rad/s; bias_acc: (3,) m/s^2.
    """

    t_ns: int
    R: torch.Tensor
    p: torch.Tensor
    v: torch.Tensor
    bias_gyro: torch.Tensor
    bias_acc: torch.Tensor


@dataclass
class PropagatedPath:
    """States at every grid stamp of a propagation: t_ns (K+1,), R (K+1,3,3), p (K+1,3), v (K+1,3)."""

    t_ns: np.ndarray
    R: torch.Tensor
    p: torch.Tensor
    v: torch.Tensor


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
    state: ImuState, imu: ImuSamples, t1_ns: int, gravity=GRAVITY_VECTOR, scheme: str = "closed_form"
) -> PropagatedPath:
    """States at every IMU sample after ``state.t_ns`` up to ``t1_ns`` (inclusive, interpolated end)."""
    path = preintegrate_path(imu, state.t_ns, t1_ns, state.bias_gyro, state.bias_acc, scheme,
                             device=state.p.device)
    g = _gravity(gravity, state.p)
    tau = torch.as_tensor((path.grid_ns - path.grid_ns[0]) * 1e-9, dtype=state.p.dtype, device=state.p.device)
    R = state.R @ path.R
    v = state.v + g * tau[:, None] + (state.R @ path.v[..., None])[..., 0]
    p = state.p + state.v * tau[:, None] + 0.5 * g * (tau * tau)[:, None] + (state.R @ path.p[..., None])[..., 0]
    return PropagatedPath(path.grid_ns, R, p, v)


def propagate(
    state: ImuState, imu: ImuSamples, t1_ns: int, gravity=GRAVITY_VECTOR, scheme: str = "closed_form"
) -> ImuState:
    """The state at ``t1_ns`` (see :func:`propagate_path`)."""
    path = propagate_path(state, imu, t1_ns, gravity, scheme)
    return replace(state, t_ns=int(t1_ns), R=path.R[-1], p=path.p[-1], v=path.v[-1])
