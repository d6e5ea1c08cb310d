"""Staged initialisation on synthetic sequences with known scale and gravity, the map alignment, the
no-staging joint path, and IMU keyframe initialisation with its covariance fallback."""
import math

import numpy as np
import torch

from vigs_core.geometry import se3_inverse, so3_exp
from vigs_core.imu.analytic_motion import AnalyticMotion
from vigs_core.imu.buffer import ImuBuffer
from vigs_core.imu.preintegration import preintegrate
from vigs_core.solver import BAConfig, bundle_adjust, reproject
from vigs_core.types import ImuSamples
from vigs_core.vio.config import ABLATIONS, VioConfig
from vigs_core.vio.estimator import VisualInertialEstimator
from vigs_core.vio.initialization import Stage, StagedInitializer, WorldAlignment
from vigs_core.vio.keyframe_init import predict_keyframe
from vio_synthetic import INTR, NOISE, T_BC, T_CB, make_scenario, visual_problem

torch.set_num_threads(1)
F64 = dict(dtype=torch.float64)
DOWN = torch.tensor([0.0, 0.0, -1.0], **F64)


def _visual_frame(sc, factor, rot_noise_deg=0.0, seed=0):
    """What vision-only BA hands over: camera poses in the first camera frame, positions times ``factor``."""
    T = torch.linalg.inv(sc.T_wc[0]) @ sc.T_wc
    if rot_noise_deg > 0:
        g = torch.Generator().manual_seed(seed)
        axis = torch.nn.functional.normalize(torch.randn(len(T), 3, generator=g, **F64), dim=-1)
        T[:, :3, :3] = so3_exp(axis * math.radians(rot_noise_deg)) @ T[:, :3, :3]
    T[:, :3, 3] *= factor
    return se3_inverse(T)


def test_staged_initialisation_recovers_scale_and_gravity():
    for seed, factor in ((0, 0.37), (3, 2.5)):
        sc = make_scenario(n=21, spacing_s=0.3, seed=seed, bias_gyro=(0.002, -0.02, 0.01),
                           bias_acc=(0.05, -0.1, 0.08), imu_noise=True)
        T_cw = _visual_frame(sc, factor, rot_noise_deg=0.2, seed=seed)
        init = StagedInitializer(VioConfig(), sc.imu, NOISE, T_CB)
        outcomes = [init.on_keyframe(sc.stamps_ns[:K], T_cw[:K]) for K in range(3, 22)]
        # the first solution (20 keyframes) waits for the next one to agree with it
        assert all(o is None for o in outcomes[:-1]) and init.stage == Stage.VISUAL_INERTIAL
        assert init.attempts[0]["refused"].startswith("awaiting") and "refused" not in init.attempts[1]
        out = outcomes[-1]
        assert abs(out.alignment.scale * factor - 1.0) < 0.02
        # gravity: in the aligned world, camera 0 sees "down" where the true camera 0 does
        R_c0w = out.alignment.pose(T_cw[:1])[0, :3, :3]
        g_est = R_c0w @ DOWN
        g_true = sc.T_wc[0, :3, :3].T @ DOWN
        assert math.degrees(math.acos(float((g_est * g_true).sum().clamp(max=1.0)))) < 1.0
        # metric distances between keyframes
        p = se3_inverse(out.alignment.pose(T_cw))[:, :3, 3]
        d_est = (p - p[0]).norm(dim=-1)[1:]
        d_true = (sc.T_wc[:, :3, 3] - sc.T_wc[0, :3, 3]).norm(dim=-1)[1:]
        assert ((d_est - d_true).abs() / d_true).max() < 0.03
        # velocities in the aligned world: norms match, vertical component matches
        assert (out.velocities.norm(dim=-1) - sc.velocities.norm(dim=-1)).abs().max() < 0.05
        assert (out.velocities[:, 2] - sc.velocities[:, 2]).abs().max() < 0.05
        assert (out.bias[:3] - torch.tensor(sc.bias_gyro, **F64)).abs().max() < 2e-3


