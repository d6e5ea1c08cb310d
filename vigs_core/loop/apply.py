"""Applying PGBA's per-keyframe Sim(3) corrections to the frontend state and to the Gaussian map in one batch
(VIGS-SLAM Sec. 3.1 "the frontend continues from the corrected states" and Sec. 3.3, Eq. 6-7).

A correction ``C_k = [c R_c, t_c]`` acts on the keyframe's similarity from the left: the keyframe's rigid pose
``T_WC = [R, t]`` becomes ``S' = C T_WC = [c R_c R, c R_c t + t_c]``, i.e. the rigid pose ``T'_WC = [R_c R,
c R_c t + t_c]`` with depths scaled by ``c`` (disparities divided by ``c``): a point ``X`` of the keyframe
(camera frame, old units) lands at ``S' X = T'_WC (c X)``. The mapper's anchored update takes exactly
``(T'_WC, c)`` per keyframe (:func:`vigs_core.mapping.anchor.anchored_update`). Keyframes created after the
PGBA's snapshot get the correction of the newest keyframe of the snapshot (they were tracked relative to it).
"""
from __future__ import annotations

from typing import Any, Iterable

import torch

from vigs_core.geometry import nearest_rotation, se3_inverse, sim3_scale

F64 = torch.float64


def corrected_poses(C: torch.Tensor, T_WC: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid poses ``T'_WC`` (..., 4, 4) and depth scales ``c`` (...) of keyframes after the corrections ``C``
    (..., 4, 4): ``S = C T_WC``, ``c = det(S_R)^(1/3)``, ``T'_WC = [S_R / c | S_t]`` with the rotation block
    projected onto SO(3): keyframes take one correction after another over a long run, and each product's
    rounding error would otherwise stay in their poses."""
    S = C.to(F64) @ torch.as_tensor(T_WC, dtype=F64)
    c = sim3_scale(S)
    T = S.clone()
    T[..., :3, :3] = nearest_rotation(S[..., :3, :3] / c[..., None, None])
    return T, c


def corrected_pose(C: torch.Tensor, T_WC: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Rigid pose ``T'_WC`` (4, 4) and depth scale ``c`` of one keyframe after the correction ``C`` (4, 4)."""
    T, c = corrected_poses(C, T_WC)
    return T, float(c)


def corrections_for(ids: Iterable[int], corrections: dict[int, torch.Tensor]) -> dict[int, torch.Tensor]:
    """Corrections for every id in ``ids``: its own, or for ids newer than the snapshot the newest one's; ids
    older than every corrected one are left out."""
    if not corrections:
        return {}
    newest = max(corrections)
    return {k: corrections[k] if k in corrections else corrections[newest] for k in ids
            if k in corrections or k > newest}


def apply_to_odometry(odometry: Any, corrections: dict[int, torch.Tensor]) -> dict[int, tuple[torch.Tensor, float]]:
    """Correct a :class:`vigs_core.frontend.DenseOdometry` in place.

    Keyframe poses (world->camera ``T_cw``) become ``T'_WC^{-1}``, disparities are divided by ``c``; the poses
    kept relative to a keyframe (frames, tracked keyframe poses: ``scale_relative_translations``) keep their
    rotation with the translation scaled by that keyframe's ``c``. The frames' causal poses stay as output (the
    constant-velocity motion model reads the latest frames through their reference keyframes). Returns
    ``{kf_id: (T'_WC, c)}`` of the corrected keyframes.
    """
    per_kf = corrections_for(sorted(odometry.keyframes), corrections)
    updates: dict[int, tuple[torch.Tensor, float]] = {}
    if per_kf:   # one batched product over all corrected keyframes
        ids = list(per_kf)
        T_WC, c = corrected_poses(torch.stack([per_kf[k] for k in ids]),
                                  se3_inverse(torch.stack([odometry.keyframes[k].pose for k in ids])))
        poses = se3_inverse(T_WC)
        for k, pose, T, scale in zip(ids, poses.unbind(0), T_WC.unbind(0), c.tolist()):
            kf = odometry.keyframes[k]
            kf.pose = pose
            kf.rescale_depth(scale)
            updates[k] = (T, scale)
    odometry.scale_relative_translations({k: scale for k, (_, scale) in updates.items()})
    return updates


def rotate_velocities(states: dict[int, Any], corrections: dict[int, torch.Tensor]) -> None:
    """Keyframes' inertial velocities under their corrections, ``v' = c R_c v`` (``C[:3, :3] = c R_c``), in one
    batched product; ``states`` maps keyframe ids to objects with a ``velocity`` (3,), ids without one are left
    out."""
    ids = [k for k in corrections if k in states]
    if ids:
        C = torch.stack([corrections[k] for k in ids]).to(F64)
        v = torch.stack([states[k].velocity for k in ids]).to(F64)
        for k, v_new in zip(ids, (C[:, :3, :3] @ v[..., None])[..., 0].unbind(0)):
            states[k].velocity = v_new


def apply_to_mapper(mapper: Any, updates: dict[int, tuple[torch.Tensor, float]]) -> None:
    """Queue the corrected keyframe poses and depth scales on a :class:`vigs_core.mapping.mapper.GaussianMapper`:
    its anchored Gaussians follow in one batch (Eq. 6-7)."""
    if updates:
        mapper.update_keyframe_poses({k: T for k, (T, _) in updates.items()},
                                     {k: c for k, (_, c) in updates.items()})
