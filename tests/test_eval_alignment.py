"""Alignment: exact recovery of known Sim(3), SE(3) and position+yaw transforms."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vigs_core.eval import align, position_yaw_alignment, umeyama


def points(n: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3)) * [3.0, 2.0, 1.0]


def rotz(theta: float) -> np.ndarray:
    return Rotation.from_euler("z", theta).as_matrix()


@pytest.mark.parametrize("seed", range(5))
def test_umeyama_recovers_sim3_exactly(seed):
    rng = np.random.default_rng(seed)
    rot = Rotation.random(random_state=seed).as_matrix()
    scale, trans = float(rng.uniform(0.2, 5.0)), rng.normal(size=3) * 10
    src = points(seed=seed)
    dst = scale * src @ rot.T + trans
    s, r, t = umeyama(src, dst, with_scale=True)
    assert s == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(t, trans, atol=1e-10)
    result = align(dst, src, "sim3")
    np.testing.assert_allclose(result.apply_positions(src), dst, atol=1e-10)
    np.testing.assert_allclose(result.matrix()[:3, :3], scale * rot, atol=1e-12)


def test_umeyama_se3_recovers_rigid_transform_and_keeps_scale_one():
    rot = Rotation.from_rotvec([0.3, -2.9, 0.5]).as_matrix()
    src = points()
    dst = src @ rot.T + [1.0, -2.0, 3.0]
    s, r, t = umeyama(src, dst, with_scale=False)
    assert s == 1.0
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, -2.0, 3.0], atol=1e-12)
    # SE(3) on scaled data does not absorb the scale (the errors stay).
    result = align(2.0 * dst, src, "se3")
    assert result.scale == 1.0
    assert np.abs(result.apply_positions(src) - 2.0 * dst).max() > 0.5


def test_umeyama_returns_a_rotation_for_reflected_data():
    src = points()
    dst = src * [1.0, 1.0, -1.0]  # a mirror image: the best proper rotation is not the reflection
    _, r, _ = umeyama(src, dst, with_scale=False)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)


@pytest.mark.parametrize("theta", [0.0, 0.7, -2.5, np.pi])
def test_position_yaw_recovers_4dof_exactly(theta):
    src = points(seed=3)
    dst = src @ rotz(theta).T + [0.5, -4.0, 1.5]
    r, t = position_yaw_alignment(src, dst)
    np.testing.assert_allclose(r, rotz(theta), atol=1e-12)
    np.testing.assert_allclose(t, [0.5, -4.0, 1.5], atol=1e-12)
    assert align(dst, src, "posyaw").scale == 1.0


def test_position_yaw_is_least_squares_under_noise():
    """With noise the closed form must beat every nearby yaw (it is the minimiser)."""
    rng = np.random.default_rng(7)
    src = points(seed=7)
    dst = src @ rotz(1.1).T + [2.0, 0.0, -1.0] + rng.normal(scale=0.05, size=src.shape)
    r, t = position_yaw_alignment(src, dst)
    cost = np.sum((src @ r.T + t - dst) ** 2)
    theta = np.arctan2(r[1, 0], r[0, 0])
    for d in (-1e-3, 1e-3):
        rd = rotz(theta + d)
        td = dst.mean(0) - rd @ src.mean(0)
        assert np.sum((src @ rd.T + td - dst) ** 2) > cost
    # A roll/pitch error is not absorbed: posyaw keeps z-axis rotation only.
    tilted = src @ Rotation.from_euler("x", 0.2).as_matrix().T
    assert np.abs(align(tilted, src, "posyaw").rotation[2]).max() == pytest.approx(1.0)


def test_none_and_errors():
    src = points(n=5)
    result = align(src + 1.0, src, "none")
    np.testing.assert_array_equal(result.matrix(), np.eye(4))
    with pytest.raises(ValueError, match="mode must be one of"):
        align(src, src, "affine")
    with pytest.raises(ValueError, match="needs at least 3 associated poses, got 2"):
        align(src[:2], src[:2], "sim3")
    line = np.outer(np.arange(10.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(line, line, with_scale=True)
    vertical = np.outer(np.arange(10.0), [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="no horizontal motion"):
        position_yaw_alignment(vertical, vertical)


def test_apply_poses_rotates_orientation_and_scales_position_only():
    rot = rotz(0.5)
    result = align(2.0 * points() @ rot.T, points(), "sim3")
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 0.0, 0.0]
    out = result.apply_poses(pose[None])[0]
    np.testing.assert_allclose(out[:3, :3], rot, atol=1e-12)
    np.testing.assert_allclose(out[:3, 3], 2.0 * rot @ [1.0, 0.0, 0.0], atol=1e-12)
