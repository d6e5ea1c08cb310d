"""Three-stage visual-inertial initialisation (VIGS-SLAM Sec. 3.2) and the map alignment it produces.

Stages, by the number ``K`` of keyframes (both thresholds are :class:`~vigs_core.vio.config.VioConfig`
parameters, paper values 10 and 20):

1. ``VISION_ONLY`` while ``K < inertial_init_keyframes``: dense BA without inertial terms gives up-to-scale
   poses in the first camera's frame (the first ``vision_only_keyframes`` form the visual initialisation).
2. At ``K = inertial_init_keyframes`` the inertial-only stage
   (:func:`vigs_core.imu.inertial_init.inertial_only_init`): with the poses fixed, solve the gravity direction
   ``R_wg``, the per-keyframe velocities, the bias and the log-scale ``sigma``. The solution is refused, and
   the stage retried at the next keyframe, unless it is trustworthy (standard deviations under the configured
   limits), physically plausible (finite; keyframe speeds and bias norms under ``max_speed``,
   ``max_bias_gyro``, ``max_bias_acc``; the closed-form solution's gravity magnitude within
   ``max_init_gravity_error``) and agrees with the previous keyframe's attempt (log-scale and gravity
   direction within ``init_agreement_log_scale`` and ``init_agreement_gravity_deg``). A singular problem is a
   "not yet" like any other refusal: it also breaks the agreement chain.
3. ``VISUAL_INERTIAL``: the map is rescaled and gravity-aligned (:class:`WorldAlignment`) and every later BA is
   the joint VI-BA with metric scale and gravity fixed along ``-z``.

After a failure (:meth:`StagedInitializer.restart`) the machine is back in stage 1 and the inertial-only stage
uses only keyframes from the restart on, once there are ``inertial_init_keyframes`` of them. Likewise after an
IMU gap (longer than ``max_imu_gap_s``) or where the IMU record no longer reaches back (a streaming buffer
keeps ``max_age_s``): the stage solves over the keyframes after it, once there are ``inertial_init_keyframes``
of them, instead of waiting until the gap has left its whole window.

Without staging (the Table 6 ablation) ``JOINT_UNALIGNED`` replaces stages 1-2 from ``vision_only_keyframes``
on: joint VI-BA with gravity direction and log-scale as free states, started from the mean accelerometer
reading (:func:`gravity_from_accelerometer`) and scale 1, aligned with those estimates at
``inertial_init_keyframes``.

Alignment: with ``s = exp(sigma)`` and ``R = R_wg^T`` the new world is ``x' = s R x`` (gravity along ``-z``,
metric). Camera poses ``T_cw = [R_cw | t_cw]`` become ``[R_cw R^T | s t_cw]``, disparities ``d / s``,
body velocities (already metric) ``R v``. Yaw stays that of the first camera (unobservable).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
import torch

from vigs_core.geometry import se3_inverse
from vigs_core.imu.buffer import ImuBuffer
from vigs_core.imu.inertial_init import InertialInit, InertialInitConfig, inertial_only_init
from vigs_core.imu.residual import gravity_rotation
from vigs_core.types import ImuNoise, ImuSamples
from vigs_core.vio.config import VioConfig


class Stage(str, Enum):
    """Initialisation stage of the visual-inertial estimator."""

    VISION_ONLY = "vision_only"
    JOINT_UNALIGNED = "joint_unaligned"
    VISUAL_INERTIAL = "visual_inertial"


@dataclass
class WorldAlignment:
    """Similarity ``x' = scale R x`` from the up-to-scale visual world to the metric gravity-aligned one.

    Attributes:
        scale: metric metres per map unit; R: (3, 3) rotation.
    """

    scale: float
    R: torch.Tensor

    def pose(self, T_cw: torch.Tensor) -> torch.Tensor:
        """World->camera poses (..., 4, 4) in the new world: ``[R_cw R^T | s t_cw]``."""
        out = T_cw.clone()
        out[..., :3, :3] = T_cw[..., :3, :3] @ self.R.to(T_cw).T
        out[..., :3, 3] = self.scale * T_cw[..., :3, 3]
        return out

    def velocity(self, v: torch.Tensor) -> torch.Tensor:
        """Metric world velocities (..., 3) rotated into the new world."""
        return v @ self.R.to(v).T

    def point(self, x: torch.Tensor) -> torch.Tensor:
        """World points (..., 3): ``s R x``."""
        return self.scale * (x @ self.R.to(x).T)


def alignment_from_gravity(R_wg: torch.Tensor, log_scale: float) -> WorldAlignment:
    """Alignment that maps gravity ``R_wg (0, 0, -g)`` to ``(0, 0, -g)`` and scales by ``exp(log_scale)``."""
    return WorldAlignment(float(np.exp(log_scale)), R_wg.to(torch.float64).T.clone())


def gravity_from_accelerometer(imu: ImuSamples, t0_ns: int, t1_ns: int, T_wc0: torch.Tensor,
                               T_cb: torch.Tensor) -> torch.Tensor:
    """``R_wg`` (3, 3) from the mean specific force over ``[t0, t1)`` rotated by the first keyframe's body
    orientation ``R_wb = R_wc0 R_cb`` (gravity ``= -R_wb mean(a)``; exact when the body does not accelerate)."""
    seg = imu.slice(t0_ns, t1_ns)
    if len(seg) == 0:
        raise ValueError(f"no IMU samples in [{t0_ns}, {t1_ns}) ns to estimate gravity from")
    a = torch.as_tensor(seg.acc.mean(0), dtype=torch.float64)
    R_wb = T_wc0[:3, :3].to(torch.float64) @ T_cb[:3, :3].to(torch.float64)
    return gravity_rotation(-(R_wb @ a))


@dataclass
class InitOutcome:
    """Result of the inertial-only stage, ready to apply.

    Attributes:
        alignment: the map transform.
        velocities: (K, 3) keyframe velocities in the NEW world (m/s).
        bias: (6,) ``(b_g, b_a)``.
        inertial: the raw inertial-only solution (trust figures), None when aligned from joint-BA states.
    """

    alignment: WorldAlignment
    velocities: torch.Tensor
    bias: torch.Tensor
    inertial: InertialInit | None


class StagedInitializer:
    """The stage machine (module docstring): call :meth:`on_keyframe` after each keyframe's BA.

    Args:
        config: VIO settings (counts, switches, trust limits).
        imu: the IMU record: a growing :class:`~vigs_core.imu.buffer.ImuBuffer` (streaming), or the samples of a
            whole recording (or at least those covering the keyframes).
        noise: IMU noise densities.
        T_cb: (4, 4) body->camera extrinsic.
    """

    def __init__(self, config: VioConfig, imu: ImuBuffer | ImuSamples, noise: ImuNoise, T_cb: torch.Tensor) -> None:
        self.config = config
        self.imu_buffer = ImuBuffer.of(imu)
        self.noise = noise
        self.T_cb = T_cb.to(torch.float64)
        self.stage = Stage.VISION_ONLY
        self.joint_start = 0      # keyframe count at which joint VI-BA without staging began
        self.first = 0            # keyframe count at the last restart: older keyframes are not used
        self.attempts: list[dict] = []
        self._candidate: InertialInit | None = None   # the previous attempt, when trustworthy and plausible

    @property
    def imu(self) -> ImuSamples:
        """The IMU samples received so far (views of the buffer)."""
        return self.imu_buffer.all()

    def _covers(self, stamps_ns: np.ndarray) -> bool:
        """True when the IMU samples bracket all stamps (ns) with no gap over ``max_imu_gap_s``."""
        return self.imu_buffer.covers_interval(int(stamps_ns[0]), int(stamps_ns[-1]),
                                               int(self.config.max_imu_gap_s * 1e9))

    def _covered_start(self, stamps_ns: np.ndarray, lo: int) -> int | None:
        """Index of the first keyframe from ``lo`` on that the IMU covers gap-free up to the newest one
        (:meth:`~vigs_core.imu.buffer.ImuBuffer.gap_free_from`), or None when the IMU does not reach the newest."""
        since = self.imu_buffer.gap_free_from(int(stamps_ns[lo]), int(stamps_ns[-1]),
                                              int(self.config.max_imu_gap_s * 1e9))
        return None if since is None else lo + int(np.searchsorted(stamps_ns[lo:], since, side="left"))

    def inertial_config(self) -> InertialInitConfig:
        c = self.config
        return InertialInitConfig(gravity=c.gravity, max_log_scale_std=c.max_init_log_scale_std,
                                  max_gravity_std_deg=c.max_init_gravity_std_deg, scheme=c.scheme,
                                  bias_random_walk=c.init_bias_random_walk)

    def on_keyframe(self, stamps_ns: np.ndarray, T_cw: torch.Tensor) -> InitOutcome | None:
        """Advance the stage machine with all keyframes so far (stamps (K,), world->camera poses (K, 4, 4)).

        Returns an :class:`InitOutcome` when the inertial-only stage succeeded at this keyframe (the caller
        applies the alignment and switches to VI-BA), else None. Without staging it only switches to
        ``JOINT_UNALIGNED``; the caller aligns with its joint estimates (:meth:`finish_joint`).
        """
        c = self.config
        K = len(stamps_ns)
        if not c.enabled or self.stage == Stage.VISUAL_INERTIAL:
            return None
        if not c.staged_init:
            if self.stage == Stage.VISION_ONLY and K >= c.vision_only_keyframes and self._covers(stamps_ns):
                self.stage = Stage.JOINT_UNALIGNED
                self.joint_start = K
            return None
        if K - self.first < c.inertial_init_keyframes:
            return None
        # the most recent keyframes, at most twice the stage's count (older poses drifted and are frozen), and
        # of those only the ones after the last IMU gap: the stage's count of them is enough to try
        lo = max(self.first, K - 2 * c.inertial_init_keyframes)
        all_stamps = np.asarray(stamps_ns, dtype=np.int64)
        start = self._covered_start(all_stamps, lo)
        if start is None or K - start < c.inertial_init_keyframes:
            self._candidate = None
            return None   # the IMU does not cover enough of the latest keyframes: stay vision-only
        stamps, poses = all_stamps[start:], T_cw[start:K].to(torch.float64)
        previous, self._candidate = self._candidate, None
        try:
            result = inertial_only_init(se3_inverse(poses), stamps, self.imu, self.noise, self.T_cb,
                                        self.inertial_config())
        except torch.linalg.LinAlgError as err:   # degenerate motion (e.g. no acceleration): not yet
            self.attempts.append({"keyframes": K, "refused": "singular: " + str(err).splitlines()[0]})
            return None
        attempt = {"keyframes": K, "scale": result.scale, "log_scale_std": result.log_scale_std,
                   "gravity_std_deg": result.gravity_std_deg, "chi2_per_dof": result.chi2_per_dof,
                   "linear_gravity_norm": result.linear_gravity_norm,
                   "trustworthy": result.trustworthy}
        self.attempts.append(attempt)
        refusal = self._refusal(result, previous)
        if refusal is not None:
            attempt["refused"] = refusal
            return None
        alignment = alignment_from_gravity(result.R_wg, result.log_scale)
        vel = torch.zeros(K, 3, dtype=torch.float64)
        vel[start:] = alignment.velocity(result.velocities)
        if start > 0:   # keyframes outside the solved window: finite differences of the aligned positions
            p = se3_inverse(alignment.pose(T_cw[:start + 1].to(torch.float64)))[:, :3, 3]
            dt = np.diff(all_stamps[:start + 1]) * 1e-9
            vel[:start] = (p[1:] - p[:-1]) / torch.as_tensor(dt)[:, None]
        bias = torch.cat((result.bias_gyro, result.bias_acc))
        self.stage = Stage.VISUAL_INERTIAL
        return InitOutcome(alignment, vel, bias, result)

    def _refusal(self, result: InertialInit, previous: InertialInit | None) -> str | None:
        """Why an inertial-only solution is not accepted (module docstring), or None; a trustworthy and
        plausible solution becomes the candidate the next attempt must agree with."""
        c = self.config
        values = torch.cat((result.velocities.reshape(-1), result.keyframe_biases.reshape(-1),
                            torch.tensor([result.log_scale, result.linear_gravity_norm], dtype=torch.float64)))
        if not bool(torch.isfinite(values).all()):
            return "not finite"
        if not abs(result.linear_gravity_norm / c.gravity - 1.0) <= c.max_init_gravity_error:
            return (f"implausible gravity: the closed-form solution has |g| {result.linear_gravity_norm:.3g} m/s^2 "
                    f"(expected {c.gravity:g} within {100 * c.max_init_gravity_error:g}%)")
        if not result.trustworthy:
            return "not trustworthy"
        speed = float(result.velocities.norm(dim=-1).max())
        b_g = float(result.keyframe_biases[:, :3].norm(dim=-1).max())
        b_a = float(result.keyframe_biases[:, 3:].norm(dim=-1).max())
        if speed > c.max_speed or b_g > c.max_bias_gyro or b_a > c.max_bias_acc:
            return (f"implausible: speed {speed:.3g} m/s (max {c.max_speed:g}), gyro bias {b_g:.3g} rad/s "
                    f"(max {c.max_bias_gyro:g}), accelerometer bias {b_a:.3g} m/s^2 (max {c.max_bias_acc:g})")
        self._candidate = result
        if previous is None:
            return "awaiting a second solution to agree with"
        d_scale = abs(result.log_scale - previous.log_scale)
        cos = torch.dot(result.gravity_world, previous.gravity_world) / (
            result.gravity_world.norm() * previous.gravity_world.norm())
        d_gravity = float(np.degrees(np.arccos(float(cos.clamp(-1.0, 1.0)))))
        if d_scale > c.init_agreement_log_scale or d_gravity > c.init_agreement_gravity_deg:
            return (f"disagrees with the previous attempt: log-scale by {d_scale:.3f} (max "
                    f"{c.init_agreement_log_scale:g}), gravity by {d_gravity:.2f} deg (max "
                    f"{c.init_agreement_gravity_deg:g})")
        return None

    def restart(self, K: int) -> None:
        """Back to the vision-only stage after a failure, with ``K`` keyframes so far (module docstring)."""
        self.stage = Stage.VISION_ONLY
        self.first = K
        self._candidate = None

    def finish_joint(self, K: int, R_wg: torch.Tensor, log_scale: float) -> WorldAlignment | None:
        """Without staging: at ``inertial_init_keyframes`` keyframes (and after at least one joint BA), the
        alignment from the joint estimates ``R_wg`` (3, 3) and ``log_scale``."""
        if (self.stage != Stage.JOINT_UNALIGNED or K < self.config.inertial_init_keyframes
                or K <= self.joint_start):
            return None
        self.stage = Stage.VISUAL_INERTIAL
        return alignment_from_gravity(R_wg, log_scale)