def test_an_imu_gap_delays_the_inertial_stage_by_its_keyframe_count_only():
    """A gap before the initialisation: the stage solves over the keyframes after it once there are 20 of them
    (K = 29 tries, K = 30 agrees), instead of waiting until the gap has left its window of up to 40 keyframes
    (never, in 32 keyframes); the keyframes before the gap get finite-difference velocities."""
    sc = make_scenario(n=32, spacing_s=0.3, seed=3, duration_s=14.0, bias_gyro=(0.002, -0.02, 0.01),
                       bias_acc=(0.05, -0.1, 0.08), imu_noise=True)
    gap = (sc.imu.t_ns > sc.stamps_ns[8] + 10**7) & (sc.imu.t_ns < sc.stamps_ns[9] - 10**7)
    imu = ImuSamples(sc.imu.t_ns[~gap], sc.imu.gyro[~gap], sc.imu.acc[~gap])
    T_cw = _visual_frame(sc, 0.37, rot_noise_deg=0.2, seed=3)
    init = StagedInitializer(VioConfig(), imu, NOISE, T_CB)
    outcomes = {K: init.on_keyframe(sc.stamps_ns[:K], T_cw[:K]) for K in range(3, 33)}
    assert [a["keyframes"] for a in init.attempts] == [29, 30] and init.stage == Stage.VISUAL_INERTIAL
    out = outcomes[30]
    assert abs(out.alignment.scale * 0.37 - 1.0) < 0.02
    assert torch.isfinite(out.velocities).all()
    assert (out.velocities[9:30].norm(dim=-1) - sc.velocities[9:30].norm(dim=-1)).abs().max() < 0.05


def test_gap_free_from_finds_where_the_imu_covers_up_to_the_newest_sample():
    buf = ImuBuffer.of(ImuSamples(np.array([0, 5, 10, 15, 40, 45, 50, 80, 85]) * 10**6, np.zeros((9, 3)),
                                  np.zeros((9, 3))))
    ms = 10**6
    assert buf.gap_free_from(2 * ms, 14 * ms, 10 * ms) == 2 * ms            # covered: the start itself
    assert buf.gap_free_from(2 * ms, 48 * ms, 10 * ms) == 40 * ms           # after the 15 -> 40 ms gap
    assert buf.gap_free_from(2 * ms, 84 * ms, 10 * ms) == 80 * ms           # the last of two gaps
    assert buf.gap_free_from(2 * ms, 84 * ms, 30 * ms) == 2 * ms            # no gap at this tolerance
    assert buf.gap_free_from(2 * ms, 86 * ms, 10 * ms) is None              # not reached yet
    assert buf.gap_free_from(20 * ms, 44 * ms, 10 * ms) == 40 * ms          # the gap spans the start
    late = ImuBuffer.of(ImuSamples(np.array([30, 35, 40]) * ms, np.zeros((3, 3)), np.zeros((3, 3))))
    assert late.gap_free_from(2 * ms, 38 * ms, 10 * ms) == 30 * ms          # the record does not reach back


def test_alignment_keeps_reprojections_and_rotates_gravity():
    sc = make_scenario(n=3)
    T_cw = se3_inverse(sc.T_wc)
    disps, coords, edges = visual_problem(T_cw)
    al = WorldAlignment(2.5, so3_exp(torch.tensor([0.3, -0.2, 1.0], **F64)))
    a = reproject(T_cw[edges.ii], T_cw[edges.jj], disps[edges.ii], coords, INTR).uv
    T2 = al.pose(T_cw)
    b = reproject(T2[edges.ii], T2[edges.jj], (disps / al.scale)[edges.ii], coords, INTR).uv
    assert torch.allclose(a, b, atol=1e-9)
    x = torch.randn(5, 3, **F64)
    # a world point seen from a camera stays where it was, up to the scale
    x_c = (T_cw[0, :3, :3] @ x.T).T + T_cw[0, :3, 3]
    x_c2 = (T2[0, :3, :3] @ al.point(x).T).T + T2[0, :3, 3]
    assert torch.allclose(x_c2, 2.5 * x_c, atol=1e-9)
    # camera-to-camera transforms keep their rotation, their translation is scaled (what
    # DenseOdometry.scale_relative_translations applies to the poses kept relative to keyframes)
    rel = T_cw[1] @ se3_inverse(T_cw[0])
    rel[:3, 3] *= al.scale
    assert torch.allclose(rel, T2[1] @ se3_inverse(T2[0]), atol=1e-9)


