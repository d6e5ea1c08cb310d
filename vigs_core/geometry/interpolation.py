"""Pose interpolation along a sampled trajectory."""
from __future__ import annotations

import torch

from vigs_core.geometry.so3 import so3_exp, so3_log


def interpolate_poses(
    times: torch.Tensor, rotations: torch.Tensor, positions: torch.Tensor, query: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Interpolate a trajectory at ``query`` times.

    Args:
        times: (N,) strictly increasing sample times (s).
        rotations: (N, 3, 3) rotations ``R_WB`` at the samples.
        positions: (N, 3) positions ``p_WB`` at the samples.
        query: (M,) times inside ``[times[0], times[-1]]``.

    Returns:
        (M, 3, 3) rotations by SLERP, ``R_k Exp(a Log(R_k^T R_{k+1}))``, and (M, 3) positions by
        linear interpolation, with ``a`` the fractional position of the query in its interval.
    """
    if query.min() < times[0] or query.max() > times[-1]:
        raise ValueError(
            f"query times [{float(query.min())}, {float(query.max())}] leave the trajectory's span "
            f"[{float(times[0])}, {float(times[-1])}]"
        )
    k = torch.searchsorted(times, query, right=True).clamp(1, len(times) - 1) - 1
    alpha = ((query - times[k]) / (times[k + 1] - times[k])).to(rotations.dtype)
    r0, r1 = rotations[k], rotations[k + 1]
    delta = so3_log(r0.transpose(-1, -2) @ r1)
    rot = r0 @ so3_exp(alpha[:, None] * delta)
    pos = positions[k] + alpha[:, None] * (positions[k + 1] - positions[k])
    return rot, pos
