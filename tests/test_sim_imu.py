"""IMU synthesis: noise-free round trip through the project's preintegration, noise statistics, motions."""
import numpy as np
import pytest
import torch

from vigs_core.imu.preintegration import preintegrate
from vigs_core.sim.hybrid import euroc_cam0_calibration
from vigs_core.sim.imu_synthesis import GRAVITY, imu_stamps, synthesize_imu
from vigs_core.sim.trajectory import ProceduralConfig, ProceduralMotion, SplineMotion, trajectory_from_motion
from vigs_core.types import ImuNoise

torch.set_num_threads(1)


def _motion(seed=3, duration=6.0):
    R_BC = euroc_cam0_calibration().T_BS[:3, :3]
    return ProceduralMotion(seed, R_BC, ProceduralConfig(duration_s=duration))


def _so3_angle(R):
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


@pytest.mark.parametrize("t_from, t_to", [(0.5, 1.5), (2.0, 4.5)])
def test_noise_free_imu_preintegrates_to_ground_truth_relative_poses(t_from, t_to):
    motion = _motion()
    t_ns = imu_stamps(motion.start_ns, motion.end_ns, 4000.0)
    synth = synthesize_imu(motion, t_ns, noise=None)
    i_ns, j_ns = motion.start_ns + int(t_from * 1e9), motion.start_ns + int(t_to * 1e9)
    pre = preintegrate(synth.imu, i_ns, j_ns, ImuNoise(rate_hz=4000.0))
    si, sj = motion.evaluate(np.array([i_ns])), motion.evaluate(np.array([j_ns]))
    Ri, Rj = si.rotation[0], sj.rotation[0]
    dt = (j_ns - i_ns) * 1e-9
    g = np.array([0.0, 0.0, -GRAVITY])
    dR = Ri.T @ Rj
    dv = Ri.T @ (sj.velocity[0] - si.velocity[0] - g * dt)
    dp = Ri.T @ (sj.position[0] - si.position[0] - si.velocity[0] * dt - 0.5 * g * dt**2)
    assert _so3_angle(dR.T @ pre.delta_R.numpy()) < 1e-6
    assert np.abs(pre.delta_v.numpy() - dv).max() < 1e-6
    assert np.abs(pre.delta_p.numpy() - dp).max() < 1e-6
    # the motion really moves (the check above is not trivially satisfied)
    assert _so3_angle(dR) > 0.02 and np.linalg.norm(dp) > 0.05


def test_procedural_angular_rate_matches_numerical_derivative():
    motion = _motion(seed=5)
    t = motion.start_ns + np.array([1_000_000_000, 2_500_000_000])
    h = 1000  # ns
    state = motion.evaluate(t)
    Rp, Rm = motion.evaluate(t + h).rotation, motion.evaluate(t - h).rotation
    for k in range(2):
        dR = (Rp[k] - Rm[k]) / (2 * h * 1e-9)
        W = state.rotation[k].T @ dR
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        np.testing.assert_allclose(state.omega_body[k], omega, atol=1e-6)
        acc_num = (motion.evaluate(t + h).velocity[k] - motion.evaluate(t - h).velocity[k]) / (2 * h * 1e-9)
        np.testing.assert_allclose(state.acceleration[k], acc_num, atol=1e-5)


def test_accelerometer_reads_gravity_at_rest_and_spline_follows_samples():
    t_ns = 10**9 + np.arange(50) * 50_000_000
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (50, 1))
    from vigs_core.types import Trajectory

    still = SplineMotion(Trajectory(t_ns, np.tile([1.0, 2.0, 3.0], (50, 1)), quat))
    synth = synthesize_imu(still, imu_stamps(t_ns[0], t_ns[-1], 200.0))
    np.testing.assert_allclose(synth.imu.acc, np.tile([0.0, 0.0, GRAVITY], (len(synth.imu), 1)), atol=1e-9)
    np.testing.assert_allclose(synth.imu.gyro, 0.0, atol=1e-9)
    # a spline through samples of a smooth motion reproduces its rates closely between the samples
    motion = _motion(seed=7)
    samples = trajectory_from_motion(motion, imu_stamps(motion.start_ns, motion.end_ns, 100.0))
    spline = SplineMotion(samples)
    t = imu_stamps(motion.start_ns + 10**9, motion.end_ns - 10**9, 333.0)
    np.testing.assert_allclose(spline.evaluate(t).omega_body, motion.evaluate(t).omega_body, atol=2e-3)
    np.testing.assert_allclose(spline.evaluate(t).acceleration, motion.evaluate(t).acceleration, atol=2e-2)


def test_noise_and_bias_walk_follow_the_noise_model():
    motion = _motion(seed=1, duration=60.0)
    t_ns = imu_stamps(motion.start_ns, motion.end_ns, 200.0)
    noise = ImuNoise(gyro_noise_density=2e-3, gyro_random_walk=1e-3, acc_noise_density=2e-2, acc_random_walk=3e-3)
    clean = synthesize_imu(motion, t_ns)
    noisy = synthesize_imu(motion, t_ns, noise, seed=11)
    again = synthesize_imu(motion, t_ns, noise, seed=11)
    np.testing.assert_array_equal(noisy.imu.gyro, again.imu.gyro)  # deterministic in the seed
    white_g = noisy.imu.gyro - clean.imu.gyro - noisy.bias_gyro
    white_a = noisy.imu.acc - clean.imu.acc - noisy.bias_acc
    dt = 1 / 200.0
    assert white_g.std() == pytest.approx(noise.gyro_noise_density / np.sqrt(dt), rel=0.05)
    assert white_a.std() == pytest.approx(noise.acc_noise_density / np.sqrt(dt), rel=0.05)
    steps = np.diff(noisy.bias_gyro, axis=0)
    assert steps.std() == pytest.approx(noise.gyro_random_walk * np.sqrt(dt), rel=0.05)
    assert np.diff(noisy.bias_acc, axis=0).std() == pytest.approx(noise.acc_random_walk * np.sqrt(dt), rel=0.05)
    np.testing.assert_array_equal(noisy.bias_gyro[0], 0.0)
