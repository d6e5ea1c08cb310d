"""Inertial-only initialisation: exact on noise-free analytic motion, accurate on a real V1_01 excerpt."""
from __future__ import annotations

import gzip
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from vigs_core.geometry import matrix_to_quat, se3_exp, se3_inverse
from vigs_core.imu.analytic_motion import AnalyticMotion
from vigs_core.imu.inertial_init import InertialInitConfig, inertial_only_init
from vigs_core.imu.init_scenario import init_errors, make_scenario
from vigs_core.imu.static_init import detect_static_segments
from vigs_core.io import read_camera_yaml, read_euroc_groundtruth, read_euroc_imu, read_imu_yaml
from vigs_core.types import ImuNoise, ImuSamples, Trajectory

torch.set_num_threads(1)  # the test machine is shared; one thread each is fastest

DATA = Path(__file__).parent / "data" / "imu"
F64 = torch.float64


def unzip(name: str, tmp_path: Path) -> Path:
    out = tmp_path / name.removesuffix(".gz")
    with gzip.open(DATA / name, "rb") as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return out


def test_noise_free_analytic_motion_is_recovered_exactly():
    motion = AnalyticMotion.default()
    imu = motion.imu(np.arange(0, 12_000_000_000, 1_000_000))
    t_kf = np.arange(1_000_000_000, 11_000_000_001, 250_000_000) + 123_457
    R, p, _ = motion.state(t_kf * 1e-9)
    gt = Trajectory(t_kf, p.numpy(), matrix_to_quat(R).numpy())
    T_bc = se3_exp(torch.tensor([0.02, -0.06, 0.01, 1.2, -1.2, 1.2], dtype=F64)).numpy()
    scenario = make_scenario(gt, int(t_kf[0]), 10.0, 0.25, T_bc, 3.7, 0.0, np.random.default_rng(0))
    calls = []   # a live caller's yield point, once per iteration
    result = inertial_only_init(scenario.T_wc, scenario.stamps_ns, imu, ImuNoise(),
                                se3_inverse(torch.as_tensor(T_bc)), between=lambda: calls.append(1))
    assert len(calls) == result.iterations > 0
    scale_err, grav_err = init_errors(result, scenario)
    assert scale_err < 1e-4 and grav_err < 0.01
    assert float(result.bias_gyro.abs().max()) < 1e-4 and float(result.bias_acc.abs().max()) < 1e-3
    assert result.trustworthy
    _, _, v = motion.state(scenario.stamps_ns * 1e-9)  # velocities in the first camera frame
    R_c0w = (torch.as_tensor(gt.matrices()[0]) @ torch.as_tensor(T_bc))[:3, :3].T
    assert float((result.velocities - (R_c0w @ v[..., None])[..., 0]).abs().max()) < 1e-3


def test_real_v1_01_excerpt_with_unknown_scale_and_rotation_noise(tmp_path):
    imu = read_euroc_imu(unzip("V1_01_easy_imu.csv.gz", tmp_path))
    gt = read_euroc_groundtruth(unzip("V1_01_easy_groundtruth.csv.gz", tmp_path))
    noise = read_imu_yaml(DATA / "imu0_sensor.yaml")
    T_bc = read_camera_yaml(DATA / "cam0_sensor.yaml").T_BS
    motion_start = detect_static_segments(imu)[0, 1]
    rng = np.random.default_rng(7)
    scenario = make_scenario(gt, int(motion_start), 10.0, 0.25, T_bc, 0.31, 0.5, rng)
    assert abs(scenario.true_scale - 1 / 0.31) < 1e-12
    result = inertial_only_init(scenario.T_wc, scenario.stamps_ns, imu, noise,
                                torch.as_tensor(np.linalg.inv(T_bc)))
    scale_err, grav_err = init_errors(result, scenario)
    assert scale_err < 0.03 and grav_err < 1.0
    # the reported uncertainty covers the actual error
    assert abs(math.log(result.scale / scenario.true_scale)) < 4 * result.log_scale_std
    k = np.searchsorted(gt.t_ns, motion_start)
    assert np.abs(result.bias_gyro.numpy() - gt.bias_gyro[k]).max() < 0.01


def test_rejects_too_few_keyframes():
    imu = AnalyticMotion.default().imu(np.arange(0, 2_000_000_000, 5_000_000))
    T = torch.eye(4, dtype=F64).expand(2, 4, 4)
    with pytest.raises(ValueError, match="N >= 3"):
        inertial_only_init(T, np.array([100_000_000, 200_000_000]), imu, ImuNoise(), torch.eye(4, dtype=F64))


