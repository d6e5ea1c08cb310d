"""Association, ATE, RPE and recall on hand-checkable trajectories."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vigs_core.eval import associate, ate, evaluate_trajectory, recall, rotation_angle, rpe, rpe_pairs
from vigs_core.types import Trajectory

MS = 1_000_000


def test_associate_nearest_within_max_diff():
    ref = np.array([0, 10, 20, 30, 40]) * MS
    est = np.array([1, 14, 18, 42]) * MS  # est is sparser: each est stamp looks for its nearest ref
    i_ref, i_est = associate(ref, est, 3 * MS)
    np.testing.assert_array_equal(i_est, [0, 2, 3])  # 14 ms is 4 ms from 10 ms: too far
    np.testing.assert_array_equal(i_ref, [0, 2, 4])
    # Ties go to the earlier stamp; the boundary |dt| == max_diff is accepted.
    i_ref, i_est = associate(ref, np.array([5, 35]) * MS, 5 * MS)
    np.testing.assert_array_equal(i_ref, [0, 3])
    i_ref, i_est = associate(ref, np.array([5]) * MS, 5 * MS - 1)
    assert len(i_ref) == 0


def test_associate_unsorted_and_swapped_roles():
    ref = np.array([30, 0, 20, 10]) * MS
    est = np.array([21, 9, 1, 29, 40, 50]) * MS  # est is denser here: each ref stamp looks up est
    i_ref, i_est = associate(ref, est, 2 * MS)
    pairs = sorted(zip(ref[i_ref], est[i_est]))
    assert pairs == [(0, 1 * MS), (10 * MS, 9 * MS), (20 * MS, 21 * MS), (30 * MS, 29 * MS)]
    with pytest.raises(ValueError, match="max_diff_ns must be >= 0"):
        associate(ref, est, -1)


def test_ate_statistics():
    gt = np.zeros((4, 3))
    est = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    stats = ate(gt, est)
    assert stats["rmse"] == pytest.approx(np.sqrt((25 + 1 + 4 + 0) / 4))
    assert stats["mean"] == pytest.approx(2.0)
    assert stats["median"] == pytest.approx(1.5)
    assert stats["max"] == pytest.approx(5.0)


def test_rotation_angle_near_zero_and_pi():
    angles = np.array([1e-9, 0.3, np.pi - 1e-7, np.pi])
    rots = Rotation.from_rotvec(angles[:, None] * np.array([[1.0, 2.0, 2.0]]) / 3.0).as_matrix()
    np.testing.assert_allclose(rotation_angle(rots), angles, rtol=1e-6, atol=1e-15)


def straight_line(n: int = 21, speed: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Poses moving along x at ``speed`` m/s, sampled at 10 Hz (stamps with jitter of +-100 ns)."""
    t_ns = np.arange(n) * 100 * MS + np.random.default_rng(0).integers(-100, 100, size=n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = speed * np.arange(n) * 0.1
    return poses, t_ns


def test_rpe_pairs_by_distance_and_time():
    poses, t_ns = straight_line()
    i, j = rpe_pairs(poses[:, :3, 3], t_ns, 0.5, "m")
    np.testing.assert_array_equal(i, np.arange(16))
    np.testing.assert_array_equal(j - i, 5)
    i, j = rpe_pairs(poses[:, :3, 3], t_ns, 1.0, "s")  # stamp jitter must not shift pairs to 1.1 s
    np.testing.assert_array_equal(j - i, 10)
    assert len(i) in (10, 11)
    with pytest.raises(ValueError, match="unit must be one of"):
        rpe_pairs(poses[:, :3, 3], t_ns, 1.0, "frames")


def test_rpe_of_known_drift():
    gt, t_ns = straight_line()
    est = gt.copy()
    est[:, 0, 3] *= 1.1  # 10 % too fast: over 0.5 m the estimate moves 0.55 m
    yaw_rate = np.radians(2.0)  # and turns 2 deg per pose
    est[:, :3, :3] = Rotation.from_euler("z", yaw_rate * np.arange(len(gt))[:, None]).as_matrix()
    stats = rpe(gt, est, t_ns, 0.5, "m")
    assert stats["pairs"] == 16
    # Relative translation: R_i^T (p_j - p_i) of length 0.55 against the true 0.5 m along x.
    expected = np.hypot(0.55 * np.cos(-yaw_rate * np.arange(16)) - 0.5, 0.55 * np.sin(-yaw_rate * np.arange(16)))
    assert stats["trans_max"] == pytest.approx(expected.max(), rel=1e-9)
    assert stats["trans_rmse"] == pytest.approx(np.sqrt(np.mean(expected**2)), rel=1e-9)
    assert stats["rot_rmse"] == pytest.approx(10.0, rel=1e-9)  # 5 poses x 2 deg
    assert stats["rot_max"] == pytest.approx(10.0, rel=1e-9)
    with pytest.raises(ValueError, match="shorter than delta"):
        rpe(gt, est, t_ns, 100.0, "m")


def test_recall_counts_unmatched_ground_truth_as_misses():
    errors = np.array([0.01, 0.2, 0.07, 0.03])
    gt_index = np.array([0, 1, 2, 2])  # pose 2 paired twice: its best error 0.03 counts
    result = recall(errors, gt_index, n_gt=5, thresholds=(0.05, 0.1, 1.0))
    assert result == {0.05: 2 / 5, 0.1: 2 / 5, 1.0: 3 / 5}


def helix(n: int = 100) -> Trajectory:
    s = np.linspace(0.0, 4.0 * np.pi, n)
    position = np.stack((np.cos(s), np.sin(s), 0.1 * s), axis=1) * 2.0
    quat = Rotation.from_euler("z", s[:, None]).as_quat(scalar_first=True)
    return Trajectory(10**18 + np.arange(n) * 50 * MS, position, quat)


def test_evaluate_trajectory_with_misses_and_scale():
    gt = helix()
    keep = np.ones(len(gt), bool)
    keep[::4] = False  # a quarter of the ground-truth poses get no estimate
    rot = Rotation.from_rotvec([0.2, -0.1, 1.0]).as_matrix()
    est_pos = 0.5 * gt.position[keep] @ rot.T + [3.0, 1.0, -2.0]
    est = Trajectory(gt.t_ns[keep] + 3 * MS, est_pos, gt.quat_wxyz[keep])
    result = evaluate_trajectory(gt, est, align="sim3", thresholds=(0.05,), max_diff_s=0.005)
    assert result["n_matched"] == keep.sum()
    assert result["ate_rmse"] < 1e-9
    assert result["scale"] == pytest.approx(2.0, rel=1e-12)
    assert result["recall@0.05"] == pytest.approx(keep.mean())
    # Stamps 3 ms apart are not associated with a 2 ms limit.
    with pytest.raises(ValueError, match="no estimate stamp lies within 0.002 s"):
        evaluate_trajectory(gt, est, max_diff_s=0.002)


def test_evaluate_trajectory_posyaw_and_rpe_keys():
    gt = helix()
    yaw = Rotation.from_euler("z", 1.2)
    est = Trajectory(
        gt.t_ns,
        yaw.apply(gt.position) + [1.0, 2.0, 3.0],
        (yaw * Rotation.from_quat(gt.quat_wxyz, scalar_first=True)).as_quat(scalar_first=True),
    )
    result = evaluate_trajectory(gt, est, align="posyaw", rpe_delta=1.0, rpe_unit="m")
    assert result["ate_max"] < 1e-9
    assert result["rpe_trans_max"] < 1e-9 and result["rpe_rot_max"] < 1e-6
    assert result["rpe_pairs"] > 50 and result["rpe_unit"] == "m"
    unaligned = evaluate_trajectory(gt, est, align="none")
    assert unaligned["ate_rmse"] > 1.0 and unaligned["recall@0.1"] == 0.0
