"""Initial pose of a new keyframe (or frame) from IMU preintegration (VIGS-SLAM Sec. 3.3).

From the previous keyframe's state (camera pose ``T_cw,i``, body velocity ``v_i``, bias ``b_i``) in the metric,
gravity-aligned world, the body state is predicted with the bias-corrected deltas (Forster et al. T-RO 2017,
Eq. 33; :func:`vigs_core.imu.propagation.predict_state`)::

    R_j = R_i dR_ij,   v_j = v_i + g dt + R_i dv_ij,   p_j = p_i + v_i dt + g dt^2 / 2 + R_i dp_ij

with the body pose ``T_wb = T_wc T_cb``. When the trace of the preintegration covariance of
``(dphi, dv, dp)`` exceeds ``tau`` (long gaps, noisy IMU) the prediction is not trusted and the new keyframe
starts at the previous keyframe's pose, keeping its velocity (the paper's fallback).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from vigs_core.geometry import se3_inverse
from vigs_core.imu.preintegration import Preintegrated
from vigs_core.imu.propagation import ImuState, predict_state


@dataclass
class KeyframePrediction:
    """Predicted state of a new keyframe.

    Attributes:
        T_cw: (4, 4) world->camera pose.
        velocity: (3,) body velocity in the world (m/s).
        from_imu: True when the IMU prediction was used, False for the fallback to the previous pose.
        cov_trace: trace of the (dphi, dv, dp) preintegration covariance that decided it.
    """

    T_cw: torch.Tensor
    velocity: torch.Tensor
    from_imu: bool
    cov_trace: float


def predict_keyframe(T_cw_prev: torch.Tensor, velocity_prev: torch.Tensor, bias_prev: torch.Tensor,
                     pre: Preintegrated, T_cb: torch.Tensor, gravity_world: torch.Tensor,
                     max_cov_trace: float = 1e-4) -> KeyframePrediction:
    """Pose and velocity at ``pre.t1_ns`` from the previous keyframe's state at ``pre.t0_ns``.

    Args:
        T_cw_prev: (4, 4) world->camera pose of the previous keyframe (metric, gravity-aligned world).
        velocity_prev: (3,) its body velocity (m/s); bias_prev: (6,) ``(b_g rad/s, b_a m/s^2)``.
        pre: single (unbatched) preintegration from the previous keyframe to the new stamp.
        T_cb: (4, 4) body->camera extrinsic.
        gravity_world: (3,) gravity vector (m/s^2), e.g. ``(0, 0, -9.81)``.
        max_cov_trace: tau, the fallback threshold on the covariance trace.
    """
    f = dict(dtype=torch.float64, device=T_cw_prev.device)
    if pre.delta_R.dim() != 2:
        raise ValueError(f"predict_keyframe needs one interval, got delta_R {tuple(pre.delta_R.shape)}")
    T_cw_prev, T_cb = T_cw_prev.to(**f), T_cb.to(**f)
    trace = float(torch.diagonal(pre.cov[:9, :9]).sum())
    if trace > max_cov_trace:
        return KeyframePrediction(T_cw_prev.clone(), velocity_prev.to(**f).clone(), False, trace)
    T_wb = se3_inverse(T_cw_prev) @ T_cb
    bias_prev = bias_prev.to(**f)
    state = ImuState(int(pre.t0_ns), T_wb[:3, :3], T_wb[:3, 3], velocity_prev.to(**f), bias_prev[:3], bias_prev[3:])
    new = predict_state(state, pre, gravity=tuple(float(x) for x in gravity_world))
    T_wb_new = torch.eye(4, **f)
    T_wb_new[:3, :3], T_wb_new[:3, 3] = new.R, new.p
    T_cw_new = T_cb @ se3_inverse(T_wb_new)
    return KeyframePrediction(T_cw_new, new.v, True, trace)
