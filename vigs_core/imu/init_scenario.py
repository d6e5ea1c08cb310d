"""Inertial-only initialisation scenarios built from real ground truth (for benchmarks and tests).

A scenario emulates what a monocular front end hands to the inertial-only stage: keyframe camera
poses expressed in the first keyframe's camera frame (so gravity is not aligned with any axis),
positions multiplied by an unknown factor, rotations perturbed by noise. The true answer is the
factor that restores metric positions and the gravity direction in that frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.geometry import so3_exp
from vigs_core.imu.inertial_init import InertialInit
from vigs_core.types import Trajectory


@dataclass
class InitScenario:
    """Keyframes of one window.

    Attributes:
        stamps_ns: (N,) keyframe stamps (ns), taken from ground-truth stamps.
        T_wc: (N, 4, 4) float64 camera poses in the first camera frame, positions times ``1 / true_scale``.
        true_scale: the factor the initialisation must recover (metric = true_scale * given).
        gravity_dir: (3,) true gravity direction in the first camera frame (unit).
    """

    stamps_ns: np.ndarray
    T_wc: torch.Tensor
    true_scale: float
    gravity_dir: torch.Tensor


def make_scenario(
    gt: Trajectory,
    t0_ns: int,
    duration_s: float,
    spacing_s: float,
    T_bc: np.ndarray,
    position_factor: float,
    rotation_noise_deg: float,
    rng: np.random.Generator,
) -> InitScenario:
    """Keyframes every ``spacing_s`` (nearest ground-truth stamps) over ``[t0, t0 + duration]``.

    Args:
        gt: body (IMU) poses ``T_wb`` in a z-up world.
        T_bc: (4, 4) camera pose in the body frame (EuRoC ``T_BS`` of cam0).
        position_factor: the unknown scale applied to positions (the true scale is its inverse).
        rotation_noise_deg: each keyframe rotation gets ``Exp(n)``, ``n`` with a uniformly random axis
            and an angle of exactly this many degrees.
    """
    wanted = t0_ns + np.round(np.arange(0.0, duration_s + 1e-9, spacing_s) * 1e9).astype(np.int64)
    idx = np.unique(np.clip(np.searchsorted(gt.t_ns, wanted), 0, len(gt) - 1))
    if len(idx) < 3:
        raise ValueError(f"ground truth has only {len(idx)} stamps in the window starting at {t0_ns} ns")
    T_wb = torch.as_tensor(gt.matrices()[idx])
    T_wc = T_wb @ torch.as_tensor(T_bc, dtype=torch.float64)
    T_c0c = torch.linalg.inv(T_wc[0]) @ T_wc
    axis = rng.normal(size=(len(idx), 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    noise = torch.as_tensor(axis * math.radians(rotation_noise_deg))
    T = T_c0c.clone()
    T[:, :3, :3] = so3_exp(noise) @ T_c0c[:, :3, :3]
    T[:, :3, 3] = T_c0c[:, :3, 3] * position_factor
    g_dir = T_wc[0, :3, :3].T @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    return InitScenario(gt.t_ns[idx], T, 1.0 / position_factor, g_dir)


def init_errors(result: InertialInit, scenario: InitScenario) -> tuple[float, float]:
    """(relative scale error, gravity direction error in degrees) of a solution."""
    scale_err = abs(result.scale / scenario.true_scale - 1.0)
    g = result.gravity_world / result.gravity_world.norm()
    cosang = float((g * scenario.gravity_dir).sum().clamp(-1.0, 1.0))
    return scale_err, math.degrees(math.acos(cosang))