def test_stage_machine_switches():
    sc = make_scenario(n=12)
    T_cw = se3_inverse(sc.T_wc)
    off = StagedInitializer(VioConfig(**ABLATIONS["no_imu_fusion"]), sc.imu, NOISE, T_CB)
    joint = StagedInitializer(VioConfig(**ABLATIONS["no_staged_init"]), sc.imu, NOISE, T_CB)
    stages = []
    for K in range(3, 13):
        assert off.on_keyframe(sc.stamps_ns[:K], T_cw[:K]) is None
        joint.on_keyframe(sc.stamps_ns[:K], T_cw[:K])
        stages.append(joint.stage)
    assert off.stage == Stage.VISION_ONLY
    assert stages.index(Stage.JOINT_UNALIGNED) == 10 - 3


def test_joint_ba_without_staging_estimates_gravity_and_scale():
    """No staging: VI-BA with gravity and log-scale states from an up-to-scale visual world."""
    sc = make_scenario(n=11, spacing_s=0.3, seed=1)
    factor = 0.5
    T_vis = _visual_frame(sc, factor)
    disps, coords, edges = visual_problem(T_vis, depth=(1.0, 2.0))
    est = VisualInertialEstimator(VioConfig(staged_init=False, vision_only_keyframes=10, inertial_init_keyframes=11),
                                  sc.imu, NOISE, T_BC)
    ids = list(range(11))
    for k in ids[:10]:
        est.add_keyframe(k, int(sc.stamps_ns[k]))
    assert est.on_keyframe(ids[:10], sc.stamps_ns[:10], T_vis[:10]) is None
    assert est.stage == Stage.JOINT_UNALIGNED
    est.add_keyframe(10, int(sc.stamps_ns[10]))
    terms, state = est.terms(ids, T_vis)
    assert terms.estimate_gravity and terms.estimate_scale
    fixed = torch.zeros(11, dtype=torch.bool)
    fixed[:2] = True   # as the frame graph does: two fixed poses hold the visual scale, log-scale is then unique
    res = bundle_adjust(T_vis, disps, edges, coords, INTR, fixed, BAConfig(iterations=40, huber_delta=1e6),
                        extra=terms, extra_state=state)
    est.update(ids, res.extra_state)
    assert abs(math.exp(est.log_scale) * factor - 1.0) < 0.02
    g_true = sc.T_wc[0, :3, :3].T @ DOWN
    g_est = est.R_wg @ DOWN
    assert math.degrees(math.acos(float((g_est * g_true).sum().clamp(max=1.0)))) < 1.0
    al = est.on_keyframe(ids, sc.stamps_ns, res.poses)
    assert al is not None and est.metric
    v = torch.stack([est.states[k].velocity for k in ids])
    assert (v.norm(dim=-1) - sc.velocities.norm(dim=-1)).abs().max() < 0.02
    assert (v[:, 2] - sc.velocities[:, 2]).abs().max() < 0.02
    assert est.report()["scale_history"][-1]["scale"] == al.scale


