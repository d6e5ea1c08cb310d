"""Ground-truth jump repair of hybrid sources: tracker glitches removed, real motion untouched."""
from __future__ import annotations

import numpy as np
import pytest

from vigs_core.sim.hybrid import hybrid_source, repair_position_jumps
from vigs_core.types import ImuSamples, Trajectory


def circle(n: int = 1000, rate_hz: float = 200.0) -> Trajectory:
    """1.5 m/s on a 1 m circle with a vertical bob (centripetal 2.25 m/s^2), sampled at 200 Hz."""
    t = np.arange(n) / rate_hz
    w = 1.5
    p = np.stack((np.cos(w * t), np.sin(w * t), 0.2 * np.sin(3 * t)), axis=1)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return Trajectory((1_000_000_000 + t * 1e9).astype(np.int64), p, q)


def test_clean_motion_is_left_alone():
    traj = circle()
    repaired, jumps = repair_position_jumps(traj)
    assert len(jumps) == 0 and repaired is traj


def test_steps_and_spikes_are_removed():
    truth = circle()
    p = truth.position.copy()
    p[300:] += [0.05, -0.02, 0.0]        # a 5.4 cm step that stays
    p[600] += [0.0, 0.0, 0.03]           # a 3 cm spike (one sample out and back)
    glitched = Trajectory(truth.t_ns, p, truth.quat_wxyz)
    repaired, jumps = repair_position_jumps(glitched)
    assert set(jumps.tolist()) == {299, 599, 600}
    np.testing.assert_allclose(repaired.position, truth.position, atol=1e-4)
    np.testing.assert_array_equal(repaired.quat_wxyz, truth.quat_wxyz)


def test_hybrid_source_warns_and_renders_the_repaired_motion():
    truth = circle()
    p = truth.position.copy()
    p[500:] += [0.0, 0.08, 0.0]
    imu = ImuSamples(truth.t_ns, np.zeros((len(truth), 3)), np.tile([0.0, 0.0, 9.81], (len(truth), 1)))
    with pytest.warns(UserWarning, match="repaired 1 ground-truth position jumps"):
        source = hybrid_source(Trajectory(truth.t_ns, p, truth.quat_wxyz), imu)
    np.testing.assert_allclose(source.groundtruth.position, truth.position, atol=1e-4)
    _, p_wb = source.motion.poses(truth.t_ns[[100, 700]])
    np.testing.assert_allclose(np.asarray(p_wb), truth.position[[100, 700]], atol=1e-4)
    kept = hybrid_source(Trajectory(truth.t_ns, p, truth.quat_wxyz), imu, jump_threshold_m=None)
    np.testing.assert_array_equal(kept.groundtruth.position, p)
