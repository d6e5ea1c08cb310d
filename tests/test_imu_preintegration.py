"""Preintegration: GTSAM 4.3 agreement on real EuRoC IMU, analytic motion, bias Jacobians, stream hygiene."""
from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from vigs_core.geometry import hat, so3_exp, so3_left_jacobian, so3_log, so3_right_jacobian
from vigs_core.imu.analytic_motion import GRAVITY, AnalyticMotion
from vigs_core.imu.preintegration import (
    _PieceMatrices,
    preintegrate,
    preintegrate_between,
    preintegrate_intervals,
    preintegrate_measurements,
    preintegrate_rotation,
    preintegrate_segments,
)
from vigs_core.imu.samples import ImuDataWarning, interval_measurements
from vigs_core.io import read_euroc_imu, read_imu_yaml
from vigs_core.types import ImuNoise, ImuSamples

torch.set_num_threads(1)  # the test machine is shared; one thread each is fastest

DATA = Path(__file__).parent / "data" / "imu"


def load_imu(name: str, tmp_path: Path) -> ImuSamples:
    """Read a shipped gzipped EuRoC IMU excerpt through vigs_core.io."""
    csv = tmp_path / f"{name}_imu.csv"
    with gzip.open(DATA / f"{name}_imu.csv.gz", "rb") as src, open(csv, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return read_euroc_imu(csv)


def true_deltas(motion: AnalyticMotion, t0_ns: int, t1_ns: int):
    R, p, v = motion.state(np.array([t0_ns, t1_ns]) * 1e-9)
    T, g = (t1_ns - t0_ns) * 1e-9, torch.as_tensor(GRAVITY)
    return R[0].T @ R[1], R[0].T @ (v[1] - v[0] - g * T), R[0].T @ (p[1] - p[0] - v[0] * T - 0.5 * g * T * T)


def delta_errors(pre, truth) -> tuple[float, float, float]:
    dR, dv, dp = truth
    return (float(so3_log(pre.delta_R.T @ dR).norm()), float((pre.delta_v - dv).norm()),
            float((pre.delta_p - dp).norm()))


@pytest.mark.parametrize("name", ["V1_01_easy", "V2_01_easy", "MH_03_medium"])
def test_matches_gtsam_manifold_preintegration_on_real_imu(name, tmp_path):
    import gtsam  # test-only dependency (requirements/test.txt)

    imu = load_imu(name, tmp_path)
    noise = read_imu_yaml(DATA / "imu0_sensor.yaml")
    t0 = int(imu.t_ns[40]) + 1_234_567  # between samples
    t1 = t0 + 2_000_000_777
    _, dt, w, a = interval_measurements(imu, t0, t1)
    bg, ba = np.array([-0.002, 0.021, 0.077]), np.array([-0.02, 0.066, 0.03])
    pre = preintegrate_measurements(torch.tensor(dt), torch.tensor(w), torch.tensor(a), noise,
                                    torch.tensor(bg), torch.tensor(ba), scheme="forster")
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    # gtsam takes continuous-time covariances (sigma^2 I) and divides by dt itself
    params.setGyroscopeCovariance(noise.gyro_noise_density**2 * np.eye(3))
    params.setAccelerometerCovariance(noise.acc_noise_density**2 * np.eye(3))
    params.setIntegrationCovariance(np.zeros((3, 3)))
    pim = gtsam.PreintegratedImuMeasurementsManifold(params, gtsam.imuBias.ConstantBias(ba, bg))
    for k in range(len(dt)):
        pim.integrateMeasurement(a[k], w[k], dt[k])
    assert np.abs(pim.deltaRij().matrix() - pre.delta_R.numpy()).max() < 1e-9
    assert np.abs(pim.deltaVij() - pre.delta_v.numpy()).max() < 1e-9
    assert np.abs(pim.deltaPij() - pre.delta_p.numpy()).max() < 1e-9
    # gtsam orders (rotation, position, velocity) and expresses p, v errors in the frame of t_j
    # (NavState retraction p + R dp): cov_gtsam = M cov_ours M^T with M the reordering and dR^T blocks.
    Rt = pre.delta_R.numpy().T
    M = np.zeros((9, 9))
    M[0:3, 0:3], M[3:6, 6:9], M[6:9, 3:6] = np.eye(3), Rt, Rt
    ours = M @ pre.cov.numpy()[:9, :9] @ M.T
    theirs = pim.preintMeasCov()
    assert np.abs(ours - theirs).max() / np.abs(theirs).max() < 1e-6
    assert np.abs(np.diag(ours) / np.diag(theirs) - 1).max() < 1e-6
    # first-order bias correction against gtsam's predict with a changed bias
    dbg, dba = np.array([1e-3, -2e-3, 5e-4]), np.array([0.01, -0.02, 0.005])
    pred = pim.predict(gtsam.NavState(gtsam.Rot3(), np.zeros(3), np.zeros(3)),
                       gtsam.imuBias.ConstantBias(ba + dba, bg + dbg))
    R, v, p = pre.corrected(torch.tensor(bg + dbg), torch.tensor(ba + dba))
    T, g = dt.sum(), np.array([0.0, 0.0, -9.81])
    assert np.abs(pred.attitude().matrix() - R.numpy()).max() < 1e-9
    assert np.abs(pred.velocity() - (v.numpy() + g * T)).max() < 1e-9
    assert np.abs(pred.position() - (p.numpy() + 0.5 * g * T * T)).max() < 1e-9


def test_noise_free_analytic_motion_reproduces_relative_pose():
    motion = AnalyticMotion.default()
    imu = motion.imu(np.arange(0, 3_000_000_000, 1_000_000))  # 1 kHz
    t0, t1 = 1_000_123_457, 2_000_456_789
    pre = preintegrate(imu, t0, t1, ImuNoise())
    err_R, err_v, err_p = delta_errors(pre, true_deltas(motion, t0, t1))
    assert err_R < 1e-6 and err_v < 1e-6 and err_p < 1e-6
    assert abs(float(pre.dt) - (t1 - t0) * 1e-9) < 1e-15


def test_closed_form_scheme_converges_at_second_order_and_forster_at_first():
    motion = AnalyticMotion.default()
    t0, t1 = 1_234_567_891, 3_456_789_123
    errs = {}
    for scheme in ("closed_form", "forster"):
        for rate in (200, 400):
            imu = motion.imu(np.arange(0, 4_000_000_000, 1_000_000_000 // rate))
            errs[scheme, rate] = delta_errors(preintegrate(imu, t0, t1, ImuNoise(), scheme=scheme),
                                              true_deltas(motion, t0, t1))
    for k in range(3):
        assert errs["closed_form", 200][k] / errs["closed_form", 400][k] > 3.5
    assert 1.8 < errs["forster", 200][2] / errs["forster", 400][2] < 2.2
    assert errs["closed_form", 200][2] < 0.01 * errs["forster", 200][2]


@pytest.mark.parametrize("scheme,tol", [("forster", 1e-6), ("closed_form", 2e-3)])
def test_bias_jacobians_match_numerical_derivatives_of_reintegration(scheme, tol, tmp_path):
    imu = load_imu("V1_01_easy", tmp_path)
    t0 = int(imu.t_ns[1000]) + 2_500_000
    t1 = t0 + 1_500_000_000
    noise, eps = ImuNoise(), 1e-5
    bg0, ba0 = torch.tensor([-0.002, 0.02, 0.077]), torch.tensor([-0.02, 0.06, 0.03])
    pre = preintegrate(imu, t0, t1, noise, bg0, ba0, scheme=scheme)
    for which in ("gyro", "acc"):
        cols = []
        for k in range(3):
            d = torch.zeros(3, dtype=torch.float64)
            d[k] = eps
            out = []
            for sign in (1, -1):
                bg, ba = (bg0 + sign * d, ba0) if which == "gyro" else (bg0, ba0 + sign * d)
                q = preintegrate(imu, t0, t1, noise, bg, ba, scheme=scheme)
                out.append(torch.cat((so3_log(pre.delta_R.T @ q.delta_R), q.delta_v, q.delta_p)))
            cols.append((out[0] - out[1]) / (2 * eps))
        numeric = torch.stack(cols, -1)
        if which == "gyro":
            analytic = torch.cat((pre.J_R_bg, pre.J_v_bg, pre.J_p_bg))
        else:
            analytic = torch.cat((torch.zeros(3, 3, dtype=torch.float64), pre.J_v_ba, pre.J_p_ba))
        assert float((numeric - analytic).abs().max()) < tol * float(analytic.abs().max())
    # first-order correction tracks re-integration: the error is second order in the bias change
    dbg = torch.tensor([2e-3, -1e-3, 1.5e-3])
    errs = []
    for scale in (1.0, 0.5):
        q = preintegrate(imu, t0, t1, noise, bg0 + scale * dbg, ba0, scheme=scheme)
        R, v, p = pre.corrected(bg0 + scale * dbg, ba0)
        errs.append(float((p - q.delta_p).norm()))
    assert errs[1] < 0.3 * errs[0]


def test_splitting_an_interval_between_samples_composes_exactly_for_constant_rates():
    t = np.arange(0, 1_000_000_000, 5_000_000)
    w, a = np.array([0.3, -0.2, 0.5]), np.array([0.4, 0.1, 9.7])
    imu = ImuSamples(t, np.tile(w, (len(t), 1)), np.tile(a, (len(t), 1)))
    t0, tm, t1 = 101_000_000, 433_333_333, 901_234_567
    whole = preintegrate(imu, t0, t1, ImuNoise())
    first, second = preintegrate(imu, t0, tm, ImuNoise()), preintegrate(imu, tm, t1, ImuNoise())
    T2 = second.dt
    assert torch.allclose(first.delta_R @ second.delta_R, whole.delta_R, atol=1e-12)
    assert torch.allclose(first.delta_v + first.delta_R @ second.delta_v, whole.delta_v, atol=1e-12)
    assert torch.allclose(first.delta_p + first.delta_v * T2 + first.delta_R @ second.delta_p, whole.delta_p,
                          atol=1e-12)


def test_boundary_values_are_interpolated():
    t = np.array([0, 10, 20, 30]) * 1_000_000
    gyro = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    grid, dt, w, _ = interval_measurements(ImuSamples(t, gyro, np.zeros((4, 3))), 5_000_000, 25_000_000)
    assert list(grid) == [5_000_000, 10_000_000, 20_000_000, 25_000_000]
    np.testing.assert_allclose(dt, [0.005, 0.010, 0.005])
    np.testing.assert_allclose(w[:, 0], [0.75, 1.5, 2.25])  # means of the linear signal on each piece


def test_covariance_is_symmetric_positive_definite_and_grows_with_time(tmp_path):
    imu = load_imu("V2_01_easy", tmp_path)
    t0 = int(imu.t_ns[10]) + 1_000_000
    short = preintegrate(imu, t0, t0 + 500_000_000, ImuNoise())
    long = preintegrate(imu, t0, t0 + 1_500_000_000, ImuNoise())
    for pre in (short, long):
        assert torch.allclose(pre.cov, pre.cov.T)
        assert float(torch.linalg.eigvalsh(pre.cov).min()) > 0
    assert bool((long.cov.diagonal() > short.cov.diagonal()).all())


def test_warns_on_gaps_out_of_order_and_duplicates():
    t = np.arange(0, 400_000_000, 5_000_000)
    imu = ImuSamples(t, np.zeros((len(t), 3)), np.tile([0, 0, 9.81], (len(t), 1)))
    noise = ImuNoise()
    gap = ImuSamples(np.delete(t, range(20, 30)), np.zeros((len(t) - 10, 3)), imu.acc[10:])
    with pytest.warns(ImuDataWarning, match="gap"):
        preintegrate(gap, 50_000_000, 300_000_000, noise)
    swapped = imu.t_ns.copy()
    swapped[[30, 31]] = swapped[[31, 30]]
    with pytest.warns(ImuDataWarning, match="out-of-order"):
        pre = preintegrate(ImuSamples(swapped, imu.gyro, imu.acc), 50_000_000, 300_000_000, noise)
    assert torch.allclose(pre.delta_v, torch.tensor([0, 0, 9.81 * 0.25], dtype=torch.float64), atol=1e-12)
    dup = ImuSamples(np.insert(t, 30, t[30]), np.zeros((len(t) + 1, 3)), np.tile([0, 0, 9.81], (len(t) + 1, 1)))
    with pytest.warns(ImuDataWarning, match="duplicated"):
        preintegrate(dup, 50_000_000, 300_000_000, noise)
    bad_acc = imu.acc.copy()
    bad_acc[30, 2] = np.nan   # a driver's invalid reading: dropped, the constant signal is bridged exactly
    with pytest.warns(ImuDataWarning, match="1 sample.* non-finite value; dropped"):
        pre = preintegrate(ImuSamples(imu.t_ns, imu.gyro, bad_acc), 50_000_000, 300_000_000, noise)
    assert torch.allclose(pre.delta_v, torch.tensor([0, 0, 9.81 * 0.25], dtype=torch.float64), atol=1e-12)


def test_rejects_intervals_outside_the_samples():
    t = np.arange(0, 100_000_000, 5_000_000)
    imu = ImuSamples(t, np.zeros((len(t), 3)), np.zeros((len(t), 3)))
    with pytest.raises(ValueError, match="inside the samples"):
        preintegrate(imu, 50_000_000, 200_000_000, ImuNoise())
    with pytest.raises(ValueError, match="t1 > t0"):
        preintegrate(imu, 50_000_000, 50_000_000, ImuNoise())


def test_batched_between_equals_one_interval_at_a_time(tmp_path):
    imu = load_imu("MH_03_medium", tmp_path)
    stamps = int(imu.t_ns[5]) + np.array([0, 123_456_789, 400_000_001, 1_000_000_000, 1_000_400_000])
    bg = torch.tensor([[0.01, 0.02, 0.03]] * 4, dtype=torch.float64) * torch.arange(1, 5)[:, None]
    batch = preintegrate_between(imu, stamps, ImuNoise(), bg, None)
    assert batch.delta_R.shape == (4, 3, 3) and list(batch.t0_ns) == list(stamps[:-1])
    for k in range(4):
        one = preintegrate(imu, stamps[k], stamps[k + 1], ImuNoise(), bg[k])
        for name in ("delta_R", "delta_v", "delta_p", "cov", "J_R_bg", "J_v_bg", "J_v_ba", "J_p_bg", "J_p_ba"):
            assert torch.allclose(getattr(batch, name)[k], getattr(one, name), rtol=1e-12, atol=1e-14), name


def test_covariance_matches_monte_carlo_of_white_measurement_noise():
    """Closed-form scheme: the predicted covariance matches the scatter of deltas under simulated noise."""
    motion = AnalyticMotion.default()
    t = np.arange(0, 1_000_000_000, 5_000_000)
    clean = motion.imu(t)
    noise = ImuNoise(gyro_noise_density=2e-3, acc_noise_density=2e-2)
    t0, t1 = 100_000_000, 900_000_000
    _, dt, w, a = interval_measurements(clean, t0, t1)
    rng = np.random.default_rng(3)
    trials = 400
    # white noise of density sigma on a piece of length dt has standard deviation sigma / sqrt(dt)
    sw = noise.gyro_noise_density / np.sqrt(dt)[None, :, None]
    sa = noise.acc_noise_density / np.sqrt(dt)[None, :, None]
    ws = torch.as_tensor(w[None] + sw * rng.standard_normal((trials, len(dt), 3)))
    accs = torch.as_tensor(a[None] + sa * rng.standard_normal((trials, len(dt), 3)))
    ref = preintegrate_measurements(torch.as_tensor(dt), torch.as_tensor(w), torch.as_tensor(a), noise)
    segment = torch.arange(trials).repeat_interleave(len(dt))  # all trials in one batched call
    zeros = torch.zeros(trials, 3, dtype=torch.float64)
    q = preintegrate_segments(torch.as_tensor(dt).repeat(trials), ws.reshape(-1, 3), accs.reshape(-1, 3), segment,
                              noise, zeros, zeros)
    e = torch.cat((so3_log(ref.delta_R.T @ q.delta_R), q.delta_v - ref.delta_v, q.delta_p - ref.delta_p), 1)
    sample = e.T @ e / trials
    predicted = ref.cov[:9, :9]
    # Mahalanobis check: mean of e^T Cov^-1 e is 9 for a correct covariance (std of the mean ~ sqrt(18/400))
    nees = (e @ torch.linalg.inv(predicted) * e).sum(1).mean()
    assert abs(float(nees) / 9 - 1) < 0.15
    rel = (sample.diagonal() / predicted.diagonal() - 1).abs().max()
    assert float(rel) < 0.25


def test_piece_matrices_match_the_so3_functions_and_the_gamma2_series():
    """One [phi]x and one set of coefficients give Exp, J_r, J_l (as vigs_core.geometry.so3) and
    G2 = sum_n [phi]x^n / (n+2)!, on both sides of the small-angle switch."""
    phi = torch.tensor([[0.0, 0.0, 0.0], [3e-5, -2e-5, 1e-5], [0.01, 0.02, -0.03], [0.4, -1.1, 0.7]],
                       dtype=torch.float64)
    m = _PieceMatrices.of(phi.numpy(), "closed_form")   # NumPy, as the preintegration runs
    close = lambda a, b: float(np.abs(a - b.numpy()).max()) < 1e-15  # noqa: E731 -- NumPy's vs torch's sin/cos
    assert close(m.exp, so3_exp(phi)) and close(m.right_jacobian, so3_right_jacobian(phi))
    assert close(m.left_jacobian, so3_left_jacobian(phi))
    k = hat(phi)
    series, power, fact = torch.zeros_like(k), torch.eye(3, dtype=torch.float64).expand_as(k), 2.0
    for n in range(30):
        series = series + power / fact
        power, fact = power @ k, fact * (n + 3)
    assert np.abs(m.gamma2 - series.numpy()).max() < 1e-12   # cancellation in (t^2/2 + cos t - 1) / t^4
    forster = _PieceMatrices.of(phi.numpy(), "forster")
    assert forster.left_jacobian is None and forster.gamma2 is None and np.array_equal(forster.exp, m.exp)


@pytest.mark.parametrize("scheme", ["closed_form", "forster"])
def test_rotation_alone_equals_the_full_preintegration_rotation(scheme, tmp_path):
    imu = load_imu("V1_01_easy", tmp_path)
    t0 = int(imu.t_ns[7]) + 2_345_678
    bg = torch.tensor([0.01, -0.03, 0.02], dtype=torch.float64)
    for t1 in (t0 + 1_000_000, t0 + 50_000_001, t0 + 700_000_000):
        full = preintegrate(imu, t0, t1, ImuNoise(), bg, torch.tensor([0.2, 0.1, -0.3]), scheme)
        assert torch.equal(preintegrate_rotation(imu, t0, t1, bg), full.delta_R)
    with pytest.raises(ValueError, match="inside the samples"):
        preintegrate_rotation(imu, t0, int(imu.t_ns[-1]) + 1)


def test_arbitrary_intervals_batched_equal_one_at_a_time(tmp_path):
    """Unordered, overlapping and nested intervals with one bias each, in one vectorised pass."""
    imu = load_imu("MH_03_medium", tmp_path)
    base = int(imu.t_ns[5])
    t0 = base + np.array([400_000_001, 0, 123_456_789, 10_000_000])
    t1 = base + np.array([900_000_000, 1_000_400_000, 300_000_000, 10_000_000 + 2_000_000])
    bg = torch.tensor([[0.01, 0.02, 0.03]] * 4, dtype=torch.float64) * torch.arange(1, 5)[:, None]
    ba = -2 * bg
    batch = preintegrate_intervals(imu, t0, t1, ImuNoise(), bg, ba)
    assert list(batch.t0_ns) == list(t0) and list(batch.t1_ns) == list(t1)
    for k in range(4):
        one = preintegrate(imu, t0[k], t1[k], ImuNoise(), bg[k], ba[k])
        for name in ("delta_R", "delta_v", "delta_p", "cov", "J_R_bg", "J_v_bg", "J_v_ba", "J_p_bg", "J_p_ba"):
            assert torch.allclose(getattr(batch.item(k), name), getattr(one, name), rtol=1e-12, atol=1e-14), name
    with pytest.raises(ValueError, match="interval starts and ends"):
        preintegrate_intervals(imu, t0, t1[:3], ImuNoise())
    with pytest.raises(ValueError, match="t1 > t0"):
        preintegrate_intervals(imu, t1[:1], t0[:1], ImuNoise())
