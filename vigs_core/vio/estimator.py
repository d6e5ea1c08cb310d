"""Visual-inertial state of the keyframes and the glue between the IMU, the stage machine and dense BA.

:class:`VisualInertialEstimator` keeps, per keyframe, the body velocity and the IMU bias (or one global bias),
caches the preintegration between consecutive keyframes (re-integrated, all stale pairs of a window in one batch,
when the bias estimate moved more than ``relinearize_bias_threshold`` from the linearisation bias, since the
first-order correction of Forster Eq. 44 degrades with the bias change; a frame predicted from the previous
keyframe that becomes a keyframe hands its preintegration on to the new pair), builds the
:class:`~vigs_core.vio.inertial_terms.InertialTerms` of a BA window, predicts new frames from the IMU
(:mod:`vigs_core.vio.keyframe_init`) and runs the stage machine (:mod:`vigs_core.vio.initialization`). A front
end drives it with these calls::

    add_keyframe(id, t_ns)                      # a new keyframe exists
    predict(ref_id, T_cw_ref, t_ns)             # IMU prior for a frame (None before initialisation)
    predict_rotation(ref_id, T_cw_ref, t_ns)    # gyro-only rotation prior before initialisation
    terms(ids, poses) -> (terms, state) | None  # inertial terms of a BA window (pass to bundle_adjust)
    marginalize(ids, poses, visual)             # the oldest keyframe leaves the window (once metric)
    update(ids, state)                          # store the BA's velocities and biases
    health(ids, stamps, poses) -> str | None    # once metric, after a keyframe's BA: why the state is divergent
    fail(t_ns, reason)                          # then: back to vision-only on the current map, initialise again
    on_keyframe(ids, stamps, poses) -> WorldAlignment | None   # after the keyframe's BA; apply it to the map
    check_scale(ids, stamps, poses) -> WorldAlignment | None   # when scale_check_due(): the scale check
    monitor_scale(ids, stamps, poses) -> str | None             # after it, each keyframe: the rolling check

Failure detection (after VINS-Mono's and OpenVINS's checks): once metric, a keyframe whose speed or bias norm
is implausible (``max_speed``, ``max_bias_gyro``, ``max_bias_acc``) or whose position jumped further from the
previous keyframe's than ``max_speed`` allows, a scale check whose scale moved more than ``max_scale_drift``,
or ``scale_monitor_strikes`` successive rolling scale checks far from 1 (``scale_monitor_*``) is a failure: the
estimator forgets its inertial state (velocities, biases, preintegrations, prior) and the initialisation starts
again on the current map (:meth:`StagedInitializer.restart`); ``failures`` lists them.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from vigs_core.geometry import se3_inverse
from vigs_core.imu.buffer import ImuBuffer
from vigs_core.imu.inertial_init import inertial_only_init
from vigs_core.imu.preintegration import (Preintegrated, preintegrate, preintegrate_intervals, preintegrate_rotation,
                                          stack_preintegrated)
from vigs_core.types import ImuNoise, ImuSamples
from vigs_core.vio.config import VioConfig
from vigs_core.vio.inertial_terms import AnchorPrior, InertialState, InertialTerms, MarginalPrior
from vigs_core.vio.initialization import (Stage, StagedInitializer, WorldAlignment, alignment_from_gravity,
                                          gravity_from_accelerometer)
from vigs_core.vio.keyframe_init import KeyframePrediction, predict_keyframe
from vigs_core.vio.marginalization import marginalize_keyframe

F64 = torch.float64
_JUMP_SLACK_M = 0.5   # a keyframe may move this much beyond max_speed * dt (pose noise, camera lever arm)


def _bias_stds(gyro: float, acc: float) -> torch.Tensor:
    """(6,) standard deviations of a bias (gyroscope x3, accelerometer x3)."""
    return torch.tensor([gyro] * 3 + [acc] * 3, dtype=F64)


@dataclass
class KeyframeInertial:
    """Inertial state of one keyframe: stamp (ns), body velocity (3,) m/s (world), bias (6,) (b_g, b_a)."""

    t_ns: int
    velocity: torch.Tensor
    bias: torch.Tensor


class VisualInertialEstimator:
    """Per-keyframe velocities/biases, inertial BA terms, IMU prediction and staged initialisation.

    Args:
        config: VIO settings.
        imu: the IMU record (body frame): a growing :class:`~vigs_core.imu.buffer.ImuBuffer` that the caller
            appends to as samples arrive (streaming), or the samples of a whole recording.
        noise: IMU noise densities.
        T_bc: (4, 4) camera pose in the body frame (EuRoC ``T_BS`` of cam0); ``T_cb = T_bc^-1``.
    """

    def __init__(self, config: VioConfig, imu: ImuBuffer | ImuSamples, noise: ImuNoise,
                 T_bc: np.ndarray | torch.Tensor) -> None:
        self.config = config
        self.imu_buffer = ImuBuffer.of(imu)
        self.noise = noise
        self.T_cb = torch.linalg.inv(torch.as_tensor(np.asarray(T_bc), dtype=F64))
        self.initializer = StagedInitializer(config, self.imu_buffer, noise, self.T_cb)
        self.states: dict[int, KeyframeInertial] = {}
        self.global_bias = torch.zeros(6, dtype=F64)
        self.R_wg = torch.eye(3, dtype=F64)
        self.log_scale = 0.0
        self.scale_history: list[dict] = []
        self.alignment: WorldAlignment | None = None
        self.metric_since_ns: int | None = None   # stamp of the keyframe at which the map became metric
        self.scale_checked = False
        self.scale_verified_ns: int | None = None   # last keyframe of the last rolling check that found scale ~1
        self.scale_monitor = {"checks": 0, "deviating": 0}
        self._monitor_wait = 0
        self._monitor_strikes = 0
        self.failures: list[dict] = []
        self.reinitialisations = 0
        self.imu_predictions = 0
        self.fallbacks = 0
        self._pre: dict[tuple[int, int], Preintegrated] = {}
        self._last_predicted: tuple[int, Preintegrated] | None = None   # (reference keyframe id, its prediction's)
        self.marginal: MarginalPrior | None = None
        self.marginalized = 0

    # ------------------------------------------------------------------ queries
    @property
    def imu(self) -> ImuSamples:
        """The IMU samples received so far (views of the buffer)."""
        return self.imu_buffer.all()

    @property
    def stage(self) -> Stage:
        return self.initializer.stage

    @property
    def metric(self) -> bool:
        """True once the map is metric and gravity-aligned."""
        return self.stage == Stage.VISUAL_INERTIAL

    def gravity_world(self) -> torch.Tensor:
        """(3,) gravity in the current world frame (m/s^2)."""
        return self.R_wg @ torch.tensor([0.0, 0.0, -self.config.gravity], dtype=F64)

    def imu_covers(self, t0_ns: int, t1_ns: int) -> bool:
        """True when the IMU samples bracket ``[t0_ns, t1_ns]`` with no gap over ``max_imu_gap_s`` (keyframes
        outside, or across a gap, stay vision-only)."""
        return self.imu_buffer.covers_interval(t0_ns, t1_ns, int(self.config.max_imu_gap_s * 1e9))

    def prior_holds_gauge(self, ids: list[int]) -> bool:
        """True when the BA of window ``ids`` gets a marginalisation prior (it then fixes no keyframe)."""
        return (self.metric and self.marginal is not None and len(ids) >= 2
                and set(self.marginal.ids) <= set(ids)
                and self.imu_covers(self.states[ids[0]].t_ns, self.states[ids[-1]].t_ns))

    def bias_of(self, kf_id: int) -> torch.Tensor:
        """(6,) bias of a keyframe (the global one without per-keyframe biases)."""
        return self.states[kf_id].bias if self.config.per_keyframe_bias else self.global_bias

    # ------------------------------------------------------------------ keyframes
    def add_keyframe(self, kf_id: int, t_ns: int, velocity: torch.Tensor | None = None) -> None:
        """Register a keyframe (ids increase with time); velocity and bias start from the previous keyframe."""
        prev_id = max(self.states) if self.states else None
        prev = None if prev_id is None else self.states[prev_id]
        if prev is not None and int(t_ns) <= prev.t_ns:
            raise ValueError(f"keyframe {kf_id} at {t_ns} ns is not after the previous keyframe ({prev.t_ns} ns)")
        v = velocity if velocity is not None else (prev.velocity.clone() if prev else torch.zeros(3, dtype=F64))
        b = prev.bias.clone() if prev else self.global_bias.clone()
        self.states[kf_id] = KeyframeInertial(int(t_ns), v.to(F64), b)
        last = self._last_predicted
        if last is not None and last[0] == prev_id and int(last[1].t1_ns) == int(t_ns):
            # the frame that became this keyframe was predicted from the previous keyframe: that preintegration is
            # the pair's (same stamps; preintegrations() still re-integrates it if the bias moved since)
            self._pre[(prev_id, kf_id)] = last[1]
        self._last_predicted = None

    def preintegrations(self, pairs: list[tuple[int, int]]) -> Preintegrated:
        """Preintegrations from keyframe ``i`` to ``j`` at ``i``'s bias for each ``(i, j)`` of ``pairs``, batched
        (B = len(pairs)). Cached per pair; the stale ones (none yet, or the bias moved more than
        ``relinearize_bias_threshold`` from its linearisation bias) are re-integrated in one vectorised pass."""
        stale = []
        for i, j in pairs:
            pre = self._pre.get((i, j))
            if pre is None or float((self.bias_of(i) - torch.cat((pre.bias_gyro, pre.bias_acc))).norm()) > \
                    self.config.relinearize_bias_threshold:
                stale.append((i, j))
        if stale:
            b = torch.stack([self.bias_of(i) for i, _ in stale])
            batch = preintegrate_intervals(self.imu, [self.states[i].t_ns for i, _ in stale],
                                           [self.states[j].t_ns for _, j in stale], self.noise, b[:, :3], b[:, 3:],
                                           self.config.scheme)
            for n, pair in enumerate(stale):
                self._pre[pair] = batch.item(n)
        return stack_preintegrated([self._pre[pair] for pair in pairs])

    def predict(self, ref_id: int, T_cw_ref: torch.Tensor, t_ns: int) -> KeyframePrediction | None:
        """IMU prediction of the pose at ``t_ns`` from keyframe ``ref_id`` (VIGS-SLAM keyframe initialisation,
        with the tau fallback); None before the map is metric or when disabled."""
        c = self.config
        if not (c.enabled and c.imu_keyframe_init and self.metric):
            return None
        ref = self.states[ref_id]
        if int(t_ns) <= ref.t_ns or not self.imu_covers(ref.t_ns, int(t_ns)):
            return None
        b = self.bias_of(ref_id)
        pre = preintegrate(self.imu, ref.t_ns, int(t_ns), self.noise, b[:3], b[3:], c.scheme)
        self._last_predicted = (ref_id, pre)
        pred = predict_keyframe(T_cw_ref, ref.velocity, b, pre, self.T_cb, self.gravity_world(),
                                c.keyframe_init_max_cov_trace)
        if pred.from_imu:
            self.imu_predictions += 1
        else:
            self.fallbacks += 1
        return pred

    def predict_rotation(self, ref_id: int, T_cw_ref: torch.Tensor, t_ns: int) -> torch.Tensor | None:
        """Before the map is metric: the camera rotation ``R_cw`` (3, 3) at ``t_ns`` from the gyro alone,
        ``R_wb = R_wb,ref dR`` (rotation needs neither scale nor gravity); None once metric (:meth:`predict`
        gives the full state then) or when disabled."""
        c = self.config
        if not (c.enabled and c.imu_keyframe_init) or self.metric:
            return None
        ref = self.states[ref_id]
        if int(t_ns) <= ref.t_ns or not self.imu_covers(ref.t_ns, int(t_ns)):
            return None
        dR = preintegrate_rotation(self.imu, ref.t_ns, int(t_ns), self.bias_of(ref_id)[:3], self.noise.rate_hz)
        R_cb = self.T_cb[:3, :3]
        R_wb = T_cw_ref[:3, :3].to(F64).T @ R_cb
        return (R_wb @ dR @ R_cb.T).T

    # ------------------------------------------------------------------ BA
    def terms(self, ids: list[int], poses: torch.Tensor,
              anchored: set[int] | None = None) -> tuple[InertialTerms, InertialState] | None:
        """Inertial terms and state of a BA window of consecutive keyframes ``ids`` (oldest first), or None
        when no inertial terms apply (vision-only stage, fusion off, fewer than two keyframes, no IMU data over
        the window). An interval with an IMU gap over ``max_imu_gap_s`` gets no inertial factor (weight 0): once
        metric the rest of the window keeps its factors, and a keyframe left without any keeps its velocity and
        bias through the anchor; before that the whole window is vision-only. Once metric, the window gets the
        marginalisation prior when one exists (:meth:`marginalize`); otherwise the keyframes in ``anchored`` (the
        window's fixed ones) keep their velocity and bias through an
        :class:`~vigs_core.vio.inertial_terms.AnchorPrior`. Cached preintegrations of pairs older than the window
        are dropped: windows only move forward, so a long run keeps one window's worth."""
        c = self.config
        if not c.enabled or self.stage == Stage.VISION_ONLY or len(ids) < 2:
            return None
        pairs = list(zip(ids[:-1], ids[1:]))
        covered = [self.imu_covers(self.states[i].t_ns, self.states[j].t_ns) for i, j in pairs]
        if not all(covered) and not (self.metric and any(covered)):
            return None
        joint = self.stage == Stage.JOINT_UNALIGNED
        for old in [pair for pair in self._pre if pair[0] < ids[0]]:   # the window only moves forward
            del self._pre[old]
        stand_in = pairs[covered.index(True)]   # an interval across a gap is not integrated: weight 0, any stand-in
        pre = self.preintegrations([p if ok else stand_in for p, ok in zip(pairs, covered)])
        prior = _bias_stds(c.bias_prior_gyro_std, c.bias_prior_acc_std)
        vel = torch.stack([self.states[k].velocity for k in ids])
        biases = torch.stack([self.states[k].bias for k in ids]) if c.per_keyframe_bias else self.global_bias[None]
        # keyframes without an inertial interval (inside an IMU gap): nothing but the anchor holds their velocity
        isolated = [not ((n > 0 and covered[n - 1]) or (n < len(covered) and covered[n])) for n in range(len(ids))]
        anchor, marginal, index = None, None, None
        if self.prior_holds_gauge(ids):
            marginal, index = self.marginal, [ids.index(k) for k in self.marginal.ids]
        elif self.metric and (anchored or any(isolated)) and c.anchor_velocity_std > 0:
            mask = torch.tensor([k in (anchored or ()) or isolated[n] for n, k in enumerate(ids)])
            all_biases = torch.stack([self.bias_of(k) for k in ids])
            anchor = AnchorPrior(mask, vel.clone(), all_biases, c.anchor_velocity_std,
                                 _bias_stds(c.anchor_bias_gyro_std, c.anchor_bias_acc_std))
        elif any(isolated):
            return None
        terms = InertialTerms(pre, self.T_cb, estimate_bias=c.estimate_bias, per_keyframe_bias=c.per_keyframe_bias,
                              estimate_gravity=joint, estimate_scale=joint, gravity=c.gravity,
                              weight=c.inertial_weight, bias_prior_std=prior, anchor=anchor, marginal=marginal,
                              marginal_index=index,
                              interval_weight=None if all(covered) else torch.tensor(covered, dtype=F64))
        state = InertialState(vel, biases.clone(), self.R_wg.clone(), torch.tensor(self.log_scale, dtype=F64))
        return terms, state

    def marginalize(self, ids: list[int], poses: torch.Tensor,
                    visual: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
        """Keyframe ``ids[0]`` leaves the window ``ids`` (consecutive, oldest first, world->camera ``poses``
        (N, 4, 4) at the current estimate): fold its inertial factor to ``ids[1]``, its bias prior, the reduced
        camera system ``visual`` of its hosted edges and the current prior into the prior over ``ids[1:]``
        (:mod:`vigs_core.vio.marginalization`). Only once metric with ``marginalize`` on; without IMU data over
        the interval the prior is dropped (the window then falls back to a fixed keyframe and the anchor)."""
        c = self.config
        if not (c.enabled and c.marginalize and self.metric) or len(ids) < 2:
            return
        if not self.imu_covers(self.states[ids[0]].t_ns, self.states[ids[1]].t_ns):
            self.marginal = None
            return
        vel = torch.stack([self.states[k].velocity for k in ids])
        biases = torch.stack([self.states[k].bias for k in ids]) if c.per_keyframe_bias else self.global_bias[None]
        self.marginal = marginalize_keyframe(
            self.marginal, list(ids), poses, vel, biases, self.preintegrations([(ids[0], ids[1])]),
            self.T_cb, estimate_bias=c.estimate_bias, per_keyframe_bias=c.per_keyframe_bias, gravity=c.gravity,
            weight=c.inertial_weight, bias_prior_std=_bias_stds(c.bias_prior_gyro_std, c.bias_prior_acc_std),
            visual=visual,
            anchor_std=(c.anchor_velocity_std, _bias_stds(c.anchor_bias_gyro_std, c.anchor_bias_acc_std)))
        self.marginalized += 1

    def update(self, ids: list[int], state: InertialState) -> None:
        """Store the velocities, biases (and joint gravity/scale) a BA returned for window ``ids``."""
        for n, k in enumerate(ids):
            self.states[k].velocity = state.velocities[n].clone()
            if self.config.per_keyframe_bias:
                self.states[k].bias = state.biases[n].clone()
        if not self.config.per_keyframe_bias:
            self.global_bias = state.biases[0].clone()
            for k in ids:
                self.states[k].bias = self.global_bias.clone()
        if self.stage == Stage.JOINT_UNALIGNED:
            self.R_wg, self.log_scale = state.R_wg.clone(), float(state.log_scale)

    # ------------------------------------------------------------------ stages
    def on_keyframe(self, ids: list[int], stamps_ns: np.ndarray, poses: torch.Tensor) -> WorldAlignment | None:
        """Advance the initialisation after a keyframe's BA, with ALL keyframes so far (ids (K,), stamps (K,),
        world->camera poses (K, 4, 4)). Returns the alignment the caller must apply to poses and disparities
        (velocities here are already updated), or None."""
        before = self.stage
        outcome = self.initializer.on_keyframe(np.asarray(stamps_ns), poses)
        t_ns = int(stamps_ns[-1])
        if outcome is not None:
            bias = outcome.bias if self.config.bias_from_inertial_init else None
            for n, k in enumerate(ids):
                self.states[k].velocity = outcome.velocities[n].clone()
                if bias is not None:
                    self.states[k].bias = bias.clone()
            if bias is not None:
                self.global_bias = bias.clone()
            self._finish(outcome.alignment, t_ns, len(ids))
            self.reinitialisations += bool(self.failures)
            return outcome.alignment
        if before == Stage.VISION_ONLY and self.stage == Stage.JOINT_UNALIGNED:
            self._start_joint(ids, stamps_ns, poses)
        if self.stage == Stage.JOINT_UNALIGNED:
            self.scale_history.append({"t_ns": t_ns, "keyframes": len(ids), "stage": self.stage.value,
                                       "scale": float(np.exp(self.log_scale))})
            alignment = self.initializer.finish_joint(len(ids), self.R_wg, self.log_scale)
            if alignment is not None:
                for k in ids:
                    self.states[k].velocity = alignment.velocity(self.states[k].velocity)
                self._finish(alignment, t_ns, len(ids))
                return alignment
        return None

    def hold_delay_passed(self, t_ns: int) -> bool:
        """True when the map has been metric for ``metric_hold_delay_s`` at ``t_ns``."""
        return self.metric and (int(t_ns) - self.metric_since_ns) * 1e-9 >= self.config.metric_hold_delay_s

    def scale_check_due(self, t_ns: int) -> bool:
        """True when the scale check should run at a keyframe at ``t_ns``: metric for ``metric_hold_delay_s`` and
        no trustworthy check yet since the alignment."""
        return self.config.enabled and not self.scale_checked and self.hold_delay_passed(t_ns)

    def check_scale(self, ids: list[int], stamps_ns: np.ndarray, poses: torch.Tensor,
                    between: Callable[[], None] | None = None) -> WorldAlignment | None:
        """The scale check: the inertial-only problem of the initialisation
        (:func:`~vigs_core.imu.inertial_init.inertial_only_init`: gravity direction, scale, velocities and biases
        with the poses fixed) over the keyframes since the map became metric (at most ``3 inertial_init_keyframes``
        of them; ids (K,), stamps (K,) ns, world->camera poses (K, 4, 4) of ALL keyframes), i.e. seconds of joint
        VI-BA poses instead of the vision-only stage's. An untrustworthy solution is retried at the next keyframes
        (at most ``inertial_init_keyframes`` tries; then the check is given up until the next alignment).
        A trustworthy one whose ``|log scale|`` exceeds ``max_scale_drift`` is a failure (:meth:`fail`). Otherwise,
        with ``scale_refinement`` (ORB-SLAM3's, Campos et al., T-RO 2021, Sec. V-C), the alignment the caller must
        apply to the whole map (velocities here are already updated; the biases stay the VI-BA's), else None.
        ``between`` is called after each iteration of the solve (a live caller's yield point)."""
        c = self.config
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        sel = np.nonzero(stamps_ns >= self.metric_since_ns)[0][-3 * c.inertial_init_keyframes:]
        res = self._inertial_only(sel, stamps_ns, poses, between) if len(sel) >= 3 else None
        if res is None:
            return None
        self.scale_history.append({"t_ns": int(stamps_ns[-1]), "keyframes": len(ids), "stage": "scale_check",
                                   "scale": res.scale, "log_scale_std": res.log_scale_std,
                                   "trustworthy": res.trustworthy})
        if not res.trustworthy:   # retried at the next keyframes, at most inertial_init_keyframes times
            tries = sum(h["stage"] == "scale_check" for h in self.scale_history
                        if h["t_ns"] >= self.metric_since_ns)
            self.scale_checked = tries >= c.inertial_init_keyframes
            return None
        self.scale_checked = True
        if abs(res.log_scale) > c.max_scale_drift:
            since_s = (int(stamps_ns[-1]) - self.metric_since_ns) * 1e-9
            self.fail(int(stamps_ns[-1]), f"the scale did not hold: the check {since_s:.1f} s after the alignment "
                                          f"found scale {res.scale:.3f}")
            return None
        if not c.scale_refinement or abs(res.log_scale) < c.scale_refinement_min_sigmas * res.log_scale_std:
            return None
        self.scale_history[-1]["refined"] = True
        alignment = alignment_from_gravity(res.R_wg, res.log_scale)
        refit = {ids[n]: res.velocities[m] for m, n in enumerate(sel)}
        for k in ids:
            self.states[k].velocity = alignment.velocity(refit.get(k, self.states[k].velocity))
        return alignment

    def monitor_scale(self, ids: list[int], stamps_ns: np.ndarray, poses: torch.Tensor,
                      between: Callable[[], None] | None = None) -> str | None:
        """The rolling scale check, after each keyframe's BA once the scale check is done (arguments as
        :meth:`check_scale`): every ``scale_monitor_every`` keyframes the scale check's inertial-only problem over
        the last ``inertial_init_keyframes`` keyframes. A well-conditioned solution (log-scale std within
        ``scale_monitor_max_std``) whose ``|log scale|`` exceeds ``scale_monitor_max_drift`` is a strike, one
        within it clears the strikes and moves ``scale_verified_ns``. Returns why the state is divergent after
        ``scale_monitor_strikes`` strikes in a row (the caller then calls :meth:`fail`), else None."""
        c = self.config
        if not (c.enabled and c.scale_monitor_every and self.metric and self.scale_checked):
            return None
        self._monitor_wait += 1
        if self._monitor_wait < c.scale_monitor_every:
            return None
        stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        sel = np.nonzero(stamps_ns >= self.metric_since_ns)[0][-c.inertial_init_keyframes:]
        if len(sel) < c.inertial_init_keyframes:
            return None
        self._monitor_wait = 0
        res = self._inertial_only(sel, stamps_ns, poses, between)
        if res is None or not res.log_scale_std <= c.scale_monitor_max_std:
            return None
        self.scale_monitor["checks"] += 1
        if abs(res.log_scale) <= c.scale_monitor_max_drift:
            self._monitor_strikes = 0
            self.scale_verified_ns = int(stamps_ns[sel[-1]])
            return None
        self.scale_monitor["deviating"] += 1
        self._monitor_strikes += 1
        if self._monitor_strikes < c.scale_monitor_strikes:
            return None
        span_s = (int(stamps_ns[sel[-1]]) - int(stamps_ns[sel[0]])) * 1e-9
        return (f"the scale drifted: the IMU over the last {len(sel)} keyframes ({span_s:.1f} s) finds scale "
                f"{res.scale:.3f} (+-{100 * res.log_scale_std:.1f}%), {self._monitor_strikes} checks in a row")

    def _inertial_only(self, sel: np.ndarray, stamps_ns: np.ndarray, poses: torch.Tensor,
                       between: Callable[[], None] | None):
        """The inertial-only problem over keyframes ``sel`` with their poses fixed (the scale checks' solve;
        ``scale_check_pose_noise``), or None when the IMU does not cover them or the problem is singular."""
        c = self.config
        if not self.imu_covers(int(stamps_ns[sel[0]]), int(stamps_ns[sel[-1]])):
            return None
        cfg = self.initializer.inertial_config()
        if c.scale_check_pose_noise is not None:
            cfg = replace(cfg, pose_position_std=c.scale_check_pose_noise[0],
                          pose_rotation_std=c.scale_check_pose_noise[1])
        try:
            return inertial_only_init(se3_inverse(poses[sel].to(F64)), stamps_ns[sel], self.imu, self.noise,
                                      self.T_cb, cfg, between=between)
        except torch.linalg.LinAlgError:
            return None

    def health(self, ids: list[int], stamps_ns: np.ndarray, poses: torch.Tensor) -> str | None:
        """Once metric, after the BA of the newest keyframe ``ids[-1]`` (ids, stamps (K,) ns and world->camera
        poses (K, 4, 4) of all keyframes): why its state is divergent (module docstring), or None."""
        c = self.config
        if not (c.enabled and self.metric) or not ids:
            return None
        new = self.states[ids[-1]]
        b = self.bias_of(ids[-1])
        speed, b_g, b_a = float(new.velocity.norm()), float(b[:3].norm()), float(b[3:].norm())
        if not (speed <= c.max_speed and b_g <= c.max_bias_gyro and b_a <= c.max_bias_acc):
            return (f"implausible state: speed {speed:.3g} m/s (max {c.max_speed:g}), gyro bias {b_g:.3g} rad/s "
                    f"(max {c.max_bias_gyro:g}), accelerometer bias {b_a:.3g} m/s^2 (max {c.max_bias_acc:g})")
        if len(ids) >= 2:
            p = se3_inverse(poses[-2:].to(F64))[:, :3, 3]
            jump, dt = float((p[1] - p[0]).norm()), (int(stamps_ns[-1]) - int(stamps_ns[-2])) * 1e-9
            if not jump <= c.max_speed * dt + _JUMP_SLACK_M:
                return f"pose jump: {jump:.3g} m in {dt:.3f} s between keyframes (max speed {c.max_speed:g} m/s)"
        return None

    def fail(self, t_ns: int, reason: str) -> None:
        """A failure at ``t_ns``: forget the inertial state and initialise again on the current map."""
        self.failures.append({"t_ns": int(t_ns), "reason": reason})
        self.initializer.restart(len(self.states))
        self.alignment = None
        self.metric_since_ns = None
        self.scale_checked = False
        self.scale_verified_ns = None
        self._monitor_wait = self._monitor_strikes = 0
        self.marginal = None
        self.R_wg, self.log_scale = torch.eye(3, dtype=F64), 0.0
        self.global_bias = torch.zeros(6, dtype=F64)
        for st in self.states.values():
            st.velocity, st.bias = torch.zeros(3, dtype=F64), torch.zeros(6, dtype=F64)
        self._pre.clear()
        self._last_predicted = None

    def _start_joint(self, ids: list[int], stamps_ns: np.ndarray, poses: torch.Tensor) -> None:
        """Without staging: gravity from the accelerometer, scale 1, velocities by finite differences."""
        T_wc = torch.linalg.inv(poses.to(F64))
        t0 = int(stamps_ns[0])
        t1 = max(int(stamps_ns[1]), t0 + 500_000_000) if len(stamps_ns) > 1 else t0 + 500_000_000
        self.R_wg = gravity_from_accelerometer(self.imu, t0, t1, T_wc[0], self.T_cb)
        self.log_scale = 0.0
        p = T_wc[:, :3, 3]
        dt = torch.as_tensor(np.diff(np.asarray(stamps_ns, dtype=np.int64)) * 1e-9, dtype=F64)
        v = torch.zeros_like(p)
        v[1:] = (p[1:] - p[:-1]) / dt[:, None]
        v[0] = v[1] if len(ids) > 1 else v[0]
        for n, k in enumerate(ids):
            self.states[k].velocity = v[n]

    def _finish(self, alignment: WorldAlignment, t_ns: int, keyframes: int) -> None:
        self.alignment = alignment
        self.metric_since_ns = t_ns
        self.scale_verified_ns = t_ns
        self._monitor_wait = self._monitor_strikes = 0
        self.marginal = None
        self.R_wg = torch.eye(3, dtype=F64)
        self.log_scale = 0.0
        self._pre.clear()
        self.scale_history.append({"t_ns": t_ns, "keyframes": keyframes, "stage": "aligned",
                                   "scale": alignment.scale})

    def report(self) -> dict:
        """JSON-ready summary: stage, scale history, init attempts, latest biases, IMU prediction counts."""
        last = self.states[max(self.states)] if self.states else None
        return {
            "stage": self.stage.value,
            "metric": self.metric,
            "scale": None if self.alignment is None else self.alignment.scale,
            "scale_history": self.scale_history,
            "init_attempts": self.initializer.attempts,
            "bias_gyro": None if last is None else [float(x) for x in self.bias_of(max(self.states))[:3]],
            "bias_acc": None if last is None else [float(x) for x in self.bias_of(max(self.states))[3:]],
            "imu_predictions": self.imu_predictions,
            "imu_prediction_fallbacks": self.fallbacks,
            "marginalized_keyframes": self.marginalized,
            "scale_monitor": self.scale_monitor,
            "failures": self.failures,
            "reinitialisations": self.reinitialisations,
        }
