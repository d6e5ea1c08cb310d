"""A smooth analytic body motion with exact IMU measurements (for tests and benchmarks).

Attitude ``R(t) = Exp(phi(t))`` and position ``p(t)`` are sums of sinusoids, so everything has a
closed form: ``w_b = J_r(phi) phi'`` (since ``d/dt Exp(phi) = Exp(phi) [J_r(phi) phi']x``), velocity
``p'``, specific force ``a_b = R^T (p'' - g)`` with ``g = (0, 0, -9.81)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.geometry import so3_exp, so3_right_jacobian
from vigs_core.types import ImuSamples

GRAVITY = np.array([0.0, 0.0, -9.81])


@dataclass
class AnalyticMotion:
    """``phi(t) = rot_amp * sin(rot_freq t + rot_phase)``, ``p(t) = pos_amp * sin(pos_freq t + pos_phase)``.

    Args (each (3,)): amplitudes (rad, m), angular frequencies (rad/s), phases (rad).
    """

    rot_amp: np.ndarray
    rot_freq: np.ndarray
    rot_phase: np.ndarray
    pos_amp: np.ndarray
    pos_freq: np.ndarray
    pos_phase: np.ndarray

    @staticmethod
    def default() -> "AnalyticMotion":
        """A gentle handheld-like motion: about 0.5 rad/s and 1 m/s^2 peaks."""
        return AnalyticMotion(
            rot_amp=np.array([0.3, 0.2, 0.8]), rot_freq=np.array([1.1, 0.7, 0.5]), rot_phase=np.array([0.3, 1.0, 0.0]),
            pos_amp=np.array([1.0, 0.6, 0.3]), pos_freq=np.array([0.9, 1.3, 1.7]), pos_phase=np.array([0.0, 0.5, 1.2]),
        )

    def _phi(self, t: np.ndarray):
        arg = self.rot_freq * t[:, None] + self.rot_phase
        return self.rot_amp * np.sin(arg), self.rot_amp * self.rot_freq * np.cos(arg)

    def state(self, t_s: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rotation (N,3,3), position (N,3) and world velocity (N,3) at times (N,) in seconds."""
        t = np.asarray(t_s, dtype=np.float64)
        phi, _ = self._phi(t)
        arg = self.pos_freq * t[:, None] + self.pos_phase
        p = self.pos_amp * np.sin(arg)
        v = self.pos_amp * self.pos_freq * np.cos(arg)
        return so3_exp(torch.as_tensor(phi)), torch.as_tensor(p), torch.as_tensor(v)

    def imu(self, t_ns: np.ndarray) -> ImuSamples:
        """Exact noise-free IMU samples at stamps (N,) ns (time zero at stamp 0)."""
        t = np.asarray(t_ns, dtype=np.int64) * 1e-9
        phi, dphi = self._phi(t)
        R = so3_exp(torch.as_tensor(phi))
        w = (so3_right_jacobian(torch.as_tensor(phi)) @ torch.as_tensor(dphi)[..., None])[..., 0]
        arg = self.pos_freq * t[:, None] + self.pos_phase
        acc_w = -self.pos_amp * self.pos_freq**2 * np.sin(arg)
        f_b = (R.transpose(-1, -2) @ torch.as_tensor(acc_w - GRAVITY)[..., None])[..., 0]
        return ImuSamples(np.asarray(t_ns, dtype=np.int64), w.numpy(), f_b.numpy())