def test_keyframe_prediction_from_imu_and_fallback():
    sc = make_scenario(n=3, spacing_s=0.25, bias_gyro=(0.01, 0.0, -0.01), bias_acc=(0.05, 0.0, 0.1))
    b = torch.tensor(np.concatenate([sc.bias_gyro, sc.bias_acc]), **F64)
    T_cw = se3_inverse(sc.T_wc)
    g = torch.tensor([0.0, 0.0, -9.81], **F64)
    pre = preintegrate(sc.imu, int(sc.stamps_ns[0]), int(sc.stamps_ns[1]), NOISE, b[:3], b[3:])
    pred = predict_keyframe(T_cw[0], sc.velocities[0], b, pre, T_CB, g)
    assert pred.from_imu and pred.cov_trace < 1e-4
    assert (pred.T_cw - T_cw[1]).abs().max() < 1e-5
    assert (pred.velocity - sc.velocities[1]).abs().max() < 1e-5
    # a long interval makes the covariance trace exceed tau: fall back to the previous keyframe's pose
    long = preintegrate(sc.imu, int(sc.stamps_ns[0]), int(sc.stamps_ns[0]) + 4_000_000_000, NOISE, b[:3], b[3:])
    fb = predict_keyframe(T_cw[0], sc.velocities[0], b, long, T_CB, g)
    assert not fb.from_imu and fb.cov_trace > 1e-4
    assert torch.equal(fb.T_cw, T_cw[0])


def test_estimator_predicts_only_once_metric():
    sc = make_scenario(n=3)
    T_cw = se3_inverse(sc.T_wc)
    est = VisualInertialEstimator(VioConfig(), sc.imu, NOISE, T_BC)
    est.add_keyframe(0, int(sc.stamps_ns[0]), sc.velocities[0])
    assert est.predict(0, T_cw[0], int(sc.stamps_ns[1])) is None   # vision-only stage
    R_cw = est.predict_rotation(0, T_cw[0], int(sc.stamps_ns[1]))   # the gyro alone needs no scale
    assert (R_cw - T_cw[1, :3, :3]).abs().max() < 1e-6
    assert est.terms([0], T_cw[:1]) is None
    est.initializer.stage = Stage.VISUAL_INERTIAL                  # as after a successful alignment
    pred = est.predict(0, T_cw[0], int(sc.stamps_ns[1]))
    assert pred is not None and (pred.T_cw - T_cw[1]).abs().max() < 1e-5
    assert est.predict_rotation(0, T_cw[0], int(sc.stamps_ns[1])) is None
    off = VisualInertialEstimator(VioConfig(imu_keyframe_init=False), sc.imu, NOISE, T_BC)
    off.add_keyframe(0, int(sc.stamps_ns[0]))
    off.initializer.stage = Stage.VISUAL_INERTIAL
    assert off.predict(0, T_cw[0], int(sc.stamps_ns[1])) is None



def _metric_estimator(sc, factor: float, n: int = 20, **config) -> tuple[VisualInertialEstimator, torch.Tensor]:
    """An estimator with the first ``n`` keyframes whose map is metric since keyframe 5 but scaled by ``factor``
    (and the world->camera poses of all)."""
    T_wc = sc.T_wc.clone()
    T_wc[:, :3, 3] *= factor
    est = VisualInertialEstimator(VioConfig(metric_hold_delay_s=2.0, **config), sc.imu, NOISE, T_BC)
    for k in range(n):
        est.add_keyframe(k, int(sc.stamps_ns[k]))
    assert not est.scale_check_due(int(sc.stamps_ns[n - 1]))        # not metric yet
    est.initializer.stage = Stage.VISUAL_INERTIAL                   # as after an alignment at keyframe 5
    est.metric_since_ns = int(sc.stamps_ns[5])
    return est, se3_inverse(T_wc)


