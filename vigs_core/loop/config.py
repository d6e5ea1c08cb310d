"""Settings of loop closure (VIGS-SLAM Sec. 3.1, "loop closure and PGBA"): detection, verification, loop-edge
estimation, the relative-pose graph and the PGBA worker. Defaults are the paper's values where it gives them
(keyframe gap 55, mean flow 22 px, orientation 120 deg) and ours elsewhere (documented per field)."""
from __future__ import annotations

from dataclasses import dataclass, field

from vigs_core.loop.pose_graph import PoseGraphConfig
from vigs_core.ranges import bounded
from vigs_core.spill import SpillConfig


@dataclass
class LoopDetectionConfig:
    """Which old keyframes a new keyframe is compared with.

    Args:
        min_keyframe_gap: a candidate is at least this many keyframes older than the new one (paper: 55).
        max_mean_flow_px: candidate when the confidence-weighted mean flow magnitude of the dense
            correspondences new -> old is below this, pixels at input resolution (paper: 22).
        max_orientation_deg: candidate only when the current estimates' relative orientation is below this,
            degrees (paper: 120).
        min_mean_confidence: and only when the mean correspondence confidence exceeds this, [0, 1] (ours: a
            flow field without confident matches says nothing about the flow magnitude).
        max_flow_checks: dense flow is computed for at most this many old keyframes per new keyframe: those
            passing the orientation test with the highest thumbnail correlation (ours; bounds the cost).
        max_check_rotation_deg: of those, only the ones whose current estimated relative rotation is below this
            get the flow (ours; saves the flows of candidates that would fail): a loop the verification accepts
            corrects the estimate by at most ``max_drift_rotation_deg``, and a mean flow below
            ``max_mean_flow_px`` leaves little true rotation (measured on whole sequences: docs/benchmarks.md).
        thumbnail_size: (width, height) of the zero-mean, unit-norm grey thumbnails used for that ranking.
        min_keyframes_between_loops: after an accepted loop, new keyframes this close to it are not
            searched again (avoids stacking near-identical loop edges; ours).
    """

    min_keyframe_gap: int = bounded(55, 0)
    max_mean_flow_px: float = bounded(22.0, 0)
    max_orientation_deg: float = bounded(120.0, 0, 180)
    min_mean_confidence: float = bounded(0.1, 0, 1)
    max_flow_checks: int = bounded(3, 0)
    max_check_rotation_deg: float = bounded(50.0, 0, 180)
    thumbnail_size: tuple[int, int] = (32, 24)
    min_keyframes_between_loops: int = bounded(5, 0)


@dataclass
class LoopVerificationConfig:
    """Geometric verification of a candidate and the loop edge's relative Sim(3) (see :mod:`.two_view`).

    Args:
        min_confidence: correspondences with a (forward-backward x photometric) confidence below this are
            not used, [0, 1].
        min_confident_fraction: at least this fraction of the grid must have confident correspondences in
            both directions (new -> old and old -> new).
        pnp_reprojection_px: RANSAC inlier threshold of the PnP initialisation, pixels.
        min_inlier_fraction: after the Sim(3) refinement, at least this fraction of the confident
            correspondences must reproject within ``inlier_px`` AND agree in depth (both directions).
        inlier_px: reprojection inlier threshold, pixels.
        max_log_depth_ratio: depth agreement: ``|log(z_predicted / z_measured)|`` below this.
        depth_sigma: standard deviation of the log-depth residuals of the refinement (the keyframes' depth
            maps disagree by this relative amount; ours).
        refine_iterations: Gauss-Newton iterations of the two-view Sim(3) refinement.
        max_drift_fraction: the loop's correction of the current relative estimate (translation) may be at
            most this fraction of the path length between the two keyframes, plus ``min_drift_m`` (ours:
            a repeated texture far away along the path fakes a loop that odometry cannot have drifted to).
        min_drift_m: the translation allowance of a loop between nearby keyframes, in map units.
        max_drift_rotation_deg: the loop's rotation correction of the current relative estimate at most.
        max_drift_log_scale: the loop's scale correction at most ``exp(+-this)``.
        information_scale: multiplies the dense two-view information (the dense residuals are correlated,
            so their Gauss-Newton information is over-confident; ours).
    """

    min_confidence: float = bounded(0.3, 0, 1)
    min_confident_fraction: float = bounded(0.3, 0, 1)
    pnp_reprojection_px: float = bounded(2.0, 0)
    min_inlier_fraction: float = bounded(0.6, 0, 1)
    inlier_px: float = bounded(2.0, 0, lo_open=True)
    max_log_depth_ratio: float = bounded(0.15, 0)
    depth_sigma: float = bounded(0.05, 0, lo_open=True)
    refine_iterations: int = bounded(8, 0)
    max_drift_fraction: float = bounded(0.2, 0)
    min_drift_m: float = bounded(0.1, 0)
    max_drift_rotation_deg: float = bounded(20.0, 0, 180)
    max_drift_log_scale: float = bounded(0.5, 0)
    information_scale: float = bounded(0.01, 0, lo_open=True)


