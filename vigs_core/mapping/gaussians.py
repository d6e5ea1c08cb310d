"""Gaussian map state: one row per 3D Gaussian, stored as plain tensors.

A Gaussian ``i`` has mean ``mu_i`` (3,) in metres (world frame), covariance
``Sigma_i = R_i diag(s_i)^2 R_i^T`` with ``s_i = exp(log_scales_i)`` (metres) and ``R_i`` the rotation of the
unit quaternion ``quats_i`` (Hamilton, ``(w, x, y, z)``; stored unnormalised, normalised on use), opacity
``sigmoid(opacity_logits_i)`` in (0, 1) and an RGB colour in [0, 1] (no spherical harmonics). Each Gaussian
is anchored to the keyframe that created it (``anchor_ids``) so keyframe pose/scale corrections move it
(VIGS-SLAM Sec. 3.3, Eq. 6-7; see :mod:`vigs_core.mapping.anchor`). ``ids`` are persistent integers unique
over the life of a map, used to report added/changed/removed Gaussians to subscribers.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from vigs_core.geometry import quat_to_matrix

# The fields optimised by the mapper, in a fixed order (the rest are bookkeeping).
PARAMETER_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "colors")


@dataclass
class GaussianMap:
    """Rows of a Gaussian map (all tensors share ``N`` and the device).

    Args:
        means: (N, 3) centres in the world frame, metres.
        log_scales: (N, 3) natural log of the per-axis standard deviations, metres.
        quats: (N, 4) orientation quaternions ``(w, x, y, z)`` (need not be unit length).
        opacity_logits: (N,) ``logit(opacity)``.
        colors: (N, 3) RGB in [0, 1].
        anchor_ids: (N,) int64 id of the keyframe each Gaussian is anchored to.
        ids: (N,) int64 persistent Gaussian ids.
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    anchor_ids: torch.Tensor
    ids: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
            "colors": (n, 3),
            "anchor_ids": (n,),
            "ids": (n,),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"GaussianMap.{name} must have shape {shape} (N={n} from means), got {got}")
        for name in ("anchor_ids", "ids"):
            if getattr(self, name).dtype != torch.int64:
                raise TypeError(f"GaussianMap.{name} must be int64, got {getattr(self, name).dtype}")

    @staticmethod
    def empty(dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> GaussianMap:
        """A map with no Gaussians."""
        f = dict(dtype=dtype, device=device)
        i = dict(dtype=torch.int64, device=device)
        return GaussianMap(
            torch.zeros(0, 3, **f),
            torch.zeros(0, 3, **f),
            torch.zeros(0, 4, **f),
            torch.zeros(0, **f),
            torch.zeros(0, 3, **f),
            torch.zeros(0, **i),
            torch.zeros(0, **i),
        )

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    def scales(self) -> torch.Tensor:
        """(N, 3) standard deviations along the Gaussian's axes, metres."""
        return self.log_scales.exp()

    def opacities(self) -> torch.Tensor:
        """(N,) opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    def unit_quats(self) -> torch.Tensor:
        """(N, 4) normalised quaternions ``(w, x, y, z)``."""
        return self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def covariances(self) -> torch.Tensor:
        """(N, 3, 3) world-frame covariances ``R diag(s)^2 R^T``, square metres."""
        rot = quat_to_matrix(self.quats)
        m = rot * self.scales()[:, None, :]
        return m @ m.transpose(-1, -2)

    def select(self, rows: torch.Tensor) -> GaussianMap:
        """The Gaussians at ``rows`` (bool mask (N,) or int64 indices), detached copies."""
        if rows.dtype == torch.bool:
            rows = rows.nonzero().squeeze(1)
        return GaussianMap(*(getattr(self, f.name).detach().index_select(0, rows) for f in fields(self)))

    def concat(self, other: GaussianMap) -> GaussianMap:
        """This map followed by ``other`` (detached)."""
        return GaussianMap(
            *(torch.cat((getattr(self, f.name).detach(), getattr(other, f.name).detach())) for f in fields(self))
        )

    def detached(self) -> GaussianMap:
        """A copy whose tensors carry no autograd history."""
        return GaussianMap(*(getattr(self, f.name).detach().clone() for f in fields(self)))

    def to(self, device: torch.device | str) -> GaussianMap:
        return GaussianMap(*(getattr(self, f.name).to(device) for f in fields(self)))

    def memory_bytes(self) -> int:
        """Bytes held by the map's tensors (excluding optimiser state)."""
        return sum(getattr(self, f.name).element_size() * getattr(self, f.name).numel() for f in fields(self))
