"""State propagation through IMU samples on analytic motion."""
from __future__ import annotations

import numpy as np
import torch

from vigs_core.geometry import so3_log
from vigs_core.imu.analytic_motion import AnalyticMotion
from vigs_core.imu.preintegration import preintegrate
from vigs_core.imu.propagation import ImuState, predict_state, propagate, propagate_path
from vigs_core.types import ImuNoise

torch.set_num_threads(1)  # the test machine is shared; one thread each is fastest

F64 = torch.float64


def test_propagation_follows_the_analytic_motion_at_every_sample():
    motion = AnalyticMotion.default()
    imu = motion.imu(np.arange(0, 3_000_000_000, 1_000_000))
    t0, t1 = 700_000_321, 1_600_000_987
    R, p, v = motion.state(np.array([t0 * 1e-9]))
    zero = torch.zeros(3, dtype=F64)
    state = ImuState(t0, R[0], p[0], v[0], zero, zero)
    path = propagate_path(state, imu, t1)
    assert path.t_ns[0] == t0 and path.t_ns[-1] == t1 and len(path.t_ns) == 902
    R_true, p_true, v_true = motion.state(path.t_ns * 1e-9)
    assert float(so3_log(path.R.transpose(-1, -2) @ R_true).norm(dim=-1).max()) < 1e-6
    assert float((path.p - p_true).norm(dim=-1).max()) < 1e-6
    assert float((path.v - v_true).norm(dim=-1).max()) < 1e-6
    end = propagate(state, imu, t1)
    via_pre = predict_state(state, preintegrate(imu, t0, t1, ImuNoise()))
    assert end.t_ns == via_pre.t_ns == t1
    assert torch.allclose(end.R, via_pre.R, atol=1e-12) and torch.allclose(end.p, via_pre.p, atol=1e-12)
    assert torch.allclose(end.v, via_pre.v, atol=1e-12)


def test_biased_measurements_are_corrected_by_the_state_bias():
    motion = AnalyticMotion.default()
    imu = motion.imu(np.arange(0, 2_000_000_000, 1_000_000))
    bg, ba = np.array([0.01, -0.02, 0.03]), np.array([0.1, 0.05, -0.08])
    imu.gyro += bg
    imu.acc += ba
    t0, t1 = 300_000_000, 1_300_000_000
    R, p, v = motion.state(np.array([t0, t1]) * 1e-9)
    state = ImuState(t0, R[0], p[0], v[0], torch.tensor(bg), torch.tensor(ba))
    end = propagate(state, imu, t1)
    assert float((end.p - p[1]).norm()) < 1e-6 and float(so3_log(end.R.T @ R[1]).norm()) < 1e-6
    naive = propagate(ImuState(t0, R[0], p[0], v[0], torch.zeros(3, dtype=F64), torch.zeros(3, dtype=F64)), imu, t1)
    assert float((naive.p - p[1]).norm()) > 0.01
