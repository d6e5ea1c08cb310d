"""The estimator's IMU preintegrations: frame predictions and rotation priors equal integration from scratch, the
BA window's pairs re-integrated in one batch only when stale, and a predicted frame that becomes a keyframe hands
its preintegration on to the keyframe pair."""
import numpy as np
import pytest
import torch

from vigs_core.geometry import se3_inverse
from vigs_core.imu.preintegration import preintegrate
from vigs_core.imu.samples import ImuDataWarning
from vigs_core.types import ImuSamples
from vigs_core.vio.config import VioConfig
from vigs_core.vio.estimator import VisualInertialEstimator
from vigs_core.vio.initialization import Stage
from vigs_core.vio.keyframe_init import predict_keyframe
from vio_synthetic import NOISE, T_BC, make_scenario

torch.set_num_threads(1)
FIELDS = ("delta_R", "delta_v", "delta_p", "cov", "J_R_bg", "J_v_bg", "J_v_ba", "J_p_bg", "J_p_ba")


def _metric_estimator(sc, config: VioConfig | None = None) -> VisualInertialEstimator:
    est = VisualInertialEstimator(config or VioConfig(), sc.imu, NOISE, T_BC)
    est.initializer.stage = Stage.VISUAL_INERTIAL   # as after a successful alignment
    return est


def _scenario():
    return make_scenario(n=6, spacing_s=0.3, seed=2, bias_gyro=(0.002, -0.02, 0.01), bias_acc=(0.05, -0.1, 0.08),
                         imu_noise=True)


def _assert_same(a, b, tol=1e-12):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x - y).abs().max() <= tol * max(1.0, float(y.abs().max())), name


@pytest.mark.parametrize("scheme", ["closed_form", "forster"])
def test_predictions_equal_integration_from_scratch_across_keyframe_and_bias_changes(scheme):
    sc = _scenario()
    T_cw = se3_inverse(sc.T_wc)
    est = _metric_estimator(sc, VioConfig(scheme=scheme))
    est.add_keyframe(0, int(sc.stamps_ns[0]), sc.velocities[0])
    g = est.gravity_world()
    for ref, bias in ((0, None), (0, torch.tensor([0.003, -0.01, 0.02, 0.1, -0.05, 0.02], dtype=torch.float64)),
                      (1, None)):
        if ref == 1:
            est.add_keyframe(1, int(sc.stamps_ns[1]), sc.velocities[1])
        if bias is not None:
            est.states[ref].bias = bias
            est.global_bias = bias.clone()
        t0 = int(sc.stamps_ns[ref])
        for t in t0 + np.array([50_000_000, 100_000_000, 150_000_123, 333_333_333]):
            pred = est.predict(ref, T_cw[ref], int(t))
            b = est.bias_of(ref)
            pre = preintegrate(sc.imu, t0, int(t), NOISE, b[:3], b[3:], scheme)
            want = predict_keyframe(T_cw[ref], est.states[ref].velocity, b, pre, est.T_cb, g,
                                    est.config.keyframe_init_max_cov_trace)
            assert pred.from_imu and torch.equal(pred.T_cw, want.T_cw) and torch.equal(pred.velocity, want.velocity)


def test_rotation_prior_equals_the_full_preintegration_rotation():
    sc = _scenario()
    T_cw = se3_inverse(sc.T_wc)
    est = VisualInertialEstimator(VioConfig(), sc.imu, NOISE, T_BC)   # vision-only stage: rotation prior only
    est.add_keyframe(0, int(sc.stamps_ns[0]))
    est.states[0].bias = torch.tensor([0.01, -0.02, 0.005, 0.3, 0.1, -0.2], dtype=torch.float64)
    est.global_bias = est.states[0].bias.clone()
    t = int(sc.stamps_ns[1]) + 7_000_001
    R_cw = est.predict_rotation(0, T_cw[0], t)
    b = est.bias_of(0)
    pre = preintegrate(sc.imu, int(sc.stamps_ns[0]), t, NOISE, b[:3], b[3:])
    R_cb = est.T_cb[:3, :3]
    want = (T_cw[0, :3, :3].T @ R_cb @ pre.delta_R @ R_cb.T).T
    assert torch.equal(R_cw, want)
    # the IMU stream checks still apply: a recording with a swapped pair of stamps warns and is used sorted
    swapped = sc.imu.t_ns.copy()
    k = int(np.searchsorted(swapped, int(sc.stamps_ns[0]))) + 5
    swapped[[k, k + 1]] = swapped[[k + 1, k]]
    with pytest.warns(ImuDataWarning, match="out-of-order"):
        est = VisualInertialEstimator(VioConfig(), ImuSamples(swapped, sc.imu.gyro, sc.imu.acc), NOISE, T_BC)
    est.add_keyframe(0, int(sc.stamps_ns[0]))
    est.states[0].bias = b.clone()
    est.global_bias = b.clone()
    R_sorted = est.predict_rotation(0, T_cw[0], t)
    assert (R_sorted - R_cw).abs().max() < 1e-3   # the two swapped samples' measurements change places only