@pytest.mark.parametrize("refine", [False, True])
def test_noisy_analytic_motion_error_is_covered_by_the_reported_uncertainty(refine):
    """IMU white noise at the modelled densities, 2 mm position and 0.5 deg rotation noise on the poses."""
    rng = np.random.default_rng(3)
    motion = AnalyticMotion(rot_amp=np.array([0.3, 0.2, 0.4]), rot_freq=np.array([0.9, 0.6, 1.1]),
                            rot_phase=np.array([0.1, 2.0, 4.0]), pos_amp=np.array([0.6, 0.4, 0.3]),
                            pos_freq=np.array([1.2, 0.8, 1.4]), pos_phase=np.array([1.0, 3.0, 5.0]))
    noise = ImuNoise()
    t = np.arange(0, 12_000_000_000, 5_000_000)
    clean = motion.imu(t)
    bg, ba = np.array([-0.002, 0.02, 0.077]), np.array([-0.02, 0.06, 0.03])
    imu = ImuSamples(t, clean.gyro + bg + rng.normal(0, noise.gyro_noise_density * np.sqrt(200), clean.gyro.shape),
                     clean.acc + ba + rng.normal(0, noise.acc_noise_density * np.sqrt(200), clean.acc.shape))
    t_kf = np.arange(1_000_000_000, 11_000_000_001, 250_000_000)
    R, p, _ = motion.state(t_kf * 1e-9)
    gt = Trajectory(t_kf, p.numpy() + rng.normal(0, 0.002, p.shape), matrix_to_quat(R).numpy())
    T_bc = se3_exp(torch.tensor([0.02, -0.06, 0.01, 1.2, -1.2, 1.2], dtype=F64)).numpy()
    scenario = make_scenario(gt, int(t_kf[0]), 10.0, 0.25, T_bc, 0.5, 0.5, rng)
    result = inertial_only_init(scenario.T_wc, scenario.stamps_ns, imu, noise, se3_inverse(torch.as_tensor(T_bc)),
                                InertialInitConfig(refine_rotations=refine))
    scale_err, grav_err = init_errors(result, scenario)
    assert abs(math.log(result.scale / scenario.true_scale)) < 3 * result.log_scale_std
    assert bool(result.rotation_corrections.abs().max() > 0) == refine
    assert scale_err < 0.02 and grav_err < 0.5
    assert np.abs(result.bias_gyro.numpy() - bg).max() < 0.002


def test_bias_random_walk_follows_a_drifting_accelerometer_bias():
    """A bias that drifts 0.15 m/s^2 over the window: one shared bias pushes the error into the scale, one
    bias per keyframe tied by the random walk follows the drift and keeps the scale."""
    motion = AnalyticMotion(rot_amp=np.array([0.3, 0.2, 0.4]), rot_freq=np.array([0.9, 0.6, 1.1]),
                            rot_phase=np.array([0.1, 2.0, 4.0]), pos_amp=np.array([0.6, 0.4, 0.3]),
                            pos_freq=np.array([1.2, 0.8, 1.4]), pos_phase=np.array([1.0, 3.0, 5.0]))
    t = np.arange(0, 12_000_000_000, 5_000_000)
    clean = motion.imu(t)
    drift = np.outer(t * 1e-9 / 12.0, [0.15, -0.1, 0.05])  # (N, 3) m/s^2, linear in time
    imu = ImuSamples(t, clean.gyro, clean.acc + drift)
    t_kf = np.arange(1_000_000_000, 11_000_000_001, 250_000_000)
    R, p, _ = motion.state(t_kf * 1e-9)
    gt = Trajectory(t_kf, p.numpy(), matrix_to_quat(R).numpy())
    T_bc = se3_exp(torch.tensor([0.02, -0.06, 0.01, 1.2, -1.2, 1.2], dtype=F64)).numpy()
    scenario = make_scenario(gt, int(t_kf[0]), 10.0, 0.25, T_bc, 2.0, 0.0, np.random.default_rng(0))
    noise = ImuNoise(acc_random_walk=0.02)
    errors = {}
    for walk in (False, True):
        result = inertial_only_init(scenario.T_wc, scenario.stamps_ns, imu, noise, se3_inverse(torch.as_tensor(T_bc)),
                                    InertialInitConfig(bias_random_walk=walk))
        errors[walk] = init_errors(result, scenario)
    assert errors[True][0] < 0.003 and errors[True][1] < 0.1
    assert errors[False][0] > 2 * errors[True][0] and errors[False][1] > 3 * errors[True][1]
    k = np.searchsorted(t, scenario.stamps_ns)
    assert result.keyframe_biases.shape == (len(t_kf), 6)
    assert np.abs(result.keyframe_biases[:, 3:].numpy() - drift[k]).max() < 0.03  # the drift spans 0.15
    assert np.allclose(result.bias_acc.numpy(), result.keyframe_biases[-1, 3:].numpy())
