"""Keyframe-anchored updates (VIGS-SLAM Eq. 6-7): Gaussians move exactly with their keyframe."""
from __future__ import annotations

import pytest
import torch

from vigs_core.geometry import quat_to_matrix, se3_exp, se3_inverse
from vigs_core.mapping.anchor import anchored_update

torch.set_num_threads(1)


def _covariances(quats: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    m = quat_to_matrix(quats) * log_scales.exp()[:, None, :]
    return m @ m.transpose(-1, -2)


def test_anchored_gaussians_keep_their_pose_relative_to_the_keyframe():
    dt = torch.float64
    g = torch.Generator().manual_seed(1)
    n = 50
    means = torch.randn(n, 3, generator=g, dtype=dt) * 2.0
    quats = torch.randn(n, 4, generator=g, dtype=dt)
    log_scales = torch.randn(n, 3, generator=g, dtype=dt) * 0.3 - 3.0
    anchors = torch.tensor([3] * 20 + [7] * 20 + [9] * 10, dtype=torch.int64)
    old = {k: se3_exp(torch.randn(6, generator=g, dtype=dt)) for k in (3, 7, 9)}
    new = {3: se3_exp(torch.randn(6, generator=g, dtype=dt)), 7: se3_exp(torch.randn(6, generator=g, dtype=dt))}
    scales = {3: 1.7}
    m2, q2, s2, moved = anchored_update(means, quats, log_scales, anchors, old, new, scales)
    assert moved.tolist() == [True] * 40 + [False] * 10
    cov, cov2 = _covariances(quats, log_scales), _covariances(q2, s2)
    for kf, rows, s in ((3, slice(0, 20), 1.7), (7, slice(20, 40), 1.0)):
        T_old_inv, T_new_inv = se3_inverse(old[kf]), se3_inverse(new[kf])
        local_old = means[rows] @ T_old_inv[:3, :3].T + T_old_inv[:3, 3]
        local_new = m2[rows] @ T_new_inv[:3, :3].T + T_new_inv[:3, 3]
        torch.testing.assert_close(local_new, s * local_old, rtol=1e-12, atol=1e-12)
        R_old, R_new = old[kf][:3, :3], new[kf][:3, :3]
        torch.testing.assert_close(
            R_new.T @ cov2[rows] @ R_new, s * s * (R_old.T @ cov[rows] @ R_old), rtol=1e-10, atol=1e-14
        )
    # Gaussians of keyframes without a new pose are untouched
    assert torch.equal(m2[40:], means[40:]) and torch.equal(q2[40:], quats[40:])
    assert torch.equal(s2[40:], log_scales[40:])


def test_anchored_update_rejects_inconsistent_input():
    dt = torch.float64
    args = (torch.zeros(1, 3, dtype=dt), torch.tensor([[1.0, 0, 0, 0]], dtype=dt), torch.zeros(1, 3, dtype=dt))
    ids = torch.tensor([0])
    eye = torch.eye(4, dtype=dt)
    with pytest.raises(KeyError, match="no previous pose"):
        anchored_update(*args, ids, {}, {0: eye})
    with pytest.raises(ValueError, match="> 0"):
        anchored_update(*args, ids, {0: eye}, {0: eye}, {0: -1.0})
    with pytest.raises(ValueError, match="without a new pose"):
        anchored_update(*args, ids, {0: eye}, {0: eye}, {1: 2.0})