@dataclass
class LoopGraphConfig:
    """Odometry edges of the relative-pose graph.

    Args:
        odometry_neighbours: each new keyframe gets edges to this many previous keyframes (its local window).
        sigma_rotation_rad: standard deviation of an odometry edge's rotation per unit of information scale,
            used when no dense-correspondence information is given for the edge, radians.
        sigma_translation_m: likewise for translation, map units.
        sigma_log_scale: standard deviation of an odometry edge's log scale (the dense reprojection of one
            direction does not observe it).
        sigma_metric_log_scale: every keyframe created while the visual-inertial odometry is metric gets an
            absolute prior of this standard deviation on its log scale in PGBA (the IMU observes the scale at each
            such keyframe, so loops correct mostly position and orientation; ours). Loose enough for loops to
            correct the few percent the metric odometry's scale can drift (9 % within 30 s of hybrid MH_03 from
            90 s; 0.002 held it there).
        sigma_metric_gravity_rad: each such keyframe's gravity direction (roll and pitch) gets an
            absolute prior of this standard deviation (rad) at its value before PGBA: the IMU observes them, so a
            loop corrects position and yaw (VINS-Mono's 4-DoF loop graph, softly) and does not tilt the world.
            0 (default): no such prior; measured no better (docs/benchmarks.md, "Estimator robustness").
    """

    odometry_neighbours: int = bounded(1, 1)
    sigma_rotation_rad: float = bounded(0.002, 0, lo_open=True)
    sigma_translation_m: float = bounded(0.005, 0, lo_open=True)
    sigma_log_scale: float = bounded(0.01, 0, lo_open=True)
    sigma_metric_log_scale: float = bounded(0.02, 0, lo_open=True)
    sigma_metric_gravity_rad: float = bounded(0.0, 0)


@dataclass
class LoopConfig:
    """Loop closure as a whole.

    Args:
        enabled: run loop closure in the pipeline (``loop.enabled``).
        detection, verification, graph: see the respective dataclasses.
        pose_graph: Sim(3) LM settings of the PGBA (Huber on loop edges).
        asynchronous: run detection and PGBA beside tracking (False: run them inline, for tests).
        process: asynchronous work in a child process (:mod:`vigs_core.loop.process`) rather than a thread of the
            tracking process (the loop-closure thread's Python work made tracking wait for the interpreter lock);
            used by the in-process pipeline's :class:`~vigs_core.loop.driver.LoopClosureDriver`.
        process_nice: niceness increment of that child process: on a saturated CPU tracking keeps its core.
        images: where the detector keeps keyframe images for verification (the most recent in memory, older
            ones spilled to disk: memory does not grow with the number of keyframes).
    """

    enabled: bool = True
    detection: LoopDetectionConfig = field(default_factory=LoopDetectionConfig)
    verification: LoopVerificationConfig = field(default_factory=LoopVerificationConfig)
    graph: LoopGraphConfig = field(default_factory=LoopGraphConfig)
    pose_graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    asynchronous: bool = True
    process: bool = True
    process_nice: int = 10
    images: SpillConfig = field(default_factory=SpillConfig)