def test_scale_check_refines_a_scale_a_few_percent_off_and_fails_one_that_did_not_hold():
    """``metric_hold_delay_s`` after the alignment the inertial-only refit over the keyframes since then checks the
    scale, once: 4% off, it passes (with ``scale_refinement`` it returns the correcting alignment and the
    velocities in the corrected world); 30% off, the alignment did not hold: a failure, back to vision-only."""
    sc = make_scenario(n=20, spacing_s=0.3, seed=3, bias_gyro=(0.002, -0.02, 0.01), bias_acc=(0.05, -0.1, 0.08),
                       imu_noise=True)
    ids = list(range(20))
    est, T_cw = _metric_estimator(sc, 1.04, scale_refinement=True)
    assert not est.scale_check_due(int(sc.stamps_ns[8]))           # 0.9 s after the alignment
    assert est.scale_check_due(int(sc.stamps_ns[-1]))
    al = est.check_scale(ids, sc.stamps_ns, T_cw)
    assert al is not None and abs(al.scale * 1.04 - 1.0) < 0.01
    assert math.degrees(math.acos(min(1.0, float(al.R[2, 2])))) < 1.0   # gravity stays along -z
    assert (est.states[12].velocity - sc.velocities[12]).norm() < 0.05
    assert est.scale_history[-1]["stage"] == "scale_check" and est.metric and not est.failures
    assert not est.scale_check_due(int(sc.stamps_ns[-1]))            # once
    est, T_cw = _metric_estimator(sc, 1.04)                         # refinement off (default): checked only
    assert est.check_scale(ids, sc.stamps_ns, T_cw) is None and est.metric and est.scale_checked
    est, T_cw = _metric_estimator(sc, 1.3)
    assert est.check_scale(ids, sc.stamps_ns, T_cw) is None
    assert not est.metric and est.stage == Stage.VISION_ONLY and est.initializer.first == 20
    assert "scale did not hold" in est.failures[0]["reason"]
    assert (est.states[12].velocity == 0).all() and est.alignment is None


def test_scale_refinement_only_when_the_check_is_significant_with_its_own_pose_noise():
    """``scale_refinement_min_sigmas``: a check whose |log scale| is under that many standard deviations leaves the
    map alone (recorded, not refined); a 4% error is many of them and is refined. ``scale_check_pose_noise`` is
    the pose noise the check's inertial-only problem assumes: smaller noise, smaller standard deviation."""
    sc = make_scenario(n=20, spacing_s=0.3, seed=3, bias_gyro=(0.002, -0.02, 0.01), bias_acc=(0.05, -0.1, 0.08),
                       imu_noise=True)
    ids = list(range(20))
    stds = {}
    for noise in (None, (1e-4, 1e-4)):
        est, T_cw = _metric_estimator(sc, 1.04, scale_refinement=True, scale_refinement_min_sigmas=3.0,
                                      scale_check_pose_noise=noise)
        assert est.check_scale(ids, sc.stamps_ns, T_cw) is not None and est.scale_history[-1]["refined"]
        stds[noise] = est.scale_history[-1]["log_scale_std"]
    assert stds[(1e-4, 1e-4)] < stds[None]
    est, T_cw = _metric_estimator(sc, 1.0, scale_refinement=True, scale_refinement_min_sigmas=3.0,
                                  scale_check_pose_noise=(1e-4, 1e-4))
    assert est.check_scale(ids, sc.stamps_ns, T_cw) is None and est.metric and est.scale_checked
    check = est.scale_history[-1]
    assert "refined" not in check and abs(math.log(check["scale"])) < 3.0 * check["log_scale_std"]


