"""Keyframe-anchored map updates (VIGS-SLAM Sec. 3.3, Eq. 6-7).

Each Gaussian is anchored to the keyframe ``k`` that created it. When loop closure / bundle adjustment moves
that keyframe from ``T_k = (R_k, t_k)`` to ``T'_k = (R'_k, t'_k)`` and rescales its depth by ``s_k``, the
Gaussian keeps its position *relative to the keyframe*, scaled by ``s_k``:

    mu'    = R'_k (s_k R_k^T (mu - t_k)) + t'_k                       (Eq. 6)
    Sigma' = s_k^2 (R'_k R_k^T) Sigma (R'_k R_k^T)^T                   (Eq. 7)

i.e. the similarity ``S_k = T'_k diag(s_k, 1) T_k^{-1}`` acts on the mean, the rotation
``dR_k = R'_k R_k^T`` is left-multiplied onto the Gaussian's orientation (``q' = q(dR_k) q``) and the log
scales grow by ``log s_k``. Opacity and colour are unchanged. All Gaussians of all moved keyframes are
updated in one batched operation.
"""
from __future__ import annotations

import torch

from vigs_core.geometry import matrix_to_quat, quat_multiply


def anchored_update(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    anchor_ids: torch.Tensor,
    old_poses: dict[int, torch.Tensor],
    new_poses: dict[int, torch.Tensor],
    scales: dict[int, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Move the Gaussians anchored to the keyframes in ``new_poses`` (Eq. 6-7).

    Args:
        means: (N, 3) world positions, metres.
        quats: (N, 4) ``(w, x, y, z)`` orientations.
        log_scales: (N, 3) log standard deviations.
        anchor_ids: (N,) int64 keyframe id per Gaussian.
        old_poses: ``{kf_id: T_WC (4, 4)}`` the poses the Gaussians were expressed with; must contain every
            id of ``new_poses``.
        new_poses: ``{kf_id: T_WC (4, 4)}`` corrected rigid poses.
        scales: optional ``{kf_id: s}`` depth scale corrections (default 1 for every keyframe).

    Returns:
        ``(means, quats, log_scales, moved)``: updated copies and the (N,) bool mask of moved rows.
    """
    scales = scales or {}
    unknown = set(scales) - set(new_poses)
    if unknown:
        raise ValueError(f"scale corrections given for keyframes without a new pose: {sorted(unknown)}")
    missing = set(new_poses) - set(old_poses)
    if missing:
        raise KeyError(f"no previous pose for keyframes {sorted(missing)}; known keyframes: {sorted(old_poses)}")
    dtype, device = means.dtype, means.device
    if not new_poses or means.shape[0] == 0:
        none = torch.zeros(means.shape[0], dtype=torch.bool, device=device)
        return means.clone(), quats.clone(), log_scales.clone(), none
    ids = sorted(new_poses)
    kf_ids = torch.tensor(ids, dtype=torch.int64, device=device)
    T_old = torch.stack([torch.as_tensor(old_poses[k], dtype=torch.float64) for k in ids]).to(device)
    T_new = torch.stack([torch.as_tensor(new_poses[k], dtype=torch.float64) for k in ids]).to(device)
    s = torch.tensor([float(scales.get(k, 1.0)) for k in ids], dtype=torch.float64, device=device)
    if not bool((s > 0).all()):
        raise ValueError(f"keyframe scale corrections must be > 0, got {dict(zip(ids, s.tolist()))}")
    dR = T_new[:, :3, :3] @ T_old[:, :3, :3].transpose(1, 2)  # (K, 3, 3)
    # mu' = s dR mu + (t' - s dR t)
    A = s[:, None, None] * dR
    b = T_new[:, :3, 3] - (A @ T_old[:, :3, 3, None])[..., 0]
    pos = torch.searchsorted(kf_ids, anchor_ids).clamp_max(len(ids) - 1)
    moved = kf_ids[pos] == anchor_ids
    rows = moved.nonzero().squeeze(1)
    k = pos[rows]
    new_means, new_quats, new_log_scales = means.clone(), quats.clone(), log_scales.clone()
    mu = means[rows].to(torch.float64)
    new_means[rows] = ((A[k] @ mu[..., None])[..., 0] + b[k]).to(dtype)
    dq = matrix_to_quat(dR)[k]
    new_quats[rows] = quat_multiply(dq, quats[rows].to(torch.float64)).to(dtype)
    new_log_scales[rows] = log_scales[rows] + s.log()[k].to(dtype)[:, None]
    return new_means, new_quats, new_log_scales, moved
