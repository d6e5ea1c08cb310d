"""Settings of the visual-inertial back end (VIGS-SLAM Sec. 3.2-3.3), including the ablation switches of
VIGS-SLAM Table 6.

The ablations map onto the switches as follows:

* "w/o IMU fusion": ``enabled=False`` -- vision-only BA throughout; no initialisation, no metric scale.
* "w/o bias estimation": ``estimate_bias=False, bias_from_inertial_init=False`` -- biases are not states and
  stay zero (with ``bias_from_inertial_init`` they would stay at the inertial-only stage's estimate).
* "w/o staged initialisation": ``staged_init=False`` -- no vision-only warm-up and no inertial-only stage: as
  soon as ``vision_only_keyframes`` keyframes exist, joint VI-BA starts with the gravity direction and the
  log-scale as additional free states, initialised from the mean accelerometer reading (gravity) and scale 1.
* "w/o IMU keyframe initialisation": ``imu_keyframe_init=False`` -- new frames/keyframes are initialised by the
  visual front end's own motion model instead of IMU preintegration.
* "single global bias": ``per_keyframe_bias=False`` -- one bias shared by the whole window instead of one per
  keyframe (no bias-smoothness residuals).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from vigs_core.ranges import bounded


@dataclass
class VioConfig:
    """Visual-inertial settings (defaults: the paper's values for EuRoC).

    Args:
        enabled: fuse the IMU at all (False = the "w/o IMU fusion" ablation, and the vision-only pipeline).
        estimate_bias: biases are optimised states (False = "w/o bias estimation").
        per_keyframe_bias: one bias per keyframe with smoothness residuals (False = one global bias).
        staged_init: three-stage initialisation (False = "w/o staged initialisation", see the module docstring).
        imu_keyframe_init: initialise new frames/keyframes from IMU preintegration (False = the front end's
            motion model, "w/o IMU keyframe initialisation").
        vision_only_keyframes: keyframes of the vision-only stage before inertial data are used (paper: 10).
        inertial_init_keyframes: keyframe count at which the inertial-only stage runs (paper: 20).
        keyframe_init_max_cov_trace: tau of the IMU keyframe initialisation: when the trace of the
            preintegration covariance of (rotation, velocity, position) exceeds it, the new pose falls back to
            the previous keyframe's pose (paper: 1e-4; units mixed rad^2, (m/s)^2, m^2 as in the paper).
        gravity: gravity magnitude, m/s^2.
        inertial_weight: multiplies the inertial information matrices relative to the visual terms (whose
            residuals are in pixels with unit weight per confidence). 0.03 amounts to noise densities 5.8x the
            datasheet's, which understate the vibrating EuRoC platform's noise 4-9x (``vigs imu-check``).
            First 30 s of hybrid V1_01 / V2_01 / MH_03, SE(3) ATE: weight 1 gave 1.8 / 4.5 / 8.4 cm at frame
            stride 1 and 1.8 / 5.1 / 6.3 cm (MH_03 recall@10cm 90%) at stride 10; 0.1 gave 1.4 / 3.5 / 6.6 and
            2.5 / 5.2 / 5.2 cm; with the later front-end defaults (edge flow at full resolution) 0.1 gave
            MH_03 7.5 cm at stride 1 and 2.3 / 5.1 / 6.6 cm (MH_03 recall 87%) at stride 10, 0.03 gave MH_03
            6.7 cm and 2.6 / 5.8 / 5.5 cm (recall 95%).
        bias_prior_gyro_std: zero-mean prior on each gyroscope bias state, rad/s (keeps unobservable directions
            bounded).
        bias_prior_acc_std: zero-mean prior on each accelerometer bias state, m/s^2.
        bias_from_inertial_init: start the biases from the inertial-only estimate (else zero).
        relinearize_bias_threshold: re-preintegrate an interval when its bias estimate moved further than this
            from the linearisation bias (Euclidean norm of the 6-vector), rad/s and m/s^2.
        max_init_log_scale_std: the inertial-only stage is accepted when the standard deviation of its log-scale
            is below this; otherwise it is retried at the next keyframe.
        max_init_gravity_std_deg: same for the gravity direction, degrees.
        init_bias_random_walk: the inertial-only stage estimates one bias per keyframe tied by the random walk
            (:class:`~vigs_core.imu.inertial_init.InertialInitConfig` ``bias_random_walk``) instead of one
            bias for its window.
        scheme: preintegration scheme (see :mod:`vigs_core.imu.preintegration`).
        max_imu_gap_s: the IMU is not integrated across a gap longer than this (s): a frame whose interval holds
            such a gap gets no IMU prediction (tracked vision-only against the metric map), a keyframe interval
            across it no inertial factor (the window's other intervals keep theirs; the window holds its fixed
            keyframe's depth at once, as the scale's only carrier), and a keyframe after it takes its velocity
            from the keyframe positions; before the initialisation, the inertial-only stage solves over the
            keyframes after the gap once there are ``inertial_init_keyframes`` of them. Integrating across it
            (the linear signal model) sent a 2 s gap's trajectory kilometres away.
        marginalize: once the map is metric, a keyframe leaving the BA window is marginalised into a Gaussian
            prior on the window's remaining poses, velocities and biases (:mod:`vigs_core.vio.marginalization`),
            and BA holds no keyframe fixed (the prior carries the gauge and the window's scale and velocity
            information). Off (default): ``metric_fixed_keyframes`` fixed keyframes with the anchor prior and
            the held depth. First 60 s of hybrid MH_03: SE(3) ATE 21.2 cm with it, 20.6 cm with the fixed keyframe
            and free depth, 11.8 cm with the held depth; the prior keeps the IMU's scale information, but the
            window's scale is then the IMU's alone, which on this sequence swings by 5% within seconds.
        marginalize_visual: the marginalisation includes the departing keyframe's hosted visual edges (its
            disparities eliminated); off, only its inertial factor and priors.
        metric_fixed_keyframes: without ``marginalize`` (and until the first marginalisation): once the map is
            metric, this many oldest window keyframes are held fixed in BA (1: rotation and position gauge only,
            the IMU observes the scale; 0 keeps the frame graph's count).
        metric_hold_fixed_disparity: once metric (after ``metric_hold_delay_s``), BA holds the disparities of
            the window's fixed keyframe as well as its pose, so its depth map carries the window's scale from one
            window to the next (with them free, vision is blind to the scale inside the window, whose scale is then
            the IMU's alone: on hybrid MH_03 the scale of 8-keyframe windows swung between 0.90 and 1.13 within
            seconds, and an interval whose images contradict the IMU is cheapest explained by rescaling the whole
            window). First 60 s of hybrid MH_03 (HEAD 666b83e + this change): SE(3) ATE 20.6 -> 12.9 cm, Sim(3)
            19.2 -> 5.7 cm. Not applied with ``marginalize`` (no keyframe is fixed there).
        metric_hold_delay_s: seconds after the map became metric before the depth is held: the held depth keeps
            whatever scale the window has, so the IMU first corrects the inertial-only stage's scale with the
            depth free (first 60 s of hybrid V2_01: 0 s froze a 3.6% scale error, SE(3) ATE 9.0 cm; 10 s: 0.2%,
            4.0 cm; MH_03: 11.8 / 12.9 cm).
        scale_refinement: rescale the whole map once by the scale check's solution (see ``max_scale_drift``:
            gravity direction and scale re-estimated inertial-only over the keyframes since the alignment, poses
            fixed; ORB-SLAM3's scale refinement,
            :meth:`~vigs_core.vio.estimator.VisualInertialEstimator.check_scale`), so the depth is held at that
            scale rather than at the window's of that moment; only when the check is significant
            (``scale_refinement_min_sigmas``). Off by default: with ``scale_check_pose_noise`` (1e-4, 1e-4) it took
            whole hybrid MH_03 from 12.6 to 4.9 cm SE(3) ATE (V1_01, V2_01 unchanged), but the 30 s clip of V1_01
            from 90 s from 3.7 to 7.8 cm (a wrong 3-sigma check); docs/benchmarks.md.
        anchor_velocity_std: without ``marginalize`` (and at the first marginalisation, for the keyframe that
            was fixed): once metric, the velocities of the window's fixed keyframes are held at their last
            estimate with this standard deviation, m/s (the inertial counterpart of fixing their poses; 0 = off).
        anchor_bias_gyro_std: same for their gyroscope biases, rad/s.
        anchor_bias_acc_std: same for their accelerometer biases, m/s^2.
        max_speed: a body speed above this (m/s) is implausible: an inertial-only solution with such a keyframe
            velocity is refused, and a metric keyframe moving this fast is a failure (reset, initialise again).
        max_bias_gyro: a gyroscope bias norm above this (rad/s) is implausible (refused at initialisation, a
            failure once metric).
        max_bias_acc: the same for the accelerometer bias norm (m/s^2).
        max_init_gravity_error: an inertial-only solution is refused when the gravity magnitude of its closed-form
            initial values (free there; ``linear_gravity_norm``) is off ``gravity`` by more than this fraction: the
            poses and the IMU disagree (an accelerometer in other units or with a wrong scale factor, a wrong
            extrinsic). Over 579 attempts on hybrid EuRoC it stayed within 1.6%.
        scale_refinement_min_sigmas: with ``scale_refinement``, the map is rescaled only when the check's
            ``|log scale|`` is at least this many of its standard deviations (0: always): unrefined, the check
            alone (an earlier session) rescaled V2_01's right map by 3% (4.1 -> 4.9 cm).
        scale_check_pose_noise: ``(position m, rotation rad)`` noise the scale check's inertial-only problem
            assumes on the keyframe poses (None: the initialisation's, ``InertialInitConfig`` defaults: 2 mm,
            5 mrad). Given ground-truth poses, those defaults biased the inertial-only scale low by up to 15%
            (several of its standard deviations) where 0.1 mm / 0.1 mrad found it within 1-2%; on estimated
            poses 0.1 mm makes the check overconfident.
        init_agreement_log_scale: an inertial-only solution is accepted only when the attempt at the keyframe
            before was trustworthy and plausible too and their log-scales differ by less than this (a single
            well-conditioned solution can still be wrong; two successive windows agreeing rarely are).
        init_agreement_gravity_deg: the same for the angle between their gravity directions (deg).
        max_scale_drift: the scale check (at the first keyframe ``metric_hold_delay_s`` after the alignment,
            retried at up to ``inertial_init_keyframes`` later keyframes while its solution is not trustworthy)
            solves the inertial-only problem again over the keyframes since the alignment; when its
            ``|log scale|`` exceeds this the alignment did not hold: failure, back to vision-only, initialise again.
        scale_monitor_every: after the scale check, every this many keyframes (0 = off) the inertial-only problem
            is solved again over the last ``inertial_init_keyframes`` keyframes, poses fixed (a rolling scale
            check): a visual scale that drifts away from the IMU's while the VI-BA runs (its inertial terms
            absorbed into velocities and biases) shows as a window scale far from 1.
        scale_monitor_max_drift: a rolling check deviates when its ``|log scale|`` exceeds this (0.25: 28%) with a
            log-scale standard deviation within ``scale_monitor_max_std`` (windows of little acceleration are
            ill-conditioned and neither count nor clear).
        scale_monitor_max_std: see ``scale_monitor_max_drift``.
        scale_monitor_strikes: this many successive deviating checks are a failure; a consistent one clears them.
        still_max_flow_px: before the front end initialises, a frame whose mean flow from the first frame is
            below this (input pixels) is held at the first frame's pose (see :mod:`vigs_core.vio.odometry`).
    """

    enabled: bool = True
    estimate_bias: bool = True
    per_keyframe_bias: bool = True
    staged_init: bool = True
    imu_keyframe_init: bool = True
    vision_only_keyframes: int = bounded(10, 3)
    inertial_init_keyframes: int = bounded(20, 3)
    keyframe_init_max_cov_trace: float = bounded(1e-4, 0, lo_open=True)
    gravity: float = bounded(9.81, 0, lo_open=True)
    inertial_weight: float = bounded(0.03, 0, lo_open=True)
    bias_prior_gyro_std: float = bounded(0.1, 0, lo_open=True)
    bias_prior_acc_std: float = bounded(0.5, 0, lo_open=True)
    bias_from_inertial_init: bool = True
    relinearize_bias_threshold: float = bounded(0.01, 0)
    max_init_log_scale_std: float = bounded(0.02, 0)
    max_init_gravity_std_deg: float = bounded(2.0, 0)
    init_bias_random_walk: bool = True
    scheme: str = "closed_form"
    max_imu_gap_s: float = bounded(0.1, 0)
    marginalize: bool = False
    marginalize_visual: bool = True
    metric_fixed_keyframes: int = bounded(1, 0)
    metric_hold_fixed_disparity: bool = True
    metric_hold_delay_s: float = bounded(10.0, 0)
    scale_refinement: bool = False
    scale_refinement_min_sigmas: float = bounded(3.0, 0)
    scale_check_pose_noise: tuple[float, float] | None = None
    anchor_velocity_std: float = bounded(0.01, 0)
    anchor_bias_gyro_std: float = bounded(1e-3, 0, lo_open=True)
    anchor_bias_acc_std: float = bounded(1e-2, 0, lo_open=True)
    max_speed: float = bounded(10.0, 0, lo_open=True)
    max_bias_gyro: float = bounded(0.2, 0, lo_open=True)
    max_bias_acc: float = bounded(1.0, 0, lo_open=True)
    max_init_gravity_error: float = bounded(0.1, 0, lo_open=True)
    init_agreement_log_scale: float = bounded(0.05, 0, lo_open=True)
    init_agreement_gravity_deg: float = bounded(2.0, 0, lo_open=True)
    max_scale_drift: float = bounded(0.15, 0, lo_open=True)
    scale_monitor_every: int = bounded(10, 0)
    scale_monitor_max_drift: float = bounded(0.25, 0, lo_open=True)
    scale_monitor_max_std: float = bounded(0.05, 0, lo_open=True)
    scale_monitor_strikes: int = bounded(2, 1)
    still_max_flow_px: float = bounded(1.0, 0)

    def __post_init__(self) -> None:
        if self.vision_only_keyframes < 3 or self.inertial_init_keyframes < self.vision_only_keyframes:
            raise ValueError(f"VioConfig: vision_only_keyframes {self.vision_only_keyframes}, inertial_init_keyframes "
                             f"{self.inertial_init_keyframes}; expected 3 <= vision_only <= inertial_init")
        if self.keyframe_init_max_cov_trace <= 0 or self.inertial_weight <= 0:
            raise ValueError("VioConfig: keyframe_init_max_cov_trace and inertial_weight must be positive")
        limits = ("max_speed", "max_bias_gyro", "max_bias_acc", "max_init_gravity_error", "init_agreement_log_scale",
                  "init_agreement_gravity_deg", "max_scale_drift")
        if any(not getattr(self, name) > 0 for name in limits):
            raise ValueError("VioConfig: " + ", ".join(f"{n} {getattr(self, n)}" for n in limits)
                             + "; expected all positive")


ABLATIONS: dict[str, dict[str, Any]] = {
    "full": {},
    "no_bias_estimation": {"estimate_bias": False, "bias_from_inertial_init": False},
    "no_imu_fusion": {"enabled": False},
    "no_staged_init": {"staged_init": False},
    "no_imu_keyframe_init": {"imu_keyframe_init": False},
    "single_global_bias": {"per_keyframe_bias": False},
}
"""The rows of VIGS-SLAM Table 6 as overrides of :class:`VioConfig`."""