def test_a_divergent_metric_state_is_a_failure_and_initialisation_restarts_after_it():
    """Once metric, an implausible speed or bias, or a keyframe position jump, is a failure; the estimator then
    forgets its inertial state and the inertial-only stage uses only keyframes from the failure on."""
    sc = make_scenario(n=45, spacing_s=0.3, seed=3, duration_s=16.0, bias_gyro=(0.002, -0.02, 0.01),
                       bias_acc=(0.05, -0.1, 0.08), imu_noise=True)
    T_cw = se3_inverse(sc.T_wc)
    est, _ = _metric_estimator(sc, 1.0)
    ids, stamps = list(range(20)), sc.stamps_ns[:20]
    for k in ids:
        est.states[k].velocity = sc.velocities[k].clone()
    assert est.health(ids, stamps, T_cw[:20]) is None
    est.states[19].velocity = torch.tensor([40.0, 0.0, 0.0], **F64)
    assert "implausible state: speed 40" in est.health(ids, stamps, T_cw[:20])
    est.states[19].velocity = sc.velocities[19].clone()
    est.states[19].bias = torch.tensor([0, 0, 0, 0, 0, 2.5], **F64)
    assert "accelerometer bias 2.5" in est.health(ids, stamps, T_cw[:20])
    est.states[19].bias = torch.zeros(6, **F64)
    jumped = T_cw[:20].clone()
    jumped[-1] = T_cw[19] @ torch.linalg.inv(torch.tensor([[1, 0, 0, 50.0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                           [0, 0, 0, 1]], **F64))
    reason = est.health(ids, stamps, jumped)
    assert reason.startswith("pose jump: 49.9 m in 0.300 s")
    est.fail(int(stamps[-1]), reason)
    assert not est.metric and est.failures[0]["reason"] == reason
    init = est.initializer
    for K in range(21, 40):   # keyframes 20.. only: 20 of them are needed before the stage runs again
        est.add_keyframe(K - 1, int(sc.stamps_ns[K - 1]))
        assert est.on_keyframe(list(range(K)), sc.stamps_ns[:K], T_cw[:K]) is None
    assert len(init.attempts) == 0
    for K in range(40, 46):
        est.add_keyframe(K - 1, int(sc.stamps_ns[K - 1]))
        if est.on_keyframe(list(range(K)), sc.stamps_ns[:K], T_cw[:K]) is not None:
            break
    assert est.metric and est.reinitialisations == 1 and init.attempts[0]["keyframes"] == 40


def test_initialisation_refuses_implausible_and_degenerate_solutions():
    """Constructed degenerate initialisations are refused (a "not yet"), never accepted: an accelerometer reading
    1 m/s^2 off is an implausible bias against a 0.5 m/s^2 limit, 3 m/s^2 off an inconsistent fit, 25% too large an
    implausible gravity; constant velocity
    along a line leaves the scale unobservable; keyframe poses whose scale jumps between windows never agree."""
    sc = make_scenario(n=24, spacing_s=0.3, seed=0, imu_noise=True)
    T_cw = _visual_frame(sc, 0.5)
    for gain, offset, config, refusal in ((1.0, 1.0, VioConfig(max_bias_acc=0.5), "implausible: speed"),
                                          (1.0, 3.0, VioConfig(), "not trustworthy"),   # chi2 / dof 7
                                          (1.25, 0.0, VioConfig(), "implausible gravity")):   # a wrong scale factor
        biased = type(sc.imu)(sc.imu.t_ns, sc.imu.gyro, gain * sc.imu.acc + np.array([0.0, 0.0, offset]))
        init = StagedInitializer(config, biased, NOISE, T_CB)
        assert all(init.on_keyframe(sc.stamps_ns[:K], T_cw[:K]) is None for K in range(3, 25))
        assert init.stage == Stage.VISION_ONLY and len(init.attempts) == 5
        assert all(a["refused"].startswith(refusal) for a in init.attempts), init.attempts

    # 1 m/s along a line (acceleration 1 mm/s^2) while the body turns: the scale trades against the velocity
    line = AnalyticMotion.default()
    line.pos_amp, line.pos_freq = np.array([1000.0, 600.0, 0.0]), np.array([1e-3, 1e-3, 1e-3])
    t_imu = np.arange(0, int(9e9), int(5e6), dtype=np.int64)
    stamps = np.arange(24, dtype=np.int64) * 300_000_000 + 1_234_567
    R, p, _ = line.state(stamps * 1e-9)
    T_wb = torch.eye(4, **F64).repeat(24, 1, 1)
    T_wb[:, :3, :3], T_wb[:, :3, 3] = R, p
    T_line = se3_inverse(T_wb @ T_BC)
    T_line[:, :3, 3] *= 0.5
    init = StagedInitializer(VioConfig(), line.imu(t_imu), NOISE, T_CB)
    assert all(init.on_keyframe(stamps[:K], T_line[:K]) is None for K in range(3, 25))
    assert init.stage == Stage.VISION_ONLY and len(init.attempts) == 5
    assert all("refused" in a for a in init.attempts), init.attempts

    init = StagedInitializer(VioConfig(), sc.imu, NOISE, T_CB)
    for K in range(3, 25):   # the map's scale changes by 20% from one keyframe to the next
        T = _visual_frame(sc, 0.5 * (1.2 if K % 2 else 1.0))
        assert init.on_keyframe(sc.stamps_ns[:K], T[:K]) is None
    assert init.stage == Stage.VISION_ONLY
    assert sum(a["refused"].startswith("disagrees") for a in init.attempts) >= 3


def test_keyframes_outside_the_imu_stay_vision_only():
    sc = make_scenario(n=22, spacing_s=0.3)
    T_cw = se3_inverse(sc.T_wc)
    short = sc.imu.slice(int(sc.stamps_ns[5]), int(sc.stamps_ns[-1]) + 1)   # IMU starts after keyframe 5
    init = StagedInitializer(VioConfig(), short, NOISE, T_CB)
    assert all(init.on_keyframe(sc.stamps_ns[:K], T_cw[:K]) is None for K in range(3, 23))
    assert init.stage == Stage.VISION_ONLY
    est = VisualInertialEstimator(VioConfig(), short, NOISE, T_BC)
    for k in range(3):
        est.add_keyframe(k, int(sc.stamps_ns[k]))
    est.initializer.stage = Stage.VISUAL_INERTIAL
    assert est.terms([0, 1, 2], T_cw[:3]) is None
    assert est.predict(0, T_cw[0], int(sc.stamps_ns[1])) is None


def _monitor(est, T_cw, stamps, first: int) -> list[tuple[int, str]]:
    """Run the rolling scale check at each keyframe from ``first`` on; the (keyframe, reason) of each failure."""
    out = []
    for K in range(first, len(stamps) + 1):
        if (reason := est.monitor_scale(list(range(K)), stamps[:K], T_cw[:K])) is not None:
            out.append((K - 1, reason))
    return out


def test_the_rolling_scale_check_flags_a_scale_that_drifts_after_the_first_check():
    """After the scale check, the inertial-only problem over the last ``inertial_init_keyframes`` keyframes every
    ``scale_monitor_every`` of them: true poses never strike and keep ``scale_verified_ns`` moving; poses whose
    motion shrinks to 60% from keyframe 25 on (a visual scale that collapsed while the VI-BA ran) strike twice
    in a row once the window sits in the shrunk part, and that is a failure; off, nothing is checked."""
    sc = make_scenario(n=50, spacing_s=0.3, seed=3, duration_s=17.0, bias_gyro=(0.002, -0.02, 0.01),
                       bias_acc=(0.05, -0.1, 0.08), imu_noise=True)
    stamps = sc.stamps_ns
    est, T_cw = _metric_estimator(sc, 1.0, n=50)
    est.scale_checked = True
    assert _monitor(est, T_cw, stamps, 21) == [] and est.scale_monitor["deviating"] == 0
    assert est.scale_monitor["checks"] == 3 and est.scale_verified_ns == int(stamps[49])   # at keyframes 29, 39, 49
    shrunk = sc.T_wc.clone()
    p25 = shrunk[25, :3, 3].clone()
    shrunk[25:, :3, 3] = p25 + 0.6 * (shrunk[25:, :3, 3] - p25)
    est, _ = _metric_estimator(sc, 1.0, n=50)
    est.scale_checked = True
    failures = _monitor(est, se3_inverse(shrunk), stamps, 21)
    assert failures and failures[0][0] >= 30 and "the scale drifted" in failures[0][1]
    assert est.scale_verified_ns == int(stamps[29])   # the frames since the last check that held get marked lost
    est, _ = _metric_estimator(sc, 1.0, n=50, scale_monitor_every=0)
    est.scale_checked = True
    assert _monitor(est, se3_inverse(shrunk), stamps, 21) == [] and est.scale_monitor["checks"] == 0