def test_window_pairs_are_reintegrated_in_one_batch_only_when_stale():
    sc = _scenario()
    est = _metric_estimator(sc, VioConfig(relinearize_bias_threshold=1e-3))
    for k in range(4):
        est.add_keyframe(k, int(sc.stamps_ns[k]), sc.velocities[k])
    pairs = [(0, 1), (1, 2), (2, 3)]

    def scratch(i, j):
        b = est.bias_of(i)
        return preintegrate(sc.imu, int(sc.stamps_ns[i]), int(sc.stamps_ns[j]), NOISE, b[:3], b[3:])

    batch = est.preintegrations(pairs)
    assert batch.delta_R.shape == (3, 3, 3) and list(batch.t1_ns) == [int(sc.stamps_ns[j]) for _, j in pairs]
    for n, (i, j) in enumerate(pairs):
        _assert_same(batch.item(n), scratch(i, j))
    cached = est._pre[(1, 2)]

    def set_bias(b):
        est.global_bias = b.clone()
        for k in est.states:
            est.states[k].bias = b.clone()

    small = torch.tensor([5e-4, 0, 0, 0, 0, 0], dtype=torch.float64)
    set_bias(small)                         # within the threshold: the cached linearisation stays
    assert est.preintegrations([(1, 2)]).delta_v[0].equal(cached.delta_v)
    set_bias(small + torch.tensor([0, 0, 0, 0.05, 0, 0], dtype=torch.float64))   # beyond: re-integrated
    again = est.preintegrations(pairs)
    for n, (i, j) in enumerate(pairs):
        _assert_same(again.item(n), scratch(i, j))
    assert not again.delta_v[1].equal(cached.delta_v)


def test_a_predicted_frame_that_becomes_a_keyframe_hands_on_its_preintegration():
    sc = _scenario()
    T_cw = se3_inverse(sc.T_wc)
    est = _metric_estimator(sc)
    est.add_keyframe(0, int(sc.stamps_ns[0]), sc.velocities[0])
    t1 = int(sc.stamps_ns[1])
    est.predict(0, T_cw[0], t1 - 50_000_000)
    est.predict(0, T_cw[0], t1)
    est.add_keyframe(1, t1, sc.velocities[1])
    handed = est._pre[(0, 1)]
    b = est.bias_of(0)
    _assert_same(est.preintegrations([(0, 1)]).item(0), preintegrate(sc.imu, int(sc.stamps_ns[0]), t1, NOISE,
                                                                      b[:3], b[3:]), tol=0.0)
    assert est.preintegrations([(0, 1)]).delta_v[0].equal(handed.delta_v)
    # a keyframe at another stamp than the last prediction gets nothing handed on
    est.predict(1, T_cw[1], int(sc.stamps_ns[2]) - 1)
    est.add_keyframe(2, int(sc.stamps_ns[2]), sc.velocities[2])
    assert (1, 2) not in est._pre



def test_a_window_across_an_imu_gap_keeps_the_factors_of_its_covered_intervals():
    """IMU samples missing over keyframe 2 (intervals (1, 2) and (2, 3) hold a gap over ``max_imu_gap_s``): once
    metric, the window's inertial terms keep intervals (0, 1), (3, 4), (4, 5) at full weight, give the two
    across the gap weight 0, and anchor the velocity of keyframe 2, which no interval observes; before the map
    is metric the window is vision-only (no terms)."""
    sc = _scenario()
    t = sc.imu.t_ns
    keep = np.abs(t - sc.stamps_ns[2]) > 2 * 10**8   # 0.4 s without samples around keyframe 2
    imu = ImuSamples(t[keep], sc.imu.gyro[keep], sc.imu.acc[keep])
    est = VisualInertialEstimator(VioConfig(), imu, NOISE, T_BC)
    for k in range(6):
        est.add_keyframe(k, int(sc.stamps_ns[k]), sc.velocities[k])
    ids, poses = list(range(6)), se3_inverse(sc.T_wc)
    est.initializer.stage = Stage.JOINT_UNALIGNED
    assert est.terms(ids, poses, {0}) is None
    est.initializer.stage = Stage.VISUAL_INERTIAL
    terms, _ = est.terms(ids, poses, {0})
    full = VioConfig().inertial_weight * torch.linalg.inv(terms.pre.cov)
    assert torch.allclose(terms.info[[0, 3, 4]], full[[0, 3, 4]])
    assert terms.info[[1, 2]].abs().max() == 0
    assert terms.anchor.mask.tolist() == [True, False, True, False, False, False]
